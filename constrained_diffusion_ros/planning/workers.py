"""Background planners: where the next chunk is denoised while the current one executes.

`BackgroundPlanner` plans in a thread of the node's process; `PlanningProcess` in a child
process. Denoising runs hundreds of torch calls with Python between them, all under the
interpreter's lock, which the control clock and the zone callbacks need too; a child process has
an interpreter of its own, so the node's threads never wait behind planning, and a planner that
crashes does not take the node with it, as LeRobot's asynchronous inference keeps the policy in
a server of its own. (On the 2-core VM of the README the two gave the same live figures within
its noise.) Both take jobs the
same way: `submit` replaces a job not yet started (only the newest request matters), a result
goes to `on_result` with its job, `reseed` applies before the next job, `shutdown` stops and
joins (like tf2_ros's listener, each owns its thread).
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import torch

from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.sampling.hooks import CommittedPrefix
from constrained_diffusion_ros.sampling.sampler import Interrupted
from constrained_diffusion_ros.zones.area import RestrictedArea

LOGGER = logging.getLogger(__name__)

STARVED_SHARE = 0.25  # of a core, while planning: below it, idle priority starves the planner
WATCH_PERIOD_S = 0.5  # how often the node looks at what the planning process gets


@dataclass
class PlanJob:
    """One request to the background planner: everything it needs, copied when asked."""

    generation: int
    step: int  # the control step of the newest observation in `observations`
    observations: torch.Tensor  # (1, n_obs_steps, obs_dim)
    zones: RestrictedArea | None  # the zones in force when asked
    zone_version: int
    prefix: CommittedPrefix | None


@dataclass
class PlanResult:
    job: PlanJob
    chunk: np.ndarray  # (horizon, 2)
    seconds: float


def plan_chunk(planner: ConstrainedPlanner, job: PlanJob, generator: torch.Generator,
               interrupt: Callable[[], bool] = lambda: False) -> np.ndarray:
    """(horizon - first_executed, 2) the executed part of a chunk planned for `job` and the
    rest of the horizon after it; raises `Interrupted` once `interrupt()` is true."""
    with planner.sampler.interruptible(interrupt):
        chunk = planner.plan(job.observations, job.zones, None, generator, job.prefix)
    return chunk[0, planner.policy_config.first_executed:].numpy().astype(float)


class BackgroundPlanner:
    """A worker thread that plans one chunk at a time, off the control thread.

    `submit` replaces any job not yet started (only the newest request matters), and with
    `cancel` stops the one in flight before its next denoising step; a result is
    offered to `on_result` with its job, whose generation the owner compares with its own to
    drop plans that a zone or configuration change made stale. The worker draws from its own
    random generator and runs at a lower CPU priority than the process's other threads, so the
    control clock is never kept waiting by planning. Owns its thread like tf2_ros's listener:
    `shutdown()` stops and joins it.
    """

    def __init__(self, plan: Callable[[PlanJob, torch.Generator, Callable[[], bool]],
                                      np.ndarray],
                 on_result: Callable[[PlanResult], None], noise_seed: int = 0,
                 niceness: int = 5, name: str = "background_planner") -> None:
        self._plan, self._on_result, self._niceness = plan, on_result, niceness
        self.priority = f"nice {niceness}"  # how the worker thread is scheduled
        self.generator = torch.Generator().manual_seed(noise_seed)
        self._job: PlanJob | None = None
        self._seed: int | None = None  # to apply before the next job
        self._busy = False
        self._stopping = False
        self._wake = threading.Condition()
        self._cancel = threading.Event()  # the plan in flight is no longer wanted
        self.error: BaseException | None = None  # the last fault
        self.errors = 0  # faults so far
        self.cancelled = 0  # plans stopped in flight
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """A job is waiting or being planned."""
        with self._wake:
            return self._busy or self._job is not None

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        with self._wake:
            self._job = job
            if cancel and self._busy:
                self._cancel.set()
            self._wake.notify()

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node, from the next job on. The plan in
        flight and any job waiting (the last episode's, worthless now) are dropped; the plan
        draws from the generator until it stops, so the seed waits for the next job."""
        with self._wake:
            self._seed, self._job = noise_seed, None  # a job waiting is the last episode's too
            if self._busy:
                self._cancel.set()

    def shutdown(self, timeout: float = 5.0) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(timeout)

    def _run(self) -> None:
        if self._niceness and hasattr(os, "setpriority"):
            with contextlib.suppress(OSError):  # Linux: a thread is a process to setpriority
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self._niceness)
        while True:
            with self._wake:
                while self._job is None and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                job, self._job, self._busy = self._job, None, True
                self._cancel.clear()
                if self._seed is not None:
                    self.generator.manual_seed(self._seed)
                    self._seed = None
            try:
                began = time.perf_counter()
                chunk = self._plan(job, self.generator, self._cancel.is_set)
                self._on_result(PlanResult(job, chunk, time.perf_counter() - began))
            except Interrupted:
                self.cancelled += 1
            except Exception as error:  # reported by the owner; the worker keeps serving
                self.error, self.errors = error, self.errors + 1
                LOGGER.exception("planning failed")
            finally:
                with self._wake:
                    self._busy = False


