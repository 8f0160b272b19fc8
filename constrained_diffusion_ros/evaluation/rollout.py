"""Closed-loop rollouts of many simulated episodes at once: observe, act, step, record."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop, ZoneSource
from constrained_diffusion_ros.planning.planners import ChunkPlanner
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from sim_bridge import SUCCESS_THRESHOLD, PushTBatch, score_from_coverage


@dataclass
class RolloutLog:
    """Per-step records of a batch of episodes (arrays are (episodes, steps, ...))."""

    seeds: list[int]
    commanded: np.ndarray  # (E, T, 2) setpoints sent to the simulator
    states: np.ndarray  # (E, T + 1, 5) before each step and after the last
    coverage: np.ndarray  # (E, T) after each step
    executed_chunk: np.ndarray | None = None  # (E, T) which plan each step executed; -1: held
    wanted: np.ndarray | None = None  # (E, T, 2) setpoints the plan asked for, before the guard
    planning_s: float = 0.0  # wall time inside the planner
    planned_chunks: int = 0  # episode-chunks planned (a batched call of R rows counts R)
    planner_calls: int = 0
    zone_offsets: np.ndarray | None = None  # (E, T, 2) px each episode's zones were moved by

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


def rollout(planner: ChunkPlanner, seeds: Sequence[int], n_steps: int = 200,
            zones: ZoneSource | None = None, generator: torch.Generator | None = None,
            progress: bool = False, description: str = "rollout", delay: int = 0,
            handover: str = "sync") -> RolloutLog:
    """Runs every seeded scene for `n_steps` control steps, all episodes in one batch, through
    the chunk loop the policy node runs; plans are ready `delay` steps after they are asked
    for, and `handover` says what executes meanwhile (see `ChunkLoop`). A plug-in zone check
    that fails in use raises ValueError: the node stops its pusher, a rollout stops."""
    sims = PushTBatch(len(seeds))
    states = [sims.reset(list(seeds))]
    loop = ChunkLoop.simulated(planner, zones, generator, delay, handover)
    commanded, coverages, executed_chunk, wanted = [], [], [], []
    with tqdm(total=n_steps, desc=description, unit="step", disable=not progress,
              leave=False) as bar:
        for step in range(n_steps):
            observations = sims.observations()
            if hasattr(zones, "follow"):  # zones that home on the pusher
                zones.follow(step, PUSHT_ROBOT.pusher(observations))
            action = loop.observe(step, observations)
            if loop.zone_check_error is not None:  # offline, a stopped pusher is no result
                raise ValueError(f"{loop.zone_check_error} (step {step}): no figures from it")
            states.append(sims.step(action))
            commanded.append(action)
            wanted.append(loop.rows.wanted)
            executed_chunk.append(loop.rows.executed_id.copy())
            coverages.append(sims.coverage())
            bar.update(1)
    stats = loop.stats
    return RolloutLog(list(seeds), commanded=np.stack(commanded, axis=1),
                      states=np.stack(states, axis=1), coverage=np.stack(coverages, axis=1),
                      executed_chunk=np.stack(executed_chunk, axis=1),
                      wanted=np.stack(wanted, axis=1),
                      planning_s=stats.planning_s, planned_chunks=stats.planned_chunks,
                      planner_calls=stats.planner_calls,
                      zone_offsets=_zone_offsets(zones, n_steps))


def _zone_offsets(zones: ZoneSource | None, n_steps: int) -> np.ndarray | None:
    """(E, T, 2) where a zone source that moves zones per episode had them, step by step."""
    offsets = getattr(zones, "offsets", None)
    if not offsets or any(step not in offsets for step in range(n_steps)):
        return None
    return np.stack([offsets[step] for step in range(n_steps)], axis=1)
