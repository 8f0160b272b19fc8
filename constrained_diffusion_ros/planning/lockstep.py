"""Receding-horizon execution of action chunks in lockstep with the observations: the loop of
the evaluation, the delay study and the policy node's lockstep mode, so they replan alike and
consume the same random numbers. Its rules are the live controller's too (action_queue.py).

The loop asks a planner (`ChunkPlanner`) for chunks and a zone source (`ZoneSource`) for the
zones in force. It replans an episode when its chunk runs out, or when the zones changed since
its plan and the rest of the chunk now lies where the planner keeps waypoints out of (the one
replan rule); the planner's guard has the last word on every setpoint.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from constrained_diffusion_ros.planning.action_queue import (
    ActionQueue,
    ObservationHistory,
    committed_prefix,
)
from constrained_diffusion_ros.planning.planners import ChunkPlanner
from constrained_diffusion_ros.zones.area import RestrictedArea


class ZoneSource(Protocol):
    """The zones in force for a batch of episodes, and a version that changes with them."""

    def area_at(self, step: int) -> RestrictedArea | None:
        """The zones at control step `step` (a batch-aware area, or one area for every
        episode), or None when there are none."""
        ...

    def version_at(self, step: int) -> int | np.ndarray:
        """Equal versions (one, or one per episode) mean equal zones."""
        ...


@dataclass(frozen=True)
class PlanRecord:
    """A planning call: at which step, for which rows, the chunks (R, horizon, 2), its time."""

    step: int
    rows: np.ndarray
    chunks: np.ndarray
    seconds: float


@dataclass
class ExecutionStats:
    planning_s: float = 0.0  # wall time inside the planner
    planned_chunks: int = 0  # episode-chunks planned (a batched call of R rows counts R)
    planner_calls: int = 0


HANDOVERS = ("sync", "async", "async_prefix")


class LockstepLoop:
    """Plans a chunk per episode and executes `n_action_steps` of its waypoints from
    `first_executed` on (the reference's convention), for a batch of episodes.

    With `delay` d > 0 a plan asked for at step t (from t's observation) is ready at t + d, as
    planning takes time on a real robot; `handover` says what happens meanwhile:
      - "sync": the robot waits, holding its last setpoint, and the chunk starts when ready;
      - "async": planning starts `d` steps before the chunk in force runs out, which goes on
        executing; the new chunk's waypoints for steps already past are skipped;
      - "async_prefix": as "async", with the committed waypoints inpainted into the new chunk
        (`CommittedPrefix`, `soft` more drawn toward the old one).
    d = 0 is the lockstep evaluation (and the node in lockstep), whatever the handover.
    """

    def __init__(self, planner: ChunkPlanner, zones: ZoneSource | None = None,
                 generator: torch.Generator | None = None, delay: int = 0,
                 handover: str = "sync", soft: int = 4) -> None:
        if handover not in HANDOVERS:
            raise ValueError(f"handover must be one of {HANDOVERS}, got {handover!r}")
        if not 0 <= delay <= planner.policy_config.n_action_steps:
            raise ValueError(f"delay must be in [0, n_action_steps], got {delay}")
        self.planner, self.zones, self.generator = planner, zones, generator
        self.delay, self.handover, self.soft = delay, handover, soft
        config = planner.policy_config
        self.n_obs_steps, self.first_executed = config.n_obs_steps, config.first_executed
        self.n_action_steps = config.n_action_steps
        self.stats = ExecutionStats()
        self.last_plan: PlanRecord | None = None  # the plan made at the latest `act`, if any
        self.wanted: np.ndarray | None = None  # the latest `act`'s setpoints before the guard
        self.history: ObservationHistory | None = None

    def reset(self, noise_seed: int | None = None) -> None:
        """A new episode: forget the history and the chunks; reseed the noise if asked."""
        self.history = None
        self.planner.reset()
        if noise_seed is not None and self.generator is not None:
            self.generator.manual_seed(noise_seed)

    def act(self, observations: np.ndarray, step: int) -> np.ndarray:
        """(B, obs_dim) observations at control step `step` -> (B, 2) setpoints. After it,
        `handed_over` (B,) says which rows executed the first waypoint of a new chunk."""
        area = self.zones.area_at(step) if self.zones is not None else None
        version = self.zones.version_at(step) if self.zones is not None else 0
        if self.history is None:
            self._start(observations)
        else:
            self.history.push(observations)
        self._install_ready(step)
        lead = 0 if self.handover == "sync" else self.delay
        due = (self.queue.remaining(step) <= lead) & (self.ready_at < 0)
        if not due.all():
            due |= self._zones_entered(area, np.broadcast_to(version, due.shape), step)
        self.last_plan = None
        if due.any():
            self._replan(np.nonzero(due)[0], area, version, step)
            self._install_ready(step)
        if self.last_setpoints is None:  # nothing sent yet: stay put until a plan is in
            self.last_setpoints = self.planner.robot.pusher(self.history.latest).astype(float)
        action, waiting = self.queue.at_or(step, self.last_setpoints)
        chunk = np.where(waiting, -1, self.queue.installs)
        self.handed_over = (chunk != self.executed_id) & ~waiting
        self.executed_id = chunk
        self.wanted = action  # what the plan asked for, before the guard's last word
        # The guard sees the positions as the planner saw them (float32 observations).
        self.last_setpoints = self.planner.guard(area, self.history.latest, action, step)
        return self.last_setpoints

    def _start(self, observations: np.ndarray) -> None:
        batch = len(observations)
        self.history = ObservationHistory(observations, self.n_obs_steps)
        self.queue = ActionQueue(batch, self.n_action_steps)
        self.executed_id = np.full(batch, -1)  # the chunk (install count) executed; -1: held
        self.last_setpoints: np.ndarray | None = None  # the setpoints executed last
        self.planned_version = np.zeros(batch, dtype=np.int64)
        self.ready_at = np.full(batch, -1)  # step at which the pending plan is ready; -1: none
        horizon = self.planner.policy_config.horizon
        self.pending = np.full((batch, horizon - self.first_executed, 2), np.nan)
        self.pending_first = np.zeros(batch, dtype=np.int64)
        self.pending_version = np.zeros(batch, dtype=np.int64)

    def _install_ready(self, step: int) -> None:
        rows = np.nonzero((self.ready_at >= 0) & (self.ready_at <= step))[0]
        if len(rows) == 0:
            return
        self.queue.install(rows, self.pending[rows], self.pending_first[rows], step)
        self.planned_version[rows] = self.pending_version[rows]
        self.ready_at[rows] = -1

    def _zones_entered(self, area: RestrictedArea | None, version: np.ndarray,
                       step: int) -> np.ndarray:
        """The one replan rule: zones changed since the plan, and the rest of the chunk now
        lies where the planner keeps waypoints out of (`violates`)."""
        remaining = self.queue.remaining(step)
        due = np.zeros(len(remaining), dtype=bool)
        rows = np.nonzero((version != self.planned_version) & (remaining > 0))[0]
        if len(rows) == 0:
            return due
        zones = None if area is None else area.select_rows(rows)
        due[rows] = self.queue.rest_refused(rows, step, lambda waypoints: self.planner.violates(
            torch.from_numpy(waypoints), zones, rows).numpy())
        return due

    def _replan(self, rows: np.ndarray, area: RestrictedArea | None,
                version: int | np.ndarray, step: int) -> None:
        zones = None if area is None else area.select_rows(rows)
        prefix = None
        if self.handover == "async_prefix" and self.delay > 0:
            prefix = committed_prefix(self.queue, rows, step, self.delay, self.soft,
                                      self.first_executed)
        started = time.perf_counter()
        observations = self.history.tensor(rows)
        plan = self.planner.plan(observations, zones, rows, self.generator, prefix).numpy()
        seconds = time.perf_counter() - started
        self.stats.planning_s += seconds
        self.stats.planned_chunks += len(rows)
        self.stats.planner_calls += 1
        self.last_plan = PlanRecord(step, rows, plan, seconds)
        self.pending[rows] = plan[:, self.first_executed:]
        self.pending_version[rows] = np.broadcast_to(version, self.ready_at.shape)[rows]
        self.ready_at[rows] = step + self.delay
        if self.handover == "sync":  # the robot waits for the plan, which starts when ready
            self.pending_first[rows] = step + self.delay
            self.queue.clear(rows)
        else:
            self.pending_first[rows] = step
