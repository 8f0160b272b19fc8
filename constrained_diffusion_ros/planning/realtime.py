"""Real-time chunking: waypoints indexed by control step, and a planner that works in the
background while they execute.

A chunk planned from the observation of step t puts its executed waypoint j (chunk index
`first_executed + j`) at step t + j, whenever it arrives: installed at a later step, the
waypoints whose time has passed are skipped (as LeRobot's asynchronous action queue merges
chunks). While a plan is being made, the waypoints that will execute before it arrives are
already decided; the next chunk is denoised with them held fixed (`committed_prefix`), so the
handover does not jump. The policy node runs this with a `PlanningProcess` (workers.py) and a
`ControlClock` thread; the latency evaluation runs it in lockstep with a chosen delay.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.workers import (
    BackgroundPlanner,
    PlanJob,
    PlanningProcess,
    PlanResult,
    plan_chunk,
)
from constrained_diffusion_ros.sampling.hooks import CommittedPrefix, prefix_weights
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.live import LiveZones


class ActionQueue:
    """The chunk in force per episode (B rows), as waypoints indexed by control step.

    A row holds the executed part of its chunk and the rest of the horizon after it, so a plan
    that arrives late still finds waypoints to execute; it is due for a new one once
    `n_action_steps` of them have executed after the ones skipped at install (the horizon the
    policy was trained to execute, whatever the delay).
    """

    def __init__(self, batch: int, n_action_steps: int) -> None:
        self.n_action_steps = n_action_steps
        self.waypoints = np.full((batch, 0, 2), np.nan)
        self.first_step = np.zeros(batch, dtype=np.int64)
        self.end = np.zeros(batch, dtype=np.int64)  # index after the last one to execute
        self.planned = np.zeros(batch, dtype=bool)
        self.installs = np.zeros(batch, dtype=np.int64)  # chunks installed per row: its id
        self.skipped = 0  # waypoints skipped at install because their time had passed

    def install(self, rows: np.ndarray, waypoints: np.ndarray, first_step: np.ndarray | int,
                now: int) -> np.ndarray:
        """Rows `rows` take `waypoints` (R, N, 2), waypoint j for step `first_step + j`; returns
        how many of them had already passed at step `now` (skipped)."""
        rows = np.asarray(rows)
        if waypoints.shape[1] != self.waypoints.shape[1]:
            grown = np.full((len(self.first_step), waypoints.shape[1], 2), np.nan)
            keep = min(waypoints.shape[1], self.waypoints.shape[1])
            grown[:, :keep] = self.waypoints[:, :keep]
            self.waypoints = grown
        self.waypoints[rows] = waypoints
        self.first_step[rows] = first_step
        self.planned[rows] = True
        self.installs[rows] += 1
        skipped = np.clip(now - self.first_step[rows], 0, waypoints.shape[1])
        self.end[rows] = np.minimum(skipped + self.n_action_steps, waypoints.shape[1])
        self.skipped += int(skipped.sum())
        return skipped

    def clear(self, rows: np.ndarray | None = None) -> None:
        """Forget the chunks of `rows` (all by default): nothing to execute until a plan."""
        self.planned[slice(None) if rows is None else rows] = False

    def offset(self, step: int) -> np.ndarray:
        """(B,) index of step `step` in each row's chunk."""
        return step - self.first_step

    def at(self, step: int) -> np.ndarray:
        """(B, 2) the waypoints of step `step`; NaN where a row has none (no chunk, or its
        chunk is used up)."""
        out = np.full((len(self.first_step), 2), np.nan)
        index = self.offset(step)
        ok = self.planned & (index >= 0) & (index < self.waypoints.shape[1])
        out[ok] = self.waypoints[np.nonzero(ok)[0], index[ok]]
        return out

    def remaining(self, step: int) -> np.ndarray:
        """(B,) waypoints still to execute from step `step` on; 0 without a chunk."""
        left = self.end - self.offset(step)
        return np.where(self.planned, np.clip(left, 0, self.n_action_steps), 0)

    def upcoming(self, rows: np.ndarray, step: int, count: int) -> np.ndarray:
        """(R, count, 2) the waypoints of steps step .. step + count - 1; NaN where none."""
        index = self.offset(step)[rows, None] + np.arange(count)[None]
        ok = self.planned[rows, None] & (index >= 0) & (index < self.waypoints.shape[1])
        out = np.full((len(rows), count, 2), np.nan)
        r, c = np.nonzero(ok)
        out[r, c] = self.waypoints[np.asarray(rows)[r], index[r, c]]
        return out