def _send(connection: Connection, kind: str, payload: object) -> None:
    """(kind, pickled payload): the kind always reads back, even where the payload cannot (a
    class the other side cannot import), so every job gets its reply."""
    data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    connection.send_bytes(pickle.dumps((kind, data), protocol=pickle.HIGHEST_PROTOCOL))


def may_leave_idle(niceness: int) -> bool:
    """Whether a task of this process, its nice value raised by `niceness`, may go back from
    SCHED_IDLE to normal scheduling (Linux allows it with CAP_SYS_NICE, or within RLIMIT_NICE;
    root in a container often has neither): tried on a thread of its own, which then ends. The
    child inherits the same rights. Without them going idle would be one way."""
    if not hasattr(os, "SCHED_IDLE") or not Path("/proc/self/stat").exists():
        return False
    allowed: list[bool] = []

    def probe() -> None:
        thread = threading.get_native_id()
        try:
            os.setpriority(os.PRIO_PROCESS, thread,
                           os.getpriority(os.PRIO_PROCESS, thread) + niceness)
            os.sched_setscheduler(thread, os.SCHED_IDLE, os.sched_param(0))
            os.sched_setscheduler(thread, os.SCHED_OTHER, os.sched_param(0))
            allowed.append(True)
        except OSError:
            allowed.append(False)

    prober = threading.Thread(target=probe, name="scheduling_probe")
    prober.start()
    prober.join()
    return allowed == [True]


def scheduling(pid: int = 0) -> str:
    """How a process (0: this one) is scheduled: "idle" (SCHED_IDLE) or "nice <n>"."""
    if hasattr(os, "SCHED_IDLE") and os.sched_getscheduler(pid) == os.SCHED_IDLE:
        return "idle"
    return f"nice {os.getpriority(os.PRIO_PROCESS, pid)}"


def serve(descriptor: int, threads: int, niceness: int, idle: bool = False) -> None:
    """The child: plan each job with the planner and generator it was last given, until told
    to stop or the node's end of the socket closes (the node died)."""
    connection = Connection(descriptor)
    with contextlib.suppress(OSError, AttributeError):
        os.nice(niceness)  # kept if it goes back from idle to normal scheduling
        if idle:  # before torch starts threads: they inherit it
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    _send(connection, "scheduling", (scheduling(), 0.0))  # what it got, not what was asked
    torch.set_num_threads(threads)
    policy, planner, zones = None, None, None
    generator = torch.Generator()
    while True:
        try:
            kind, data = pickle.loads(connection.recv_bytes())
        except (EOFError, OSError):
            return
        if kind == "stop":
            return
        began = time.perf_counter()
        try:  # a fault is reported to the node; the child keeps serving
            payload = pickle.loads(data)
            if kind == "policy":
                policy = payload
            elif kind == "planner":
                planner = ConstrainedPlanner(policy, *payload)
            elif kind == "seed":
                generator.manual_seed(payload)
            elif kind == "job":
                job, same_zones = payload
                job = replace(job, zones=zones) if same_zones else job
                zones = job.zones
                # Any message while it plans makes the plan worthless (the node sends a job
                # only to an idle child): "cancel", a new seed or planner, "stop".
                _send(connection, "chunk", (plan_chunk(planner, job, generator, connection.poll),
                                            time.perf_counter() - began))
            # "cancel": the plan it stopped is answered already
        except Interrupted:
            _send(connection, "cancelled", (None, time.perf_counter() - began))
        except Exception as error:
            reply = "job_error" if kind == "job" else "error"  # only a job's reply ends it
            _send(connection, reply, (f"{type(error).__name__}: {error}",
                                      time.perf_counter() - began))


