"""Runs constraint configurations over scenarios, every episode of a configuration in one
batch, and measures what the paper measures (s, r) plus what it does not (body overlap,
path crossings, planning time)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from constrained_diffusion_ros.evaluation.rollout import RolloutLog, rollout
from constrained_diffusion_ros.evaluation.scenarios import Scenario
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.sampling.constraints import ConstrainedPlanner, ConstraintConfig
from constrained_diffusion_ros.zones.episodes import EpisodeZones
from sim_bridge import AGENT_RADIUS

DEFAULT_SEEDS = tuple(range(100000, 100025))


@dataclass
class CellResult:
    """One (scenario, configuration) cell: means over its episodes."""

    scenario: str
    configuration: str
    episodes: int
    s: float  # mean of each episode's best score (the paper's s)
    final_score: float
    success_rate: float
    r: float  # executed steps whose commanded position is inside a zone (the paper's r)
    r_body: float  # steps whose pusher disc overlaps a zone
    path_crossings: float  # setpoint-to-setpoint segments that enter a zone from outside
    starts_inside: int  # episodes whose pusher disc overlaps a zone at the start
    ms_per_chunk: float  # planning wall time per episode-chunk (amortised over the batch)
    ms_per_call: float  # wall time of one batched planning call
    batch: int  # episodes per batched call in the steady state

    def to_dict(self) -> dict:
        return asdict(self)


def _zones_per_step(scenario: Scenario, n_steps: int) -> list:
    """The zone set in force at each step (one shared object when the scenario is static)."""
    return [scenario.zones_at(t) for t in range(n_steps)]


def cell_metrics(log: RolloutLog, rows: np.ndarray, scenario: Scenario) -> dict[str, float]:
    """s, r, r_body and path crossings of one scenario's episodes in a batched log."""
    commanded, pusher = log.commanded[rows], log.pusher[rows]
    n_steps = commanded.shape[1]
    previous = np.concatenate([pusher[:, :1], commanded[:, :-1]], axis=1)
    inside, body, crossing = (np.zeros(commanded.shape[:2], dtype=bool) for _ in range(3))
    zones = _zones_per_step(scenario, n_steps)
    steps = [np.arange(n_steps)] if not scenario.moving else [[t] for t in range(n_steps)]
    for columns in steps:
        area = zones[columns[0]]
        cmd = torch.from_numpy(commanded[:, columns])
        inside[:, columns] = area.contains(cmd).numpy()
        after = torch.from_numpy(pusher[:, 1:][:, columns])
        body[:, columns] = (area.signed_distance(after) < AGENT_RADIUS).numpy()
        start = torch.from_numpy(previous[:, columns])
        crossing[:, columns] = (area.crosses(start, cmd) & ~area.contains(start)).numpy()
    start = torch.from_numpy(pusher[:, 0])
    starts_inside = int((zones[0].signed_distance(start) < AGENT_RADIUS).sum())
    return {
        "s": float(log.best_score[rows].mean()),
        "final_score": float(log.final_score[rows].mean()),
        "success_rate": float(log.success[rows].mean()),
        "r": float(inside.sum(axis=1).mean()),
        "r_body": float(body.sum(axis=1).mean()),
        "path_crossings": float(crossing.sum(axis=1).mean()),
        "starts_inside": starts_inside,
    }


def evaluate_configuration(policy: DiffusionPolicy, config: ConstraintConfig,
                           scenarios: Sequence[Scenario], seeds: Sequence[int] = DEFAULT_SEEDS,
                           n_steps: int = 200, noise_seed: int = 0, progress: bool = True
                           ) -> tuple[list[CellResult], RolloutLog]:
    """All scenarios x seeds of one configuration as one batch of episodes."""
    planner = ConstrainedPlanner(policy, config)
    generator = torch.Generator().manual_seed(noise_seed)
    assignment = np.repeat(np.arange(len(scenarios)), len(seeds))
    moving = np.array([scenarios[a].moving for a in assignment])
    horizons = policy.config

    def area_at(step: int, rows: np.ndarray) -> EpisodeZones:
        return EpisodeZones([s.zones_at(step) for s in scenarios], assignment[rows])

    def plan(obs: torch.Tensor, step: int, rows: np.ndarray) -> torch.Tensor:
        return planner.plan(obs, area_at(step, rows) if config.constrains else None, generator)

    def replan_check(chunk: np.ndarray, next_index: np.ndarray, plan_step: np.ndarray,
                     step: int) -> np.ndarray:
        """Moving zones: replan where the rest of the chunk now lies in the (effective) zone."""
        due = np.zeros(len(chunk), dtype=bool)
        rows = np.nonzero(moving & (plan_step < step) & (next_index < chunk.shape[1]))[0]
        if not config.constrains or len(rows) == 0:
            return due
        area = planner.effective_area(area_at(step, rows))
        inside = area.contains(torch.from_numpy(chunk[rows])).numpy()
        remaining = np.arange(chunk.shape[1])[None] >= next_index[rows, None]
        due[rows] = (inside & remaining).any(axis=1)
        return due

    episode_seeds = [seed for _ in scenarios for seed in seeds]
    log = rollout(plan, episode_seeds, n_steps, horizons.n_obs_steps, horizons.first_executed,
                  horizons.n_action_steps, replan_check if moving.any() else None,
                  progress=progress, description=config.name)
    timing = {
        "ms_per_chunk": 1000 * log.planning_s / max(1, log.planned_chunks),
        "ms_per_call": 1000 * log.planning_s / max(1, log.planner_calls),
        "batch": len(episode_seeds),
    }
    cells = [
        CellResult(scenario=scenario.name, configuration=config.name, episodes=len(seeds),
                   **cell_metrics(log, np.nonzero(assignment == index)[0], scenario), **timing)
        for index, scenario in enumerate(scenarios)
    ]
    return cells, log