def committed_prefix(queue: ActionQueue, rows: np.ndarray, step: int, delay: int, soft: int,
                     first_executed: int) -> CommittedPrefix | None:
    """The prefix hook for a chunk planned at step `step` that arrives `delay` steps later.

    Chunk index i lies at step `step - first_executed + i`: indices up to `first_executed +
    delay` are the waypoints already executed or committed (held exactly); the `soft` after
    them are drawn toward the chunk in force. Rows with no chunk in force are left free.
    Returns None when nothing is known (the first plan of an episode).
    """
    count = first_executed + delay + soft
    known = queue.upcoming(rows, step - first_executed, count)
    weights = np.broadcast_to(prefix_weights(first_executed + delay, soft).numpy(),
                              known.shape[:2]).copy()
    missing = np.isnan(known).any(axis=-1)
    weights[missing] = 0.0
    if not weights.any():
        return None
    known[missing] = 0.0
    return CommittedPrefix(torch.from_numpy(known), torch.from_numpy(weights))


CLOCK_PRIORITY = 50  # SCHED_FIFO priority of the control clock where allowed (ros2_control's)
EXECUTOR_PRIORITY = 40  # the node's executor thread, which reacts to zones: below the clock
LATENESS_WINDOW = 100  # ticks over which the clock's lateness is kept (the diagnostics')


