"""Closed-loop rollouts of many episodes at once: observe, plan a chunk, execute part, replan."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

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
    plans: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)

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


def rollout(planner: Planner, seeds: Sequence[int], n_steps: int = 200, n_obs_steps: int = 2,
            first_executed: int = 1, n_action_steps: int = 8,
            replan_check: ReplanCheck | None = None, progress: bool = False,
            description: str = "rollout", keep_plans: bool = False) -> RolloutLog:
    """Runs every seeded scene for `n_steps` control steps, all episodes in one batch.

    Each episode executes `n_action_steps` waypoints of a chunk, from `first_executed` on (the
    reference's convention), then replans; `replan_check` may cut a chunk short.
    """
    batch = len(seeds)
    sims = PushTBatch(batch)
    states = [sims.reset(list(seeds))]
    history = ObservationHistory(sims.observations(), n_obs_steps)
    chunk = np.zeros((batch, n_action_steps, 2))
    next_index = np.full(batch, n_action_steps)
    plan_step = np.zeros(batch, dtype=int)
    log = RolloutLog(list(seeds), np.empty(0), np.empty(0), np.empty(0))
    commanded, coverages = [], []
    every = np.arange(batch)
    with tqdm(total=n_steps, desc=description, unit="step", disable=not progress,
              leave=False) as bar:
        for step in range(n_steps):
            due = next_index >= n_action_steps
            if replan_check is not None and not due.all():
                due |= replan_check(chunk, next_index, plan_step, step)
            if due.any():
                rows = np.nonzero(due)[0]
                started = time.perf_counter()
                plan = planner(history.tensor(rows), step, rows).numpy()
                log.planning_s += time.perf_counter() - started
                log.planned_chunks += len(rows)
                log.planner_calls += 1
                if keep_plans:
                    log.plans.append((step, rows, plan))
                chunk[rows] = plan[:, first_executed: first_executed + n_action_steps]
                next_index[rows], plan_step[rows] = 0, step
            action = chunk[every, next_index]
            next_index += 1
            states.append(sims.step(action))
            history.push(sims.observations())
            commanded.append(action)
            coverages.append(sims.coverage())
            bar.update(1)
    log.states = np.stack(states, axis=1)
    log.commanded = np.stack(commanded, axis=1)
    log.coverage = np.stack(coverages, axis=1)
    return log
