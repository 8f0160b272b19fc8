"""Closed-loop rollouts of many episodes at once: observe, plan a chunk, execute part, replan."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from sim_bridge import SUCCESS_THRESHOLD, PushTBatch, score_from_coverage

# Plans (R, horizon, 2) workspace actions for the episodes `rows` (R of them) from their
# (R, n_obs_steps, obs_dim) observations, at control step `step`.
Planner = Callable[[torch.Tensor, int, np.ndarray], torch.Tensor]
# Which episodes must replan now, from (chunk (B, n, 2), next index (B,), plan step (B,), step):
# e.g. those whose zones changed so that the rest of their chunk would violate them.
ReplanCheck = Callable[[np.ndarray, np.ndarray, np.ndarray, int], np.ndarray]
# The last word on the (B, 2) setpoints about to be executed, from (pusher positions (B, 2),
# setpoints, step): e.g. a shield that keeps the pusher's path out of the zones.
SetpointGuard = Callable[[np.ndarray, np.ndarray, int], np.ndarray]


class ObservationHistory:
    """The last `n_steps` observations per episode; at the start, the first one repeated."""

    def __init__(self, first: np.ndarray, n_steps: int) -> None:
        self.frames = np.repeat(np.asarray(first, dtype=np.float32)[:, None], n_steps, axis=1)

    def push(self, observation: np.ndarray) -> None:
        self.frames = np.concatenate([self.frames[:, 1:], observation[:, None]], axis=1)

    def tensor(self, rows: np.ndarray | None = None) -> torch.Tensor:
        frames = self.frames if rows is None else self.frames[rows]
        return torch.from_numpy(frames.astype(np.float32))


@dataclass
class RolloutLog:
    """Per-step records of a batch of episodes (arrays are (episodes, steps, ...))."""

    seeds: list[int]
    commanded: np.ndarray  # (E, T, 2) setpoints sent to the simulator
    states: np.ndarray  # (E, T + 1, 5) before each step and after the last
    coverage: np.ndarray  # (E, T) after each step
    planning_s: float = 0.0  # wall time inside the planner
    planned_chunks: int = 0  # episode-chunks planned (a batched call of R rows counts R)
    planner_calls: int = 0

    @property
    def scores(self) -> np.ndarray:
        return score_from_coverage(self.coverage)

    @property
    def pusher(self) -> np.ndarray:
        return self.states[:, :, :2]

    @property
    def best_score(self) -> np.ndarray:
        return self.scores.max(axis=1)

    @property
    def final_score(self) -> np.ndarray:
        return self.scores[:, -1]

    @property
    def success(self) -> np.ndarray:
        return (self.coverage > SUCCESS_THRESHOLD).any(axis=1)


class ChunkExecutor:
    """Receding-horizon execution for a batch of episodes: plan a chunk, execute
    `n_action_steps` of its waypoints from `first_executed` on (the reference's convention),
    replan when they run out or when `replan_check` says so; `guard` has the last word on each
    setpoint. The evaluation and the policy node both drive this, so they replan alike and
    consume the same random numbers."""

    def __init__(self, planner: Planner, n_obs_steps: int = 2, first_executed: int = 1,
                 n_action_steps: int = 8, replan_check: ReplanCheck | None = None,
                 guard: SetpointGuard | None = None) -> None:
        self.planner, self.replan_check, self.guard = planner, replan_check, guard
        self.n_obs_steps, self.first_executed = n_obs_steps, first_executed
        self.n_action_steps = n_action_steps
        self.history: ObservationHistory | None = None
        self.planning_s, self.planned_chunks, self.planner_calls = 0.0, 0, 0
        self.last_plan: tuple[int, np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self.history = None

    def act(self, observations: np.ndarray, step: int) -> np.ndarray:
        """(B, obs_dim) observations at control step `step` -> (B, 2) setpoints."""
        if self.history is None:
            batch = len(observations)
            self.history = ObservationHistory(observations, self.n_obs_steps)
            self.chunk = np.zeros((batch, self.n_action_steps, 2))
            self.next_index = np.full(batch, self.n_action_steps)
            self.plan_step = np.zeros(batch, dtype=int)
        else:
            self.history.push(observations)
        due = self.next_index >= self.n_action_steps
        if self.replan_check is not None and not due.all():
            due |= self.replan_check(self.chunk, self.next_index, self.plan_step, step)
        self.last_plan = None
        if due.any():
            rows = np.nonzero(due)[0]
            started = time.perf_counter()
            plan = self.planner(self.history.tensor(rows), step, rows).numpy()
            self.planning_s += time.perf_counter() - started
            self.planned_chunks += len(rows)
            self.planner_calls += 1
            self.last_plan = (step, rows, plan)
            first = self.first_executed
            self.chunk[rows] = plan[:, first: first + self.n_action_steps]
            self.next_index[rows], self.plan_step[rows] = 0, step
        action = self.chunk[np.arange(len(self.chunk)), self.next_index]
        self.next_index += 1
        if self.guard is not None:  # positions as the planner saw them (float32)
            action = self.guard(self.history.frames[:, -1, -2:].astype(float), action, step)
        return action


def rollout(planner: Planner, seeds: Sequence[int], n_steps: int = 200, n_obs_steps: int = 2,
            first_executed: int = 1, n_action_steps: int = 8,
            replan_check: ReplanCheck | None = None, guard: SetpointGuard | None = None,
            progress: bool = False, description: str = "rollout") -> RolloutLog:
    """Runs every seeded scene for `n_steps` control steps, all episodes in one batch."""
    sims = PushTBatch(len(seeds))
    states = [sims.reset(list(seeds))]
    executor = ChunkExecutor(planner, n_obs_steps, first_executed, n_action_steps, replan_check,
                             guard)
    commanded, coverages = [], []
    with tqdm(total=n_steps, desc=description, unit="step", disable=not progress,
              leave=False) as bar:
        for step in range(n_steps):
            action = executor.act(sims.observations(), step)
            states.append(sims.step(action))
            commanded.append(action)
            coverages.append(sims.coverage())
            bar.update(1)
    return RolloutLog(list(seeds), commanded=np.stack(commanded, axis=1),
                      states=np.stack(states, axis=1), coverage=np.stack(coverages, axis=1),
                      planning_s=executor.planning_s, planned_chunks=executor.planned_chunks,
                      planner_calls=executor.planner_calls)