def request_fifo(priority: int) -> bool:
    """SCHED_FIFO at `priority` for the calling thread, as ros2_control's controller manager
    asks for its loop, if the system allows it (root, CAP_SYS_NICE or an rtprio limit): the
    thread then preempts other processes' work at once. Processes it starts later get normal
    scheduling back (reset on fork). Whether it was granted."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(threading.get_native_id(),
                              os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(priority))
    except OSError:
        return False
    return True


def warm_up(planner: ConstrainedPlanner) -> None:
    """Runs the zone reaction's computing once on a scratch zone: a new zone is then not the
    first to pay for lazy imports and first calls (offline the first reaction took 32 ms, the
    next ones 11), time the node's executor holds the interpreter while the clock waits for it.
    Leaves the planner as it found it (its shield reset)."""
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


class ControlClock:
    """Threads that call `on_tick` every 1 / rate_hz seconds of the monotonic clock, on
    absolute deadlines (no drift); a tick missed by more than a period is dropped, not made up
    in a burst. Threads of their own, not an executor's timer: nothing queued in an executor (a
    zone batch, an observation, a plan being installed) can hold a tick back, and `on_tick`
    should only send what is already computed. `shutdown()` stops and joins them.

    On a virtual machine the hypervisor takes a CPU away for milliseconds at a time (steal), and
    a thread whose timer is on that CPU wakes late whatever its priority. So `threads` threads
    (default: two, where the process may use two CPUs), each pinned to a CPU of its own, wait for
    the same deadlines and the first awake sends the tick; the others find it sent. Ticks never
    overlap: `on_tick` runs under the lock that claims the tick.
    """

    def __init__(self, rate_hz: float, on_tick: Callable[[], None],
                 priority: int = CLOCK_PRIORITY, name: str = "control_clock",
                 threads: int | None = None, window: int = LATENESS_WINDOW) -> None:
        self.period, self._on_tick, self._priority = 1.0 / rate_hz, on_tick, priority
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        count = max(1, threads if threads is not None else min(2, len(cpus)))
        self.ticks = 0
        self.missed = 0  # ticks dropped because every thread woke more than a period late
        self.lateness: deque[float] = deque(maxlen=window)  # s, the latest ticks'
        self._next_tick = 0  # index of the next tick to send (tick k is due at start + k periods)
        self._tick_lock = threading.Lock()
        self._stop = threading.Event()
        self._granted: list[bool] = []  # per thread: got the real-time priority it asked for
        self._ready = threading.Semaphore(0)
        self._start = time.monotonic() + self.period
        pinned = count > 1 and len(cpus) > 1
        self._threads = [
            threading.Thread(target=self._run, args=(cpus[k % len(cpus)] if pinned else None,),
                             name=f"{name}_{k}", daemon=True) for k in range(count)]
        for thread in self._threads:
            thread.start()
        for _ in self._threads:
            self._ready.acquire(timeout=5.0)

    @property
    def realtime(self) -> bool:
        """Whether every clock thread got the real-time priority it asked for."""
        return len(self._granted) == len(self._threads) and all(self._granted)

    def late_p99(self) -> float:
        """s: how late the latest ticks woke, 99th percentile (nan before the first)."""
        latest = list(self.lateness)  # one C-level copy: the clock thread may be appending
        return float(np.percentile(latest, 99)) if latest else float("nan")

    def shutdown(self, timeout: float = 5.0) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout)

    def _wait(self, seconds: float) -> bool:
        """Sleep up to `seconds`; True once the clock is shut down."""
        return self._stop.wait(seconds)

    def _run(self, cpu: int | None) -> None:
        self._granted.append(request_fifo(self._priority))
        if cpu is not None:
            with contextlib.suppress(OSError):  # a CPU taken away since: any will do
                os.sched_setaffinity(threading.get_native_id(), {cpu})
        self._ready.release()
        tick = 0
        while not self._wait(max(0.0, self._start + tick * self.period - time.monotonic())):
            with self._tick_lock:
                if tick < self._next_tick:  # another thread sent it: wait for the next one
                    tick = self._next_tick
                    continue
                late = time.monotonic() - (self._start + tick * self.period)
                self.lateness.append(late)
                if late > self.period:
                    skipped = int(late // self.period)
                    self.missed += skipped
                    tick += skipped
                self._next_tick = tick + 1
                self.ticks += 1
                try:
                    self._on_tick()
                except Exception:  # a failed send must not stop the clock
                    logging.getLogger(__name__).exception("control tick failed")
            tick += 1


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

    A `BackgroundPlanner` plans from the latest observations `lead` steps before the chunk in
    force runs out (or at once when new zones put the rest of it where the planner keeps
    waypoints out of); its chunk is installed as soon as it arrives with the steps that passed
    skipped, and denoised with the committed waypoints inpainted. The setpoint is computed
    whenever what it depends on changes (an observation, a plan installed, zones changed) and
    passes the planner's guard (the shield) against the zones in force then; `tick` only reads
    it, so a clock on its own thread sends it on time however long the computing takes. Call
    everything else from one thread (the node's executor); `wake` is called from the worker
    when a plan is ready, to get `install_results` called.
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
        self.observations: dict[int, np.ndarray] = {}
        self.step: int | None = None  # the newest observation's control step
        self.setpoint: np.ndarray | None = None  # (2,) shielded last, what `tick` sends;
        # replaced, never changed in place
        self.plan_seconds = 0.0  # running estimate of one planning call
        self.stats = ControllerStats()
        self._results: list[PlanResult] = []
        self._results_lock = threading.Lock()
        self.worker = (BackgroundPlanner(self._plan, self._on_result, noise_seed)
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
        self.observations[step] = np.asarray(observation, dtype=np.float32)
        for old in [s for s in self.observations if s <= step - self.n_obs_steps]:
            del self.observations[old]
        self.step = step
        if first:  # the episode's first plan, at once (`new_episode` stopped the last one's)
            self._ask(prefix=False)
        if np.isnan(self.queue.at(step)[0]).any():
            self.stats.held_steps += 1
        return self._update()

    def new_episode(self) -> None:
        """The last episode is forgotten: its chunks, observations and the shield's history;
        the noise is reseeded and the plan in flight stopped (the next observation asks)."""
        self.generation += 1
        self.replan = None
        self.queue.clear()
        self.observations.clear()
        self.step, self.setpoint = None, None
        self.planner.reset()
        self.worker.reseed(self.noise_seed)

    def use_planner(self, planner: ConstrainedPlanner) -> None:
        """Another configuration: plans in flight are dropped, a new one asked for; the chunk
        in force executes until it arrives."""
        warm_up(planner)
        self.planner = planner
        if isinstance(self.worker, PlanningProcess):
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
        remaining = int(self.queue.remaining(self.step)[0])
        rest = self.queue.upcoming(np.array([0]), self.step, remaining)
        return remaining > 0 and self._violates(rest)

    def _violates(self, waypoints: np.ndarray) -> bool:
        return bool(self.planner.violates(torch.from_numpy(waypoints),
                                          self.zones.area_at(self.step), np.array([0])).any())

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

    def shutdown(self) -> None:
        self.worker.shutdown()

    # -- internals ------------------------------------------------------------------------

    def _pusher(self) -> np.ndarray:
        return self.planner.robot.pusher(self.observations[self.step]).astype(float)

    def _update(self, ask: bool = True) -> np.ndarray:
        """The setpoint of the newest step from the chunk in force (the one held when it has
        none), through the guard; asks for the next plan when the chunk is running out."""
        waypoint = self.queue.at(self.step)[0]
        if np.isnan(waypoint).any():
            waypoint = self.setpoint if self.setpoint is not None else self._pusher()
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
        latest = self.observations[self.step][None]
        setpoint = np.asarray(setpoint, float)[None]
        setpoint = self.planner.keep_out(area, setpoint)
        return self.planner.guard(area, latest, setpoint, self.step)[0]

    def _history(self) -> torch.Tensor:
        frames, latest = [], self.observations[self.step]
        for step in range(self.step - self.n_obs_steps + 1, self.step + 1):
            frames.append(self.observations.get(step, frames[-1] if frames else latest))
        return torch.from_numpy(np.stack(frames)[None])

    def _ask(self, prefix: bool, replan: bool = False) -> None:
        """Submit a plan from the newest observations (replacing any not yet started); a
        `replan` also stops the plan in flight, unless that is a replan itself."""
        committed = None
        if prefix and self.soft >= 0:
            committed = committed_prefix(self.queue, np.array([0]), self.step, self.lead,
                                         self.soft, self.first_executed)
        self.stats.plans_asked += 1
        job = PlanJob(self.generation, self.step, self._history(),
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
