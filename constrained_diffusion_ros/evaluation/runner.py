"""Runs constraint configurations over scenarios, in units of fixed composition (a sampler
group's configurations on their scenarios for a block of seeds, one batch each) that run here
or as Ray tasks (distributed.py) with the same episodes, and measures what the paper measures
(s, r) plus what it does not (body overlap, path crossings, planning time)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean, wilson
from constrained_diffusion_ros.evaluation.rollout import RolloutLog, rollout
from constrained_diffusion_ros.evaluation.scenarios import Scenario
from constrained_diffusion_ros.evaluation.zone_paths import ZoneMover
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.liveness import STANDSTILL_NEAR_PX, standstills
from constrained_diffusion_ros.planning.planners import MixedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.area import RestrictedArea, Translated
from constrained_diffusion_ros.zones.episodes import EpisodeZones
from constrained_diffusion_ros.zones.geometry import ZoneSet
from constrained_diffusion_ros.zones.motion import (
    DEFAULT_SPEED_BOUND,
    MOVED_PX,
    MovingZones,
    assumed_speeds,
)

DEFAULT_SEEDS = tuple(range(100000, 100025))
# Seeds per unit of work (`Unit`): the default study is one unit per sampler group, as it was
# one batch before units; more seeds make more units, each its own batch and noise.
DEFAULT_UNIT_SIZE = 25
# Where a contact is checked for being unavoidable: the pusher's one-step reach sampled on
# rings at these fractions of it, in CONTACT_DIRECTIONS directions, and its centre.
CONTACT_RINGS = (0.25, 0.5, 0.75, 1.0)
CONTACT_DIRECTIONS = 32


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
    # Moving zones (None for static ones): steps whose disc overlaps a zone, per episode;
    # those counted in all episodes that a setpoint could have avoided and those it could not
    # (`unavoidable`, or a disc that started in the zone and is not yet out); the least
    # disc-to-zone gap over the episodes (px, negative: overlap) and its mean per episode.
    contact_steps: float | None = None
    avoidable_contact_steps: int | None = None
    unavoidable_contact_steps: int | None = None
    min_separation: float | None = None
    mean_min_separation: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def _zones_per_step(scenario: Scenario, n_steps: int, offsets: np.ndarray | None = None
                    ) -> list:
    """The zone set in force at each step (one shared object when the scenario is static);
    with `offsets` (E, T, 2), each episode's zones moved by its own (a homing hand)."""
    if offsets is not None and scenario.area is None:
        drawn = scenario.zones_at(0)
        return [Translated(drawn, torch.from_numpy(offsets[:, t])) for t in range(n_steps)]
    return [scenario.zones_at(t) for t in range(n_steps)]


def unavoidable(pusher_before: np.ndarray, zones_after: RestrictedArea) -> np.ndarray:
    """Bool (N,): contacts that no setpoint could have avoided: every point the pusher could
    reach in one control step from where it was (`RobotModel.reach`, within the workspace,
    sampled on rings) leaves its disc overlapping the zones after it. Sampled, so it may miss
    a small free pocket; it looks one step back only, so a contact it calls unavoidable may
    have been avoidable earlier: the cause it names is the step before."""
    robot = PUSHT_ROBOT
    reach = robot.reach(1.0 / robot.control_hz)
    angles = np.linspace(0, 2 * np.pi, CONTACT_DIRECTIONS, endpoint=False)
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    offsets = np.concatenate([np.zeros((1, 2))] + [f * reach * unit for f in CONTACT_RINGS])
    points = pusher_before[:, None] + offsets[None]  # (N, P, 2)
    x_min, y_min, x_max, y_max = robot.workspace
    points = np.clip(points, (x_min, y_min), (x_max, y_max))
    clearance = zones_after.signed_distance(torch.from_numpy(points)).numpy()
    return (clearance < robot.pusher_radius).all(axis=1)


