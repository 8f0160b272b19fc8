"""Receding-horizon execution of action chunks: the runtime heart shared by the policy node and
the evaluation, so both replan alike and consume the same random numbers.

The executor asks a planner (`ChunkPlanner`) for chunks and a zone source (`ZoneSource`) for the
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


class ObservationHistory:
    """The last `n_steps` observations per episode; at the start, the first one repeated."""

    def __init__(self, first: np.ndarray, n_steps: int) -> None:
        self.frames = np.repeat(np.asarray(first, dtype=np.float32)[:, None], n_steps, axis=1)

    def push(self, observation: np.ndarray) -> None:
        self.frames = np.concatenate([self.frames[:, 1:], observation[:, None]], axis=1)

    def tensor(self, rows: np.ndarray | None = None) -> torch.Tensor:
        frames = self.frames if rows is None else self.frames[rows]
        return torch.from_numpy(frames.astype(np.float32))

    @property
    def latest(self) -> np.ndarray:
        """(B, obs_dim) the observations of the current step."""
        return self.frames[:, -1]


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


class ChunkExecutor:
    """Plans a chunk per episode and executes `n_action_steps` of its waypoints from
    `first_executed` on (the reference's convention), for a batch of episodes."""

    def __init__(self, planner: ChunkPlanner, zones: ZoneSource | None = None,
                 generator: torch.Generator | None = None) -> None:
        self.planner, self.zones, self.generator = planner, zones, generator
        config = planner.policy_config
        self.n_obs_steps, self.first_executed = config.n_obs_steps, config.first_executed
        self.n_action_steps = config.n_action_steps
        self.stats = ExecutionStats()
        self.last_plan: PlanRecord | None = None  # the plan made at the latest `act`, if any
        self.history: ObservationHistory | None = None

    def reset(self, noise_seed: int | None = None) -> None:
        """A new episode: forget the history and the chunks; reseed the noise if asked."""
        self.history = None
        self.planner.reset()
        if noise_seed is not None and self.generator is not None:
            self.generator.manual_seed(noise_seed)

    def act(self, observations: np.ndarray, step: int) -> np.ndarray:
        """(B, obs_dim) observations at control step `step` -> (B, 2) setpoints."""
        area = self.zones.area_at(step) if self.zones is not None else None
        version = self.zones.version_at(step) if self.zones is not None else 0
        if self.history is None:
            batch = len(observations)
            self.history = ObservationHistory(observations, self.n_obs_steps)
            self.chunk = np.zeros((batch, self.n_action_steps, 2))
            self.next_index = np.full(batch, self.n_action_steps)
            self.planned_version = np.zeros(batch, dtype=np.int64)
        else:
            self.history.push(observations)
        due = self.next_index >= self.n_action_steps
        if not due.all():
            due |= self._zones_entered(area, np.broadcast_to(version, due.shape))
        self.last_plan = None
        if due.any():
            self._replan(np.nonzero(due)[0], area, version, step)
        action = self.chunk[np.arange(len(self.chunk)), self.next_index]
        self.next_index += 1
        # The guard sees the positions as the planner saw them (float32 observations).
        return self.planner.guard(area, self.history.latest, action, step)

    def _zones_entered(self, area: RestrictedArea | None, version: np.ndarray) -> np.ndarray:
        """The one replan rule: zones changed since the plan, and the rest of the chunk now
        lies where the planner keeps waypoints out of."""
        due = np.zeros(len(self.chunk), dtype=bool)
        rows = np.nonzero((version != self.planned_version)
                          & (self.next_index < self.n_action_steps))[0]
        if area is None or len(rows) == 0:
            return due
        waypoints = torch.from_numpy(self.chunk[rows])
        inside = self.planner.violates(waypoints, area.select_rows(rows), rows).numpy()
        remaining = np.arange(self.n_action_steps)[None] >= self.next_index[rows, None]
        due[rows] = (inside & remaining).any(axis=1)
        return due

    def _replan(self, rows: np.ndarray, area: RestrictedArea | None,
                version: int | np.ndarray, step: int) -> None:
        zones = None if area is None else area.select_rows(rows)
        started = time.perf_counter()
        plan = self.planner.plan(self.history.tensor(rows), zones, rows, self.generator).numpy()
        seconds = time.perf_counter() - started
        self.stats.planning_s += seconds
        self.stats.planned_chunks += len(rows)
        self.stats.planner_calls += 1
        self.last_plan = PlanRecord(step, rows, plan, seconds)
        first = self.first_executed
        self.chunk[rows] = plan[:, first: first + self.n_action_steps]
        self.next_index[rows] = 0
        self.planned_version[rows] = np.broadcast_to(version, self.next_index.shape)[rows]
