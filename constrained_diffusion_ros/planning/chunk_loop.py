"""The chunk loop: receding-horizon execution of action chunks, the one loop of the evaluation,
the delay study, lockstep mode and the live node.

The loop is fed observations by control step (a simulated clock in the evaluation and in
lockstep, the wall clock live) and answers each with the setpoint to execute. It asks a planning
worker for chunks (`PlanWorker`, plan_jobs.py): `SimulatedPlanning` plans in the caller's thread
and delivers the plan `delay` control steps later; live, a thread or a child process plans in
the background and delivers whenever the plan is done (`runtime.live_loop`). Whatever the
worker, the rules are these:
- a row asks for its next chunk `lead` steps before the chunk in force runs out (the first at
  once), unless a plan is on its way;
- a row whose zones changed since its plan, and whose rest of the chunk now lies where the
  planner keeps waypoints out of, asks for a new plan at once and stops the one in flight
  (unless that one is such a replan already); so does a live zone that moves the setpoint held;
  with `replan_on_zone_change` (live), so does every change of the zones, so that a plan that
  knows them follows any zone within one planning time;
- a plan is installed when it arrives, the waypoints whose time has passed skipped
  (action_queue.py); it is dropped if it is another episode's or configuration's, if every
  waypoint's time has passed, or if it was planned before zones that it enters (and asked for
  again); with `replan_on_zone_change` it is installed even then (guarded as the chunk in force
  is, below), so the robot is not left without waypoints while the plan that knows the zones
  is made;
- a row without a waypoint holds its last setpoint;
- every setpoint passes the guard against the zones in force: a waypoint planned before them
  that they now refuse is moved out of them first (`keep_out`), then the planner's guard (the
  shield) has the last word;
- a plug-in zone check that fails in use (`ZoneCheckError`: it raised, or answered NaN), in
  planning or in the guard, leaves the zones unknown: every row stops where its pusher is until
  the check answers again, and the fault is kept for `status` and logged, naming the check.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from constrained_diffusion_ros.planning.action_queue import (
    ActionQueue,
    ObservationHistory,
    committed_prefix,
)
from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, PlanWorker
from constrained_diffusion_ros.planning.planners import ChunkPlanner
from constrained_diffusion_ros.planning.simulated_worker import SimulatedPlanning
from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.plugins import ZoneCheckError

LOGGER = logging.getLogger(__name__)
FAULT_LOG_PERIOD_S = 10.0  # a zone check's fault, said again at most this often
HANDOVERS = ("sync", "async", "async_prefix")
EVERY_TICK = "every_tick"  # a simulated schedule: async_prefix, a plan asked at every tick

WorkerFactory = Callable[[ChunkPlanner, Callable[[PlanResult], None]], PlanWorker]


class ZoneSource(Protocol):
    """The zones in force for a batch of episodes, and a version that changes with them."""

    def area_at(self, step: int) -> RestrictedArea | None:
        """The zones at control step `step` (a batch-aware area, or one area for every
        episode), or None when there are none."""
        ...

    def version_at(self, step: int) -> int | np.ndarray:
        """Equal versions (one, or one per episode) mean equal zones."""
        ...


@dataclass
class LoopStats:
    plans_asked: int = 0  # planning jobs submitted
    plans_installed: int = 0  # episode-chunks installed
    plans_dropped: int = 0  # episode-chunks stale on arrival (episode, configuration, zones)
    planned_chunks: int = 0  # episode-chunks planned (a batched job of R rows counts R)
    planner_calls: int = 0  # plans that arrived
    planning_s: float = 0.0  # wall time planning took, summed over the plans that arrived
    last_plan_ms: float = float("nan")
    held_steps: int = 0  # row-steps with no waypoint to execute (the last setpoint held)
    late_steps: int = 0  # of those, after the episode's first plan: planning missed a deadline
    zone_reactions: int = 0  # setpoints changed at once because zones changed


@dataclass(frozen=True)
class LoopSettings:
    """How a `ChunkLoop` schedules its plans.

    `handover` says what a row does while its next plan is made: "sync" holds its last
    setpoint and starts the chunk when it arrives; "async" goes on with the chunk in force, and
    the new one skips the steps that passed; "async_prefix" too, with the waypoints committed
    meanwhile inpainted into the new chunk (`committed_prefix`, `soft` more drawn toward the
    chunk in force). `lead`: steps before the chunk runs out at which the next plan is asked
    for (sync: 0); None: from the measured planning time at `rate_hz`. `every_tick`: a row asks
    for a new plan at every observation that finds none on its way, from that observation,
    with the waypoints that will execute before it arrives (`delay` steps, or the measured
    planning time) held fixed: a zone is planned around as soon as planning allows, not at the
    next chunk. `replan_on_zone_change`: any change of the zones asks for a plan that knows
    them (the module's rules). `noise_seed`: the worker is reseeded with it at every new
    episode (None: not reseeded).
    """

    handover: str = "async_prefix"
    lead: int | None = None
    soft: int = 4
    rate_hz: float = 10.0
    noise_seed: int | None = None
    every_tick: bool = False
    delay: int | None = None
    replan_on_zone_change: bool = False

    def __post_init__(self) -> None:
        if self.handover not in HANDOVERS:
            raise ValueError(f"handover must be one of {HANDOVERS}, got {self.handover!r}")
        if self.every_tick and self.handover == "sync":
            raise ValueError("every_tick needs an asynchronous handover")


@dataclass
class RowState:
    """What the loop keeps per row (episode) of its batch, from the episode's start: arrays of
    B rows, declared here once."""

    setpoints: np.ndarray  # (B, 2) to execute: the guard's answer
    wanted: np.ndarray  # (B, 2) what the chunks in force ask, before the guard
    waiting: np.ndarray  # (B,) no waypoint to execute: the last setpoint is held
    handed_over: np.ndarray  # (B,) the setpoint is a new chunk's first
    executed_id: np.ndarray  # (B,) the chunk executed (its install count); -1: none, held
    planned_version: np.ndarray  # (B,) the zones' version each chunk was planned for
    replanning: np.ndarray  # (B,) the serial of the replan on its way; 0: none
    # Setpoints in force that a live change of the zones moved since the last asking, and
    # where they were before it (`_refused` judges them when asking).
    moved_by_zones: np.ndarray  # (B,)
    before_zones_moved: np.ndarray  # (B, 2)

    @classmethod
    def start(cls, pushers: np.ndarray) -> RowState:
        """An episode's rows, holding their pushers (B, 2) where they are."""
        batch = len(pushers)
        return cls(setpoints=pushers.astype(float), wanted=pushers.astype(float),
                   waiting=np.ones(batch, dtype=bool), handed_over=np.zeros(batch, dtype=bool),
                   executed_id=np.full(batch, -1), planned_version=np.zeros(batch, np.int64),
                   replanning=np.zeros(batch, dtype=np.int64),
                   moved_by_zones=np.zeros(batch, dtype=bool),
                   before_zones_moved=np.zeros((batch, 2)))


class ChunkLoop:
    """Plans a chunk per episode (B rows) and executes `n_action_steps` of its waypoints from
    `first_executed` on (the reference's convention), scheduled by its `settings`
    (`LoopSettings`); what it keeps per row is `rows` (`RowState`, None before the first
    observation). `on_install` is called whenever plans were installed, whichever call
    installed them (`observe` or `install_results`).

    Call everything from one thread; a background worker's results wait until
    `install_results` (or the next `observe`) takes them, and `wake` is called when one arrives.
    """

    def __init__(self, planner: ChunkPlanner, make_worker: WorkerFactory,
                 zones: ZoneSource | None = None, settings: LoopSettings = LoopSettings(),
                 wake: Callable[[], None] = lambda: None,
                 on_install: Callable[[], None] = lambda: None) -> None:
        config = planner.policy_config
        if settings.lead is not None and not 0 <= settings.lead <= config.n_action_steps:
            raise ValueError(f"lead must be in [0, n_action_steps], got {settings.lead}")
        self.planner, self.zones, self.settings = planner, zones, settings
        self.handover = settings.handover
        self.fixed_lead = 0 if settings.handover == "sync" else settings.lead
        self.every_tick, self.fixed_delay = settings.every_tick, settings.delay
        self.replan_on_zone_change = settings.replan_on_zone_change
        self.soft, self.rate_hz, self.noise_seed = settings.soft, settings.rate_hz, \
            settings.noise_seed
        self.wake, self.on_install = wake, on_install
        self.rows: RowState | None = None
        self.n_obs_steps, self.first_executed = config.n_obs_steps, config.first_executed
        self.n_action_steps = config.n_action_steps
        self.stats = LoopStats()
        self.plan_seconds = 0.0  # running estimate of one planning call
        self.serial = 0  # the last job's number
        self.generation = 0  # episodes and configurations: a plan from another is dropped
        self._results: list[PlanResult] = []  # arrived (or simulated: on their way)
        self._results_lock = threading.Lock()
        self.single = False  # observations come one at a time: answers are (2,)
        self.worker = make_worker(planner, self._on_result)
        self.history: ObservationHistory | None = None
        self.step: int | None = None  # the newest observation's control step
        self.queue = ActionQueue(0, self.n_action_steps)  # an episode's rows from its start
        self.skipped_before = 0  # waypoints skipped in the episodes before
        self.zone_check_error: ZoneCheckError | None = None  # the last fault of a zone check
        self.zone_check_errors = 0  # faults so far (in the loop, or seen from the worker)
        self.zone_check_failed = False  # the last call met one: the pushers stopped
        self._seen_worker_error: BaseException | None = None
        self._said_at: float | None = None  # when a zone check's fault was logged last

    @classmethod
    def simulated(cls, planner: ChunkPlanner, zones: ZoneSource | None = None,
                  generator: torch.Generator | None = None, delay: int = 0,
                  handover: str = "sync", noise_seed: int | None = None,
                  every_tick: bool = False,
                  on_install: Callable[[], None] = lambda: None) -> ChunkLoop:
        """The loop on a simulated clock, as the evaluation, the delay study and lockstep mode
        run it: plans made in the caller's thread from `generator`, ready `delay` steps after
        they are asked for, the next asked `delay` steps before the chunk runs out (sync: when
        it has); `handover` EVERY_TICK: async_prefix with `every_tick`."""
        if handover == EVERY_TICK:
            handover, every_tick = "async_prefix", True
        settings = LoopSettings(handover, lead=delay, noise_seed=noise_seed,
                                every_tick=every_tick, delay=delay)
        return cls(planner, SimulatedPlanning.factory(generator, delay), zones, settings,
                   on_install=on_install)

    # -- inputs ------------------------------------------------------------------------------

    @torch.inference_mode()  # no autograd here: less overhead per torch call
    def observe(self, step: int, observations: np.ndarray) -> np.ndarray:
        """The observations (B, obs_dim) of control step `step` (or one, (obs_dim,)) -> the
        setpoints to execute, (B, 2) (or (2,)). An earlier step than the newest starts a new
        episode. What each row executes, wanted and waits for is kept in `rows`."""
        return self._checked(self._observe, step, observations)

    def _observe(self, step: int, observations: np.ndarray) -> np.ndarray:
        self.single = np.ndim(observations) == 1
        observations = np.atleast_2d(observations)
        if self.step is not None and step < self.step:
            self.reset()
        first = self.history is None
        if first:
            self._start(observations)
        else:
            self.history.push(observations, step - self.step)
        self.step = step
        self._install(self._take_results())
        if first:  # the episode's first plans, at once (a plan still stopping is the last's)
            self._ask(np.arange(len(observations)))
        else:
            self._ask_due()
        self._install(self._take_results())  # a plan ready at once (a simulated delay of 0)
        self.rows.waiting = np.isnan(self.queue.at(step)).any(axis=-1)
        self.stats.held_steps += int(self.rows.waiting.sum())
        self.stats.late_steps += int((self.rows.waiting & self.queue.planned).sum())
        return self._answer(self._update())

    def reset(self, noise_seed: int | None = None) -> None:
        """A new episode: forget its chunks, observations and the guard's history, drop any
        plan in flight and reseed the noise (with `noise_seed`, else the loop's, if any)."""
        self.generation += 1
        self.history, self.step = None, None
        self.planner.reset()
        seed = self.noise_seed if noise_seed is None else noise_seed
        if seed is not None:
            self.worker.reseed(seed)

    def use_planner(self, planner: ChunkPlanner) -> None:
        """Another configuration: plans in flight are dropped and a new one asked for; the
        chunk in force executes until it arrives."""
        self.planner = planner
        self.worker.use(planner)
        self.generation += 1
        if self.step is not None:
            self.rows.replanning[:] = 0
            self._ask(np.arange(len(self.queue.end)), replan=True)

    @torch.inference_mode()
    def zones_changed(self) -> np.ndarray | None:
        """Zones changed (live): the setpoints held are guarded again against them and
        returned if that changed them, to be sent at once, else None. What to plan for them is
        left to `install_results`, which `wake` gets called: a row whose held setpoint they
        refuse, or the rest of whose chunk they enter, asks for a new plan then."""
        if self.step is None:
            return None
        return self._checked(self._zones_changed)

    def _zones_changed(self) -> np.ndarray | None:
        before = self.rows.setpoints
        after = self._update()
        moved = (after != before).any(axis=-1)
        if moved.any():  # whether the zones refuse where it was: judged when asking, not now
            self.stats.zone_reactions += 1
            rows = self.rows
            first = moved & ~rows.moved_by_zones
            rows.before_zones_moved[first], rows.moved_by_zones[first] = before[first], True
        self.wake()
        return self._answer(after) if moved.any() else None

    @torch.inference_mode()
    def install_results(self) -> np.ndarray | None:
        """Install the plans that arrived and ask for what is due; the setpoints now in force,
        or None if no plan came."""
        if self.step is None:
            return None
        return self._checked(self._install_results)

    def _install_results(self) -> np.ndarray | None:
        results = self._take_results()
        self._install(results)
        self._ask_due()
        return self._answer(self._update()) if results else None

    # -- outputs -----------------------------------------------------------------------------

    @property
    def lead(self) -> int:
        """Steps before the chunk runs out at which the next plan is asked for; measured: room
        for two planning times and a step, so that a plan a zone stops just before its end and
        asks again still comes before the chunk runs out."""
        if self.every_tick:
            return self.n_action_steps
        if self.fixed_lead is not None:
            return self.fixed_lead
        twice = max(1, int(np.ceil(2 * self.plan_seconds * self.rate_hz)))
        return int(min(self.n_action_steps, twice + 1))

    @property
    def delay_steps(self) -> int:
        """Control steps a plan is expected to take: the simulated delay, or the measured
        planning time (at least 1)."""
        if self.fixed_delay is not None:
            return self.fixed_delay
        return max(1, int(np.ceil(self.plan_seconds * self.rate_hz)))

    @property
    def chunk(self) -> np.ndarray:
        """(N, 2) the waypoints of the first row's chunk in force (NaN before the first)."""
        return self.queue.waypoints[0]

    def knows_zones(self) -> bool:
        """Whether the first row's chunk in force was planned with the zones in force."""
        if self.history is None:
            return False
        return bool(self._zones_now()[1][0] == self.rows.planned_version[0])

    def shutdown(self) -> None:
        self.worker.shutdown()

    # -- internals ---------------------------------------------------------------------------

    def _checked(self, call: Callable[..., np.ndarray | None], *args: object
                 ) -> np.ndarray | None:
        """`call(*args)`, unless a plug-in zone check fails in it: then every row stops where
        its pusher is (no setpoint planned or guarded with zones that cannot be told goes out),
        and the stop is the answer. A fault the worker met planning is taken up here too."""
        try:
            answer = call(*args)
            self.zone_check_failed = False
        except ZoneCheckError as error:
            self._zone_check_fault(error)
            self.zone_check_failed = True
            rows = self.rows
            rows.setpoints = self.planner.robot.pusher(self.history.latest).astype(float)
            rows.wanted, rows.waiting = rows.setpoints.copy(), np.ones(len(rows.setpoints), bool)
            answer = self._answer(self.rows.setpoints)
        error = getattr(self.worker, "error", None)  # (a test's stand-in may keep none)
        if isinstance(error, ZoneCheckError) and error is not self._seen_worker_error:
            self._seen_worker_error = error
            self._zone_check_fault(error)
        return answer

    def _zone_check_fault(self, error: ZoneCheckError) -> None:
        """Kept for `status` and logged at ERROR, at most once per FAULT_LOG_PERIOD_S: a check
        that turned NaN fails at every plan and every step (where, differing each time)."""
        self.zone_check_error, self.zone_check_errors = error, self.zone_check_errors + 1
        now = time.monotonic()
        if self._said_at is None or now - self._said_at >= FAULT_LOG_PERIOD_S:
            self._said_at = now
            LOGGER.error("%s: the pusher stops until it answers again (%d fault(s) so far)",
                         error, self.zone_check_errors)

    def _start(self, observations: np.ndarray) -> None:
        batch = len(observations)
        self.history = ObservationHistory(observations, self.n_obs_steps)
        self.skipped_before += self.queue.skipped
        self.queue = ActionQueue(batch, self.n_action_steps)
        self.rows = RowState.start(self.planner.robot.pusher(self.history.latest))

    def _answer(self, setpoints: np.ndarray) -> np.ndarray:
        return setpoints[0] if self.single else setpoints

    def _zones_now(self) -> tuple[RestrictedArea | None, np.ndarray]:
        rows = len(self.queue.end)
        if self.zones is None:
            return None, np.zeros(rows, dtype=np.int64)
        version = np.broadcast_to(self.zones.version_at(self.step), (rows,))
        return self.zones.area_at(self.step), version

    def _refused(self, waypoints: np.ndarray, rows: np.ndarray,
                 area: RestrictedArea | None) -> np.ndarray:
        """(R, N) which waypoints (R, N, 2) of `rows` lie where the planner keeps waypoints out
        of under `area` (the zones in force)."""
        zones = None if area is None else area.select_rows(rows)
        return self.planner.violates(torch.from_numpy(waypoints), zones, rows).numpy()

    def _ask_due(self) -> None:
        """Ask for the rows that are due: running out (and no plan on its way), or with zones
        on the rest of their chunk (or that refused their held setpoint) and no replan on its
        way."""
        planning = self._planning()
        # nothing on its way: a replan that failed is not coming
        self.rows.replanning[~planning] = 0
        remaining = self.queue.remaining(self.step)
        area, version = self._zones_now()
        entered = np.zeros(len(remaining), dtype=bool)
        moved = np.nonzero(self.rows.moved_by_zones)[0]
        if len(moved):  # zones came onto the setpoints held before them
            before = self.rows.before_zones_moved[moved][:, None]
            entered[moved] = self._refused(before, moved, area)[:, 0]
            self.rows.moved_by_zones[:] = False
        changed = version != self.rows.planned_version
        if self.replan_on_zone_change:  # any change: no need to look where the zones lie
            entered |= changed & self.queue.planned
        else:
            check = np.nonzero(~entered & changed & (remaining > 0))[0]
            if len(check):
                entered[check] = self.queue.rest_refused(
                    check, self.step, lambda waypoints: self._refused(waypoints, check, area))
        entered &= self.rows.replanning == 0
        ask = ((remaining <= self.lead) & ~planning) | entered
        if ask.any():
            self._ask(np.nonzero(ask)[0], replan=entered[ask])

    def _ask(self, rows: np.ndarray, replan: np.ndarray | bool = False) -> None:
        """Submit a plan for `rows` from their newest observations; `replan` rows are planned
        free of the chunk in force (it was planned for other zones or another configuration)
        and stop the plan in flight."""
        replan = np.broadcast_to(replan, rows.shape)
        area, version = self._zones_now()
        prefix = None
        # The waypoints that execute before the plan arrives: until the chunk's end at the
        # latest when asked `lead` steps before it, `delay_steps` when asked at every tick.
        committed = self.delay_steps if self.every_tick else self.lead
        if self.handover == "async_prefix" and (self.lead > 0 or self.every_tick) \
                and self.soft >= 0:
            prefix = committed_prefix(self.queue, rows, self.step, committed, self.soft,
                                      self.first_executed, free=replan)
        self.serial += 1
        job = PlanJob(self.generation, self.step, self.history.tensor(rows),
                      None if area is None else area.select_rows(rows), version[rows].copy(),
                      prefix, rows, self.serial)
        self.stats.plans_asked += 1
        if self.handover == "sync":  # the robot waits for the plan, which starts when ready
            self.queue.clear(rows)
        self.rows.replanning[rows[replan]] = job.serial
        self.worker.submit(job, cancel=bool(replan.any()))

    def _planning(self) -> np.ndarray:
        """(B,) rows with a plan on its way: being planned, or arrived and not installed."""
        planning = np.full(len(self.queue.end), self.worker.busy)
        with self._results_lock:
            for result in self._results:
                if result.job.generation == self.generation:
                    planning[result.job.rows] = True
        return planning

    def _on_result(self, result: PlanResult) -> None:
        """From the worker (its own thread, or the caller's): kept until taken."""
        with self._results_lock:
            self._results.append(result)
        self.wake()

    def _take_results(self) -> list[PlanResult]:
        """The results ready by the newest step (a simulated worker's wait for their step)."""
        ready, later = [], []
        with self._results_lock:
            for result in self._results:
                due = result.ready_step is None or (self.step is not None
                                                    and result.ready_step <= self.step)
                (ready if due else later).append(result)
            self._results = later
        return ready

    def _install(self, results: list[PlanResult]) -> None:
        before = self.stats.plans_installed
        for result in results:
            job, chunks = result.job, result.chunk
            self.plan_seconds = (result.seconds if self.plan_seconds == 0.0
                                 else 0.7 * self.plan_seconds + 0.3 * result.seconds)
            self.stats.last_plan_ms = 1000 * result.seconds
            self.stats.planning_s += result.seconds
            self.stats.planned_chunks += len(job.rows)
            self.stats.planner_calls += 1
            if job.generation != self.generation or self.history is None:
                self.stats.plans_dropped += len(job.rows)
                continue
            if self.handover != "sync" and self.step - job.step >= chunks.shape[1]:
                # Every waypoint's time has passed (a planner that started late, as a planning
                # process still starting does): nothing to install; `_ask_due` asks again.
                self.stats.plans_dropped += len(job.rows)
                continue
            rows = job.rows
            mine = self.rows.replanning[rows] == job.serial
            self.rows.replanning[rows[mine]] = 0
            area, version = self._zones_now()
            # Planned before the zones in force: with replan_on_zone_change installed, guarded,
            # and `_ask_due` asks again; else dropped if it enters them, and asked for again.
            stale = (job.zone_version != version[rows]) & (not self.replan_on_zone_change)
            if stale.any():
                stale[stale] = self._refused(chunks[stale], rows[stale], area).any(axis=1)
            if stale.any():
                self.stats.plans_dropped += int(stale.sum())
                again = rows[stale]
                free = self.rows.replanning[again] == 0
                if free.any():
                    self._ask(again[free], replan=True)
            keep = ~stale
            first = self.step if self.handover == "sync" else job.step
            self.queue.install(rows[keep], chunks[keep], first, self.step)
            self.rows.planned_version[rows[keep]] = job.zone_version[keep]
            self.stats.plans_installed += int(keep.sum())
        if self.stats.plans_installed != before:
            self.on_install()

    def _update(self) -> np.ndarray:
        """The setpoints of the newest step from the chunks in force (the ones held where a row
        has none), through the guard."""
        waypoints, waiting = self.queue.at_or(self.step, self.rows.setpoints)
        chunk = np.where(waiting, -1, self.queue.installs)
        self.rows.handed_over = (chunk != self.rows.executed_id) & ~waiting
        self.rows.executed_id = chunk
        self.rows.wanted = waypoints
        area, version = self._zones_now()
        older = np.nonzero(version != self.rows.planned_version)[0]
        if area is not None and len(older):  # waypoints planned before these zones
            points = waypoints[older]
            refused = self._refused(points[:, None], older, area)[:, 0]
            if refused.any():
                waypoints = waypoints.copy()
                moved = older[refused]
                waypoints[moved] = self.planner.keep_out(area.select_rows(moved),
                                                         points[refused])
        # The guard sees the positions as the planner saw them (float32 observations).
        self.rows.setpoints = self.planner.guard(area, self.history.latest, waypoints, self.step)
        return self.rows.setpoints