class CpuShare:
    """The share of a core a process got while it worked on one job, over `period` s or more
    (its CPU time against the wall clock's); windows that span two jobs, or time without one,
    are not judged: between jobs a planner rightly uses nothing."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._since: tuple[float, float, object] | None = None  # (wall s, CPU s, job)

    def share(self, now: float, cpu: float | None, job: object | None) -> float | None:
        """Fed a sample (wall s, CPU s, the job in flight or None); the share since the last
        sample of the same job at least `period` ago, else None."""
        since = self._since
        if job is None or cpu is None:
            self._since = None
        elif since is None or since[2] is not job:
            self._since = (now, cpu, job)
        elif now - since[0] >= self.period:
            self._since = (now, cpu, job)
            return (cpu - since[1]) / (now - since[0])
        return None

    def starved(self, now: float, cpu: float | None, job: object | None) -> float | None:
        """`share`, when it is under `STARVED_SHARE` (a planner starved); else None."""
        share = self.share(now, cpu, job)
        return share if share is not None and share < STARVED_SHARE else None


class PlanningProcess:
    """Plans one chunk at a time in a child process; results come back on a receiver thread.

    `submit` replaces a job not yet sent (only the newest matters), and with `cancel` stops the
    one in flight; a job goes to the child when it is idle, so `reseed` and `use` apply before
    the next job (they stop the one in flight too: it was for the old episode or planner).
    `on_result` is called on the receiver thread. The child runs `threads` torch threads and
    exits when the node's end of the socket closes, even if the node was killed.

    The child plans at idle priority (SCHED_IDLE) where the node may take it back: any other
    task that wakes, the middleware's threads and the robot's driver included, runs at once,
    where at a nice value it would wait out the planner's time slice. A machine kept busy by
    other work would starve it there; the receiver thread watches, and a child that gets less
    than `STARVED_SHARE` of a core while planning goes to normal scheduling at `niceness` for
    good. Elsewhere it plans at `niceness` throughout. `priority` says how the child is
    scheduled as the child itself reports it ("starting" until its report comes).
    """

    def __init__(self, planner: ConstrainedPlanner,
                 on_result: Callable[[PlanResult], None], noise_seed: int = 0,
                 threads: int = 1, niceness: int = 5, idle: bool = True,
                 name: str = "planning_process") -> None:
        self._on_result, self._niceness = on_result, niceness
        idle = idle and may_leave_idle(niceness)
        self.priority = "starting"  # how the child is scheduled, as it reports it
        self._starvation = CpuShare(WATCH_PERIOD_S)
        # A plain interpreter on a socket pair, not multiprocessing's spawn: that one would run
        # the caller's main script again in the child; fork is unsafe beside DDS threads.
        ours, theirs = socket.socketpair()
        package_root = str(Path(__file__).resolve().parents[2])
        environment = {**os.environ, "OMP_NUM_THREADS": str(threads),
                       "PYTHONPATH": os.pathsep.join(
                           filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
        code = (f"from {__name__} import serve; "
                f"serve({theirs.fileno()}, {threads}, {niceness}, {idle})")
        self._process = subprocess.Popen([sys.executable, "-c", code], env=environment,
                                         pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL)
        theirs.close()
        self._connection = Connection(ours.detach())
        self._lock = threading.Lock()  # in flight, pending and the sending end
        self._in_flight: PlanJob | None = None
        self._pending: PlanJob | None = None
        self._sent_zones: RestrictedArea | None = None
        self.error: BaseException | None = None  # the last fault
        self.errors = 0  # faults so far
        self.cancelled = 0  # plans stopped in flight
        self._stopping = False
        with self._lock:  # the weights once (they wait for the child to start reading)
            _send(self._connection, "policy", planner.policy)
        self.use(planner)
        self.reseed(noise_seed)
        self._receiver = threading.Thread(target=self._receive, name=f"{name}_receiver",
                                          daemon=True)
        self._receiver.start()

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def busy(self) -> bool:
        """A job is waiting or being planned."""
        with self._lock:
            return self._in_flight is not None or self._pending is not None

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        with self._lock:
            if self.error is not None and not self._process_alive():
                return  # nothing plans any more: the node reports `error`
            if self._in_flight is None:
                self._start(job)
                return
            self._pending = job
            if cancel:  # under the lock: it reaches the child before the pending job can
                self._tell_locked("cancel", None)

    def _process_alive(self) -> bool:
        return self._process.poll() is None

    def use(self, planner: ConstrainedPlanner) -> None:
        """Plan with another configuration (of the same policy) from the next job on; a few
        hundred bytes, so the caller never waits for the child to finish a plan."""
        self._tell("planner", (planner.config, planner.robot))

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node from the next job on (like any
        message, it stops the plan in flight; a job waiting is the last episode's too)."""
        with self._lock:
            self._pending = None
            self._tell_locked("seed", noise_seed)

    def _tell(self, kind: str, payload: object) -> None:
        with self._lock:
            self._tell_locked(kind, payload)

    def _tell_locked(self, kind: str, payload: object) -> None:
        try:
            _send(self._connection, kind, payload)
        except OSError as error:  # the child is gone: said once, by the receiver
            self._fail(f"planning process gone: {error}")

    def shutdown(self, timeout: float = 5.0) -> None:
        self._stopping = True
        with self._lock, contextlib.suppress(OSError, ValueError):
            _send(self._connection, "stop", None)
        try:
            self._process.wait(timeout)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(timeout)
        self._connection.close()
        self._receiver.join(timeout)

    def _start(self, job: PlanJob) -> None:
        """Send a job, its zones only when they are not the ones sent last (the child keeps
        those, and what it derived from them); the caller holds the lock. A job that cannot be
        sent is reported in `error` and dropped (the next one is asked for as usual)."""
        same = job.zones is not None and job.zones is self._sent_zones
        self._in_flight = job  # already: a send that waits for a starved child counts too
        try:
            _send(self._connection, "job", (replace(job, zones=None) if same else job, same))
        except (OSError, pickle.PicklingError, TypeError, AttributeError) as error:
            self._in_flight = None
            self._fail(f"cannot send a plan to the planning process: {type(error).__name__}: "
                       f"{error}")
            return
        self._sent_zones = job.zones

    def _fail(self, message: str) -> None:
        self.error, self.errors = RuntimeError(message), self.errors + 1
        LOGGER.error("planning process: %s", message)

    def _receive(self) -> None:
        while True:
            try:
                ready = self._connection.poll(WATCH_PERIOD_S)
                self._watch()
                if not ready:
                    continue
                kind, data = pickle.loads(self._connection.recv_bytes())
                payload, seconds = pickle.loads(data)
            except (EOFError, OSError):
                if not self._stopping:  # nothing more is planned: the node reports `error`
                    with self._lock:
                        self._in_flight = self._pending = None
                    self._fail(f"the planning process exited (code {self._process.wait()})")
                return
            if kind == "scheduling":
                self.priority = payload
                continue
            if kind == "chunk":
                if not self._stopping:
                    self._on_result(PlanResult(self._in_flight, np.asarray(payload), seconds))
            elif kind == "cancelled":
                self.cancelled += 1
            else:
                self._fail(payload)
                if kind == "error":
                    continue  # a configuration or seed that failed: no job ended
            with self._lock:  # not busy until the result is handed over
                self._in_flight = None
                if self._pending is not None and not self._stopping:
                    self._start(self._pending)
                self._pending = None

    def _watch(self) -> None:
        """At idle priority: a child starved by other work goes to normal scheduling."""
        if self.priority != "idle":
            return
        job = self._in_flight  # without the lock: a send in progress holds it
        share = self._starvation.starved(time.monotonic(), self._child_cpu_seconds(), job)
        if share is not None:
            self._leave_idle(share)

    def _child_cpu_seconds(self) -> float | None:
        """CPU time the child has used (all its threads), or None if it cannot be read."""
        try:
            fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime

    def _leave_idle(self, share: float) -> None:
        threads: list[str] = []
        with contextlib.suppress(OSError):  # the child is gone: the receiver says so
            threads = os.listdir(f"/proc/{self.pid}/task")
        for thread in threads:
            try:
                os.sched_setscheduler(int(thread), os.SCHED_OTHER, os.sched_param(0))
            except ProcessLookupError:  # a thread that ended meanwhile
                pass
            except OSError as error:  # not allowed after all: say so, and stop trying
                self.priority = "idle (starved: could not leave it)"
                LOGGER.error("planning process starved at idle priority (%.0f%% of a core) and "
                             "could not leave it: %s", 100 * share, error)
                return
        with contextlib.suppress(OSError):
            self.priority = scheduling(self.pid)
        LOGGER.warning("planning process got %.0f%% of a core at idle priority (the machine "
                       "is busy): normal scheduling (%s) from now on", 100 * share,
                       self.priority)