def cell_metrics(log: RolloutLog, rows: np.ndarray, scenario: Scenario) -> dict[str, object]:
    """s, r, r_body, path crossings and liveness of one scenario's episodes in a batched
    log; for moving zones also contact steps (avoidable or not) and the least separation."""
    commanded, pusher = log.commanded[rows], log.pusher[rows]
    n_steps = commanded.shape[1]
    previous = np.concatenate([pusher[:, :1], commanded[:, :-1]], axis=1)
    inside, body, crossing, near = (np.zeros(commanded.shape[:2], dtype=bool)
                                    for _ in range(4))
    # Where a homing zone went is the rollout's; other zones go where their path says.
    offsets = log.zone_offsets[rows] if scenario.homes and log.zone_offsets is not None \
        else None
    zones = _zones_per_step(scenario, n_steps, offsets)
    steps = [np.arange(n_steps)] if not scenario.moving else [[t] for t in range(n_steps)]
    gap = np.full(commanded.shape[:2], np.inf)  # disc to zones after each step (px)
    for columns in steps:
        area = zones[columns[0]]
        cmd = torch.from_numpy(commanded[:, columns])
        inside[:, columns] = area.contains(cmd).numpy()
        after = torch.from_numpy(pusher[:, 1:][:, columns])
        clearance = area.signed_distance(after).numpy()
        if scenario.moving:  # the disc after step t meets the zones as they are at t + 1
            later = zones[min(columns[0] + 1, n_steps - 1)]
            clearance = np.minimum(clearance, later.signed_distance(after).numpy())
        gap[:, columns] = clearance - PUSHT_ROBOT.pusher_radius
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
    motion = {}
    if scenario.moving:
        # A disc that starts in a zone cannot leave it at once: its first contact steps, until
        # it is first out, are unavoidable (the zone was put on it).
        forced = started_inside[:, None] & (np.cumsum(~body, axis=1) == 0)
        for step in np.flatnonzero((body & ~forced).any(axis=0)):  # the episodes at once
            episodes = np.flatnonzero(body[:, step] & ~forced[:, step])
            later = zones[min(step + 1, n_steps - 1)]
            forced[episodes, step] = unavoidable(
                pusher[episodes, step], later.select_rows(torch.from_numpy(episodes)))
        least = gap.min(axis=1)
        motion = {"contact_steps": float(body.sum(axis=1).mean()),
                  "avoidable_contact_steps": int((body & ~forced).sum()),
                  "unavoidable_contact_steps": int(forced.sum()),
                  "min_separation": float(least.min()),
                  "mean_min_separation": float(least.mean())}
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
        **motion,
    }


class ScenarioZones:
    """The zone source of a batched evaluation: row b sees the zones of scenario
    `scenario_of_row[b]`, which change every step while that scenario moves (a homing one
    differently in each row: `follow` tells it the pushers). Moving zones come as
    `MovingZones`, each assumed able to move as a node assumes of live zones updated at the
    control rate (`zones.motion`); `offsets` keeps where each row's zones were. With `late`,
    moving zones are shown `late` control steps after they were where they are shown, aged by as
    much (a tracker and a node behind; scripts/stress_late_zones.py)."""

    def __init__(self, scenarios: Sequence[Scenario], scenario_of_row: np.ndarray,
                 speed_bound: float = DEFAULT_SPEED_BOUND, late: int = 0) -> None:
        self.scenarios, self.scenario_of_row = list(scenarios), scenario_of_row
        self.speed_bound, self.late = speed_bound, late
        self.moving = np.array([scenarios[i].moving for i in scenario_of_row])
        self.rows = [np.flatnonzero(scenario_of_row == i) for i in range(len(scenarios))]
        self.movers = {i: ZoneMover(s.motion, s.centroid, len(self.rows[i]))
                       for i, s in enumerate(self.scenarios) if s.moving and s.area is None}
        self.offsets: dict[int, np.ndarray] = {}  # step -> (B, 2) each row's zones moved by
        self.moved = np.zeros(len(scenario_of_row), dtype=bool)  # seen moving so far
        self.fastest = np.zeros(len(scenario_of_row))  # px/s, between two steps so far
        self.speeds: dict[int, np.ndarray] = {}  # step -> (B,) px/s assumed as of that step
        self.pusher: np.ndarray | None = None

    def follow(self, step: int, pusher: np.ndarray) -> None:
        """The pushers (B, 2) at control step `step`, before it is planned: where homing
        zones head."""
        self.pusher = np.asarray(pusher, dtype=float)
        self.offsets_at(step)

    def offsets_at(self, step: int) -> np.ndarray:
        """(B, 2) px each row's zones are moved by at `step` (steps in order)."""
        if step not in self.offsets:
            offsets = np.zeros((len(self.scenario_of_row), 2))
            for index, mover in self.movers.items():
                rows = self.rows[index]
                offsets[rows] = mover.at(step, None if self.pusher is None
                                         else self.pusher[rows])
            if step - 1 in self.offsets:  # updates at the control rate, as a tracker's
                shift = np.linalg.norm(offsets - self.offsets[step - 1], axis=-1)
                self.moved |= shift > MOVED_PX
                self.fastest = np.where(self.moved, np.maximum(
                    self.fastest, shift * PUSHT_ROBOT.control_hz), 0.0)
            elif step == 0:
                self.moved[:], self.fastest[:] = False, 0.0
            self.offsets[step] = offsets
            self.speeds[step] = assumed_speeds(self.moved, self.fastest, self.speed_bound)
        return self.offsets[step]

    def area_at(self, step: int) -> RestrictedArea:
        if not self.movers:
            return EpisodeZones([s.zones_at(step) for s in self.scenarios], self.scenario_of_row)
        self.offsets_at(step)
        seen = max(0, step - self.late)  # the moment the zones shown were there
        offsets = torch.from_numpy(self.offsets[seen])
        areas, still, moving = [], [], []
        for index, scenario in enumerate(self.scenarios):
            if index in self.movers:
                areas.append(Translated(scenario.zones_at(0), offsets[self.rows[index]]))
                still.append(ZoneSet.empty())
                moving.append(areas[-1])
            else:
                areas.append(scenario.zones_at(step))
                still.append(areas[-1])
                moving.append(ZoneSet.empty())
        speed = torch.from_numpy(self.speeds[seen])
        # measured as a tracker at the control rate would: the last step's displacement
        velocity = (self.offsets[seen] - self.offsets.get(seen - 1, self.offsets[seen])) \
            * PUSHT_ROBOT.control_hz
        area, still, moving = (EpisodeZones(parts, self.scenario_of_row)
                               for parts in (areas, still, moving))
        return MovingZones(area, still, moving, speed, (step - seen) / PUSHT_ROBOT.control_hz,
                           PUSHT_ROBOT.reaction_s, drift=[(moving, torch.from_numpy(velocity))])

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
        # A zone that homes on the pusher goes where that block's pushers go: its own block.
        shared = tuple(i for i in indices if not scenarios[i].homes)
        groups = ([shared] if shared else []) + [(i,) for i in indices if scenarios[i].homes] \
            if not config.constrains else [(i,) for i in indices]
        for group in groups:
            start = blocks[-1].stop if blocks else 0
            blocks.append(Block(index, group, start, start + n_seeds))
    return blocks


