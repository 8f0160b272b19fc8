"""Runs constraint configurations over scenarios, every episode of a configuration in one
batch, and measures what the paper measures (s, r) plus what it does not (body overlap,
path crossings, planning time)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean, wilson
from constrained_diffusion_ros.evaluation.rollout import RolloutLog, rollout
from constrained_diffusion_ros.evaluation.scenarios import Scenario
from constrained_diffusion_ros.planning.config import ConstraintConfig
from constrained_diffusion_ros.planning.liveness import STANDSTILL_NEAR_PX, standstills
from constrained_diffusion_ros.planning.planners import MixedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.episodes import EpisodeZones

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
    r_body_outside_starts: float | None  # r_body of the episodes not starting inside (None: none)
    ms_per_chunk: float  # planning wall time per episode-chunk (amortised over the batch)
    ms_per_call: float  # wall time of one batched planning call
    batch: int  # episodes per batched call in the steady state
    batch_wall_s: float | None = None  # wall time of the whole batched run the cell came from
    # 95% intervals (intervals.py): bootstrap over episodes for s and r, Wilson for success;
    # None in reports written before they were computed.
    s_ci: list[float] | None = None
    r_ci: list[float] | None = None
    success_ci: list[float] | None = None
    # Liveness (None in reports written before it was measured): executed steps whose setpoint
    # the shield changed, and the mean change (px); steps of standstills at a zone's edge.
    interventions: float | None = None
    intervention_px: float | None = None
    standstill_steps: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def _zones_per_step(scenario: Scenario, n_steps: int) -> list:
    """The zone set in force at each step (one shared object when the scenario is static)."""
    return [scenario.zones_at(t) for t in range(n_steps)]


def cell_metrics(log: RolloutLog, rows: np.ndarray, scenario: Scenario) -> dict[str, object]:
    """s, r, r_body, path crossings and liveness of one scenario's episodes in a batched
    log."""
    commanded, pusher = log.commanded[rows], log.pusher[rows]
    n_steps = commanded.shape[1]
    previous = np.concatenate([pusher[:, :1], commanded[:, :-1]], axis=1)
    inside, body, crossing, near = (np.zeros(commanded.shape[:2], dtype=bool)
                                    for _ in range(4))
    zones = _zones_per_step(scenario, n_steps)
    steps = [np.arange(n_steps)] if not scenario.moving else [[t] for t in range(n_steps)]
    for columns in steps:
        area = zones[columns[0]]
        cmd = torch.from_numpy(commanded[:, columns])
        inside[:, columns] = area.contains(cmd).numpy()
        after = torch.from_numpy(pusher[:, 1:][:, columns])
        clearance = area.signed_distance(after).numpy()
        body[:, columns] = clearance < PUSHT_ROBOT.pusher_radius
        near[:, columns] = clearance < PUSHT_ROBOT.pusher_radius + STANDSTILL_NEAR_PX
        start = torch.from_numpy(previous[:, columns])
        crossing[:, columns] = (area.crosses(start, cmd) & ~area.contains(start)).numpy()
    start = torch.from_numpy(pusher[:, 0])
    started_inside = (zones[0].signed_distance(start) < PUSHT_ROBOT.pusher_radius).numpy()
    outside_starts = body[~started_inside].sum(axis=1)
    best, successes, per_episode_r = log.best_score[rows], log.success[rows], inside.sum(axis=1)
    liveness = {}
    if log.wanted is not None:
        change = np.linalg.norm(commanded - log.wanted[rows], axis=-1)
        changed = change > 1e-6
        moved = np.linalg.norm(np.diff(pusher, axis=1), axis=-1)
        liveness = {"interventions": float(changed.sum(axis=1).mean()),
                    "intervention_px": float(change[changed].mean()) if changed.any() else 0.0,
                    "standstill_steps": float(standstills(moved, near).sum(axis=1).mean())}
    return {
        "s": float(best.mean()),
        "final_score": float(log.final_score[rows].mean()),
        "success_rate": float(successes.mean()),
        "r": float(per_episode_r.mean()),
        "r_body": float(body.sum(axis=1).mean()),
        "path_crossings": float(crossing.sum(axis=1).mean()),
        "starts_inside": int(started_inside.sum()),
        "r_body_outside_starts": (float(outside_starts.mean())
                                  if len(outside_starts) else None),
        # [low, high] lists, as they read back from JSON
        "s_ci": list(bootstrap_mean(best)),
        "r_ci": list(bootstrap_mean(per_episode_r)),
        "success_ci": list(wilson(int(successes.sum()), len(successes))),
        **liveness,
    }


class ScenarioZones:
    """The zone source of a batched evaluation: row b sees the zones of scenario
    `scenario_of_row[b]`, which change every step while that scenario moves."""

    def __init__(self, scenarios: Sequence[Scenario], scenario_of_row: np.ndarray) -> None:
        self.scenarios, self.scenario_of_row = list(scenarios), scenario_of_row
        self.moving = np.array([scenarios[i].moving for i in scenario_of_row])

    def area_at(self, step: int) -> EpisodeZones:
        return EpisodeZones([s.zones_at(step) for s in self.scenarios], self.scenario_of_row)

    def version_at(self, step: int) -> np.ndarray:
        return np.where(self.moving, step, 0)


@dataclass(frozen=True)
class Block:
    """Consecutive rows of a batch: the seeds of one configuration, scored against
    `scenarios`. A configuration that ignores zones plans the same whatever they are, so one
    block of its episodes serves all its scenarios."""

    config: int  # index into the configurations of the batch
    scenarios: tuple[int, ...]  # indices into the scenarios of the batch
    start: int
    stop: int

    @property
    def rows(self) -> np.ndarray:
        return np.arange(self.start, self.stop)


def _layout(configs: Sequence[ConstraintConfig], scenario_lists: Sequence[Sequence[Scenario]],
            scenarios: list[Scenario], n_seeds: int) -> list[Block]:
    blocks: list[Block] = []
    for index, (config, chosen) in enumerate(zip(configs, scenario_lists, strict=True)):
        indices = [scenarios.index(s) for s in chosen]
        groups = [tuple(indices)] if not config.constrains else [(i,) for i in indices]
        for group in groups:
            start = blocks[-1].stop if blocks else 0
            blocks.append(Block(index, group, start, start + n_seeds))
    return blocks


def evaluate_configurations(policy: DiffusionPolicy, configs: Sequence[ConstraintConfig],
                            scenario_lists: Sequence[Sequence[Scenario]],
                            seeds: Sequence[int] = DEFAULT_SEEDS, n_steps: int = 200,
                            noise_seed: int = 0, progress: bool = True, delay: int = 0,
                            handover: str = "sync"
                            ) -> tuple[list[CellResult], RolloutLog, dict[tuple[str, str], int]]:
    """Configurations that share a sampler (one `sampler_key`), each on its scenarios x seeds,
    all as one batch of episodes. Returns the cells, the log and, per (scenario, configuration),
    the log row of its first episode."""
    scenarios = list(dict.fromkeys(s for chosen in scenario_lists for s in chosen))
    blocks = _layout(configs, scenario_lists, scenarios, len(seeds))
    owner = np.concatenate([np.full(b.stop - b.start, b.config) for b in blocks])
    scenario_of_row = np.concatenate([np.full(b.stop - b.start, b.scenarios[0]) for b in blocks])
    planner = MixedPlanner(policy, configs, PUSHT_ROBOT, owner)
    zones = ScenarioZones(scenarios, scenario_of_row)
    generator = torch.Generator().manual_seed(noise_seed)

    started = time.monotonic()
    episode_seeds = [seed for _ in blocks for seed in seeds]
    log = rollout(planner, episode_seeds, n_steps, zones, generator, progress=progress,
                  description=", ".join(c.name for c in configs), delay=delay,
                  handover=handover)
    timing = {
        "ms_per_chunk": 1000 * log.planning_s / max(1, log.planned_chunks),
        "ms_per_call": 1000 * log.planning_s / max(1, log.planner_calls),
        "batch": len(episode_seeds),
        "batch_wall_s": time.monotonic() - started,
    }
    cells, first_rows = [], {}
    for block in blocks:
        config = configs[block.config]
        for index in block.scenarios:
            scenario = scenarios[index]
            metrics = cell_metrics(log, block.rows, scenario)
            cells.append(CellResult(scenario=scenario.name, configuration=config.name,
                                    episodes=len(seeds), **metrics, **timing))
            first_rows[(scenario.name, config.name)] = block.start
    return cells, log, first_rows


def evaluate_configuration(policy: DiffusionPolicy, config: ConstraintConfig,
                           scenarios: Sequence[Scenario], seeds: Sequence[int] = DEFAULT_SEEDS,
                           n_steps: int = 200, noise_seed: int = 0, progress: bool = True
                           ) -> tuple[list[CellResult], RolloutLog]:
    """One configuration on its scenarios x seeds, as one batch."""
    cells, log, _ = evaluate_configurations(policy, [config], [scenarios], seeds, n_steps,
                                            noise_seed, progress)
    return cells, log
