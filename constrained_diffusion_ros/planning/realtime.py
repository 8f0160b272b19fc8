"""The real-time controller: the live action filter, which plans in the background while the
chunk in force executes (real-time chunking).

A chunk planned from the observation of step t puts its executed waypoint j at step t + j,
whenever it arrives (the action queue, action_queue.py); the next chunk is denoised with the
waypoints that will execute before it arrives held fixed (`committed_prefix`), so the handover
does not jump. The plans are made by a worker (plan_jobs.py's `PlanWorker`): the policy node's
is a `PlanningProcess` (planning_process.py), and its setpoints go out on a `ControlClock`
thread (clock.py); the latency evaluation runs the same queue in lockstep with a chosen delay
(lockstep.py).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from constrained_diffusion_ros.planning.action_queue import (
    ActionQueue,
    ObservationHistory,
    committed_prefix,
)
from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, PlanWorker, plan_chunk
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.planning_process import PlanningProcess
from constrained_diffusion_ros.planning.thread_worker import PlanningThread
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.live import LiveZones


def warm_up(planner: ConstrainedPlanner) -> None:
    """Runs the zone reaction's computing once on a scratch zone: a new zone is then not the
    first to pay for lazy imports and first calls, time the node's executor holds the
    interpreter while the clock waits for it. Leaves the planner as it found it (its shield
    reset)."""
    robot = planner.robot
    x_min, y_min, x_max, y_max = robot.workspace
    centre, half = np.array([(x_min + x_max) / 2, (y_min + y_max) / 2]), (x_max - x_min) / 8
    scratch = LiveZones(workspace=robot.workspace)
    scratch.apply([("warm_up", [tuple(centre + half * np.array(corner))
                                for corner in ((-1, -1), (1, -1), (1, 1), (-1, 1))])], 0.0)
    area, point = scratch.area_at(0), centre[None]
    leaves_no_room(scratch.snapshot().geometry, robot.workspace, robot.pusher_radius)
    planner.violates(torch.from_numpy(point[None]), area, np.array([0]))
    observation = np.zeros((1, planner.policy_config.obs_dim))
    planner.guard(area, observation, planner.keep_out(area, point), 0)
    planner.reset()


@dataclass
class ControllerStats:
    plans_asked: int = 0
    plans_installed: int = 0
    plans_dropped: int = 0  # stale: another configuration or episode, or unsafe under new zones
    held_steps: int = 0  # steps with no waypoint to execute (the last setpoint held)
    zone_reactions: int = 0  # setpoints changed at once because a zone arrived
    last_plan_ms: float = float("nan")


class RealtimeController:
    """The live action filter, free of ROS: the node feeds it observations, zone changes and
    clock ticks, and publishes what it returns.

    Its worker (a `PlanningProcess`, or a `PlanningThread`) plans from the latest observations
    `lead` steps before the chunk in force runs out (or at once when new zones put the rest of
    it where the planner keeps waypoints out of); its chunk is installed as soon as it arrives
    with the steps that passed skipped, and denoised with the committed waypoints inpainted. The
    setpoint is computed whenever what it depends on changes (an observation, a plan installed,
    zones changed) and passes the planner's guard (the shield) against the zones in force then;
    `tick` only reads it, so a clock on its own thread sends it on time however long the
    computing takes. Call everything else from one thread (the node's executor); `wake` is
    called from the worker when a plan is ready, to get `install_results` called.
    """

    def __init__(self, planner: ConstrainedPlanner, zones: LiveZones, rate_hz: float,
                 lead: int | None = None,
                 soft: int = 4, noise_seed: int = 0,
                 wake: Callable[[], None] = lambda: None,
                 process_threads: int | None = None, idle: bool = True) -> None:
        """`process_threads`: plan in a child process with that many torch threads (what the
        node does), at idle priority if `idle` (see `PlanningProcess`); None: in a thread of
        this process."""
        config = planner.policy_config
        warm_up(planner)
        self.planner, self.zones, self.rate_hz = planner, zones, rate_hz
        self.n_action_steps, self.first_executed = config.n_action_steps, config.first_executed
        self.n_obs_steps = config.n_obs_steps
        self.fixed_lead, self.soft, self.noise_seed, self.wake = lead, soft, noise_seed, wake
        self.queue = ActionQueue(1, config.n_action_steps)
        self.generation = 0
        # The plan asked for when zones or the configuration made the one in flight worthless
        # (that one was stopped), until it arrives: later changes do not stop it in turn, or a
        # zone re-published on every frame would stop every plan.
        self.replan: PlanJob | None = None
        self.history: ObservationHistory | None = None  # (1 episode)
        self.step: int | None = None  # the newest observation's control step
        self.waiting = False  # the newest step has no waypoint: the last setpoint is held
        self.setpoint: np.ndarray | None = None  # (2,) shielded last, what `tick` sends;
        # replaced, never changed in place
        self.plan_seconds = 0.0  # running estimate of one planning call
        self.stats = ControllerStats()
        self._results: list[PlanResult] = []
        self._results_lock = threading.Lock()
        self.worker: PlanWorker = (PlanningThread(self._plan, self._on_result, noise_seed)
                       if process_threads is None else
                       PlanningProcess(planner, self._on_result, noise_seed, process_threads,
                                       idle=idle))

    # -- inputs ---------------------------------------------------------------------------

    @torch.inference_mode()  # no autograd here: less overhead per torch call
    def observe(self, step: int, observation: np.ndarray) -> np.ndarray:
        """The observation (obs_dim,) of control step `step`; an earlier step than the newest
        starts a new episode. Returns the setpoint for this step (also held for `tick`)."""
        if self.step is not None and step < self.step:
            self.new_episode()
        first = self.step is None
        if first:
            self.history = ObservationHistory(np.asarray(observation)[None], self.n_obs_steps)
        else:
            self.history.push(np.asarray(observation)[None], step - self.step)
        self.step = step
        if first:  # the episode's first plan, at once (`new_episode` stopped the last one's)
            self._ask(prefix=False)
        self.waiting = bool(np.isnan(self.queue.at(step)[0]).any())
        self.stats.held_steps += self.waiting
        return self._update()

    def new_episode(self) -> None:
        """The last episode is forgotten: its chunks, observations and the shield's history;
        the noise is reseeded and the plan in flight stopped (the next observation asks)."""
        self.generation += 1
        self.replan = None
        self.queue.clear()
        self.history = None
        self.step, self.setpoint = None, None
        self.planner.reset()
        self.worker.reseed(self.noise_seed)

    def use_planner(self, planner: ConstrainedPlanner) -> None:
        """Another configuration: plans in flight are dropped, a new one asked for; the chunk
        in force executes until it arrives."""
        warm_up(planner)
        self.planner = planner
        self.worker.use(planner)
        self.generation += 1
        self.replan = None
        if self.step is not None:
            self._ask(prefix=False, replan=True)

    @property
    def lead(self) -> int:
        """Steps before the chunk runs out at which the next plan is asked for."""
        if self.fixed_lead is not None:
            return self.fixed_lead
        return int(min(self.n_action_steps, self.delay_steps + 1))

    @property
    def delay_steps(self) -> int:
        """Control steps a plan is expected to take."""
        return max(1, int(np.ceil(self.plan_seconds * self.rate_hz)))

    # -- outputs --------------------------------------------------------------------------

    def tick(self) -> np.ndarray | None:
        """The setpoint (2,) to send on this tick, or None before the first observation.

        Only reads: the setpoint was computed (and shielded) when its inputs last changed, so
        a clock on another thread can send it without waiting for any computation."""
        return self.setpoint

    @torch.inference_mode()  # no autograd here: less overhead per torch call
    def zones_changed(self, send: Callable[[np.ndarray], None] = lambda _: None
                      ) -> np.ndarray | None:
        """Zones changed: the held setpoint is shielded again and, if that changed it, the safe
        one returned and given to `send` at once, before anything else; then, if the setpoint
        held before or the rest of the chunk is where the planner keeps waypoints out of now, a
        replan is asked for and the plan in flight stopped (unless that is a replan already):
        it was planned for zones that no longer hold. A pusher held at the end of its chunk has
        no rest of the chunk, so only the first test catches a zone on its way; a zone removed
        stops nothing (what was planned around it is still safe)."""
        if self.step is None:
            return None
        before = self.setpoint
        after = self._update(ask=False)
        changed = before is not None and not np.array_equal(after, before)
        if changed:
            self.stats.zone_reactions += 1
            send(after)
        if (changed and self._violates(before[None, None])) or self._rest_entered():
            self._ask(prefix=False, replan=True)
        else:
            self._ask_if_running_out()
        return after if changed else None

    def _rest_entered(self) -> bool:
        """The rest of the chunk lies where the planner keeps waypoints out of now."""
        return bool(self.queue.rest_refused(np.array([0]), self.step, self._refused)[0])

    def _refused(self, waypoints: np.ndarray) -> np.ndarray:
        """(1, N) the waypoints (1, N, 2) where the planner keeps them out of now."""
        return self.planner.violates(torch.from_numpy(waypoints), self.zones.area_at(self.step),
                                     np.array([0])).numpy()

    def _violates(self, waypoints: np.ndarray) -> bool:
        return bool(self._refused(waypoints).any())

    @torch.inference_mode()  # no autograd here: less overhead per torch call
    def install_results(self) -> np.ndarray | None:
        """Install the plans that arrived (on the caller's thread); the new setpoint to hold, or
        None if nothing arrived."""
        with self._results_lock:
            results, self._results = self._results, []
        if not results:
            return None
        for result in results:
            job = result.job
            if job is self.replan:
                self.replan = None
            self.plan_seconds = (result.seconds if self.plan_seconds == 0.0
                                 else 0.7 * self.plan_seconds + 0.3 * result.seconds)
            self.stats.last_plan_ms = 1000 * result.seconds
            if job.generation != self.generation or self.step is None:
                self.stats.plans_dropped += 1
                continue
            chunk = result.chunk[None]
            if job.zone_version != self.zones.version_at(self.step) and self._violates(chunk):
                self.stats.plans_dropped += 1  # planned before the zones that it enters
                if self.replan is None or not self.worker.busy:  # else one is coming
                    self._ask(prefix=False)
                continue
            self.queue.install(np.array([0]), chunk, job.step, self.step)
            self.stats.plans_installed += 1
        return self._update() if self.step is not None else None

    @property
    def chunk(self) -> np.ndarray:
        """(N, 2) the waypoints of the chunk in force (NaN before the first)."""
        return self.queue.waypoints[0]

    def status(self) -> dict[str, object]:
        """The controller's and its worker's counters, for diagnostics (`planning_error`: the
        worker's last fault, or None)."""
        stats, worker = self.stats, self.worker
        return {"plans": stats.plans_installed, "plans_dropped": stats.plans_dropped,
                "plans_cancelled": worker.cancelled, "waypoints_skipped": self.queue.skipped,
                "held_steps": stats.held_steps, "zone_reactions": stats.zone_reactions,
                "lead": self.lead, "planning_priority": worker.priority,
                "planning_errors": worker.errors, "planning_failed": worker.failed,
                "planning_restarts": worker.restarts, "planning_error": worker.error}

    def shutdown(self) -> None:
        self.worker.shutdown()

    # -- internals ------------------------------------------------------------------------

    def _pusher(self) -> np.ndarray:
        return self.planner.robot.pusher(self.history.latest[0]).astype(float)

    def _update(self, ask: bool = True) -> np.ndarray:
        """The setpoint of the newest step from the chunk in force (the one held when it has
        none), through the guard; asks for the next plan when the chunk is running out."""
        held = self.setpoint if self.setpoint is not None else self._pusher()
        waypoint = self.queue.at_or(self.step, held[None])[0][0]
        if ask:
            self._ask_if_running_out()
        self.setpoint = self._guarded(waypoint)
        return self.setpoint

    def _ask_if_running_out(self) -> None:
        if self.worker.busy:
            return
        self.replan = None  # nothing in flight or waiting: a replan that failed is not coming
        if self.queue.remaining(self.step)[0] <= self.lead:
            self._ask(prefix=True)

    def _guarded(self, setpoint: np.ndarray) -> np.ndarray:
        """The zones in force now decide: a waypoint planned before them is moved out of them
        first (the planner's `keep_out`), then the shield has the last word."""
        area = self.zones.area_at(self.step)
        latest = self.history.latest
        setpoint = np.asarray(setpoint, float)[None]
        setpoint = self.planner.keep_out(area, setpoint)
        return self.planner.guard(area, latest, setpoint, self.step)[0]

    def _ask(self, prefix: bool, replan: bool = False) -> None:
        """Submit a plan from the newest observations (replacing any not yet started); a
        `replan` also stops the plan in flight, unless that is a replan itself."""
        committed = None
        if prefix and self.soft >= 0:
            committed = committed_prefix(self.queue, np.array([0]), self.step, self.lead,
                                         self.soft, self.first_executed)
        self.stats.plans_asked += 1
        job = PlanJob(self.generation, self.step, self.history.tensor(),
                      self.zones.area_at(self.step), self.zones.version_at(self.step), committed)
        cancel = replan and self.replan is None
        if replan:
            self.replan = job
        self.worker.submit(job, cancel)

    def _plan(self, job: PlanJob, generator: torch.Generator,
              interrupt: Callable[[], bool]) -> np.ndarray:
        return plan_chunk(self.planner, job, generator, interrupt)

    def _on_result(self, result: PlanResult) -> None:
        with self._results_lock:
            self._results.append(result)
        self.wake()