@dataclass(frozen=True)
class Unit:
    """A fixed piece of a study: the configurations of one sampler group, each on its
    scenarios, for a block of consecutive seeds, run as one batch with its own noise seed.
    Units depend on the study's seeds, unit size and noise seed only, never on how many
    workers run them, so any worker count runs the same batches and gives the same episodes."""

    group: int  # index of the sampler group in the study
    seeds: tuple[int, ...]
    noise_seed: int

    @property
    def key(self) -> tuple[int, int]:
        """What the results are assembled by: a retried unit replaces, never adds."""
        return self.group, self.seeds[0]


@dataclass
class UnitRun:
    """What a unit brings back: its batch's log and the wall time it took."""

    log: RolloutLog
    wall_s: float


def study_units(n_groups: int, seeds: Sequence[int], unit_size: int, noise_seed: int = 0
                ) -> list[Unit]:
    """Each group's `seeds` in consecutive blocks of `unit_size` (the last may be shorter),
    group after group. A unit's noise seed is `noise_seed` plus how far into the seeds its own
    start: the first unit draws the study's noise seed, so a study of one unit per group (up
    to `unit_size` seeds) draws the noise it drew as one batch, as a trial of one seed with the
    node's `noise_seed` does."""
    if unit_size < 1:
        raise ValueError(f"a unit holds at least one seed, not {unit_size}")
    return [Unit(group, tuple(seeds[start:start + unit_size]), noise_seed + start)
            for group in range(n_groups) for start in range(0, len(seeds), unit_size)]


def run_unit(policy: DiffusionPolicy, configs: Sequence[ConstraintConfig],
             scenario_lists: Sequence[Sequence[Scenario]], seeds: Sequence[int],
             n_steps: int = 200, noise_seed: int = 0, progress: bool = False, delay: int = 0,
             handover: str = "sync") -> UnitRun:
    """One unit: configurations that share a sampler (one `sampler_key`), each on its
    scenarios x `seeds`, as one batch of episodes laid out as `_layout` says, with a noise
    generator seeded by `noise_seed` (the unit's, `study_units`)."""
    scenarios = list(dict.fromkeys(s for chosen in scenario_lists for s in chosen))
    blocks = _layout(configs, scenario_lists, scenarios, len(seeds))
    owner = np.concatenate([np.full(b.stop - b.start, b.config) for b in blocks])
    scenario_of_row = np.concatenate([np.full(b.stop - b.start, b.scenarios[0]) for b in blocks])
    planner = MixedPlanner(policy, configs, PUSHT_ROBOT, owner)
    zones = ScenarioZones(scenarios, scenario_of_row)
    generator = torch.Generator().manual_seed(noise_seed)
    started = time.monotonic()
    log = rollout(planner, [seed for _ in blocks for seed in seeds], n_steps, zones, generator,
                  progress=progress, description=", ".join(c.name for c in configs),
                  delay=delay, handover=handover)
    return UnitRun(log, time.monotonic() - started)


def merge_logs(logs: Sequence[RolloutLog], n_blocks: int) -> RolloutLog:
    """The logs of a group's units, in seed order, as one log laid out as a single batch of
    all the seeds would be: block by block, each block's seeds in order. Planning times and
    counts add up."""
    if len(logs) == 1:
        return logs[0]

    def rows(log: RolloutLog, block: int) -> slice:
        size = len(log.seeds) // n_blocks
        return slice(block * size, (block + 1) * size)

    def joined(field: str) -> np.ndarray | None:
        arrays = [getattr(log, field) for log in logs]
        if any(array is None for array in arrays):
            return None
        return np.concatenate([array[rows(log, block)] for block in range(n_blocks)
                               for log, array in zip(logs, arrays, strict=True)])

    return RolloutLog(
        [seed for block in range(n_blocks) for log in logs for seed in log.seeds[rows(log, block)]],
        commanded=joined("commanded"), states=joined("states"), coverage=joined("coverage"),
        executed_chunk=joined("executed_chunk"), wanted=joined("wanted"),
        planning_s=sum(log.planning_s for log in logs),
        planned_chunks=sum(log.planned_chunks for log in logs),
        planner_calls=sum(log.planner_calls for log in logs),
        zone_offsets=joined("zone_offsets"))


def assemble(configs: Sequence[ConstraintConfig], scenario_lists: Sequence[Sequence[Scenario]],
             runs: Sequence[UnitRun]
             ) -> tuple[list[CellResult], RolloutLog, dict[tuple[str, str], int]]:
    """The cells of a sampler group from its units' runs (in seed order), measured on their
    merged log exactly as on one batch. The timing fields: planning time per episode-chunk and
    per call over all the units, the largest unit's batch, and the units' wall times added
    (the compute the group cost, wherever it ran)."""
    scenarios = list(dict.fromkeys(s for chosen in scenario_lists for s in chosen))
    n_blocks = episodes_per_seed(configs, scenario_lists)
    n_seeds = sum(len(run.log.seeds) for run in runs) // n_blocks
    blocks = _layout(configs, scenario_lists, scenarios, n_seeds)
    log = merge_logs([run.log for run in runs], len(blocks))
    timing = {
        "ms_per_chunk": 1000 * log.planning_s / max(1, log.planned_chunks),
        "ms_per_call": 1000 * log.planning_s / max(1, log.planner_calls),
        "batch": max(len(run.log.seeds) for run in runs),
        "batch_wall_s": sum(run.wall_s for run in runs),
    }
    cells, first_rows = [], {}
    for block in blocks:
        config = configs[block.config]
        for index in block.scenarios:
            scenario = scenarios[index]
            metrics = cell_metrics(log, block.rows, scenario)
            cells.append(CellResult(scenario=scenario.name, configuration=config.name,
                                    episodes=n_seeds, **metrics, **timing))
            first_rows[(scenario.name, config.name)] = block.start
    return cells, log, first_rows


def episodes_per_seed(configs: Sequence[ConstraintConfig],
                      scenario_lists: Sequence[Sequence[Scenario]]) -> int:
    """Episodes a sampler group runs per seed: one per block of its batch (a configuration
    that ignores the zones runs a seed once for all its scenarios)."""
    scenarios = list(dict.fromkeys(s for chosen in scenario_lists for s in chosen))
    return len(_layout(configs, scenario_lists, scenarios, 1))


def evaluate_configurations(policy: DiffusionPolicy, configs: Sequence[ConstraintConfig],
                            scenario_lists: Sequence[Sequence[Scenario]],
                            seeds: Sequence[int] = DEFAULT_SEEDS, n_steps: int = 200,
                            noise_seed: int = 0, progress: bool = True, delay: int = 0,
                            handover: str = "sync", unit_size: int = DEFAULT_UNIT_SIZE
                            ) -> tuple[list[CellResult], RolloutLog, dict[tuple[str, str], int]]:
    """Configurations that share a sampler (one `sampler_key`), each on its scenarios x seeds,
    run here unit after unit (`unit_size` seeds each, `Unit`). Returns the cells, the merged
    log and, per (scenario, configuration), the log row of its first episode."""
    runs = [run_unit(policy, configs, scenario_lists, unit.seeds, n_steps, unit.noise_seed,
                     progress, delay, handover)
            for unit in study_units(1, seeds, unit_size, noise_seed)]
    return assemble(configs, scenario_lists, runs)


def evaluate_configuration(policy: DiffusionPolicy, config: ConstraintConfig,
                           scenarios: Sequence[Scenario], seeds: Sequence[int] = DEFAULT_SEEDS,
                           n_steps: int = 200, noise_seed: int = 0, progress: bool = True
                           ) -> tuple[list[CellResult], RolloutLog]:
    """One configuration on its scenarios x seeds, as one batch."""
    cells, log, _ = evaluate_configurations(policy, [config], [scenarios], seeds, n_steps,
                                            noise_seed, progress)
    return cells, log
