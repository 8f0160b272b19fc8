"""The planning process: plans in a child process of its own, supervised (`PlanWorker`).

Denoising runs hundreds of torch calls with Python between them, all under the interpreter's
lock, which the control clock and the zone callbacks need too; a child process has an
interpreter of its own, so the node's threads never wait behind planning, and a planner that
crashes does not take the node with it, as LeRobot's asynchronous inference keeps the policy in
a server of its own. The child is a plain interpreter started on a command line that names this
module (`child_command`) and runs `serve`; the node and the child speak over a socket pair in
the messages of plan_jobs.py (`Request`, `Reply`).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import pickle
import socket
import struct
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import torch

from constrained_diffusion_ros.planning.plan_jobs import (
    PlanJob,
    PlanResult,
    Reply,
    Request,
    plan_chunk,
)
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.os_scheduling import (
    CpuShare,
    may_leave_idle,
    process_sample,
    scheduling,
)
from constrained_diffusion_ros.sampling.sampler import Interrupted
from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.plugins import ZoneCheckError

LOGGER = logging.getLogger(__name__)

WATCH_PERIOD_S = 0.5  # how often the node looks at what the planning process gets
IDLE_RETRY_S = 60.0  # at normal scheduling after starving, before idle priority is tried again
IDLE_RETRY_MAX_S = 960.0  # the wait doubles at each try, up to this
RESTART_LIMIT = 5  # children started in a row with no plan between them, before giving up
RESTART_DELAY_S = 0.5  # before the first restart; doubled for each next one in a row
RESTART_DELAY_MAX_S = 8.0


def _message(kind: Request | Reply, payload: object) -> bytes:
    """(kind, pickled payload): the kind always reads back, even where the payload cannot (a
    class the other side cannot import), so every job gets its reply. The kind goes as a plain
    string."""
    data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    return pickle.dumps((str(kind), data), protocol=pickle.HIGHEST_PROTOCOL)


def _send(connection: Connection, kind: Request | Reply, payload: object) -> None:
    connection.send_bytes(_message(kind, payload))


def serve(descriptor: int, threads: int, niceness: int, idle: bool = False) -> None:
    """The child: plan each job with the planner and generator it was last given, until told
    to stop or the node's end of the socket closes (the node died, even by SIGKILL: then a
    plan in flight stops, its answer cannot be sent, and the child exits without a word)."""
    connection = Connection(descriptor)
    with contextlib.suppress(OSError, EOFError):  # the node is gone: nobody to answer
        _serve(connection, threads, niceness, idle)


def _serve(connection: Connection, threads: int, niceness: int, idle: bool) -> None:
    """`serve`'s loop; returns when told to stop, raises OSError or EOFError when the node's
    end of the socket is closed."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(niceness)  # kept if it goes back from idle to normal scheduling
        if idle:  # before torch starts threads: they inherit it
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    _send(connection, Reply.SCHEDULING, (scheduling(), 0.0))  # what it got, not what was asked
    torch.set_num_threads(threads)
    policy, planner, zones = None, None, None
    generator = torch.Generator()
    while True:
        kind, data = pickle.loads(connection.recv_bytes())
        if kind == Request.STOP:
            return
        began = time.perf_counter()
        try:  # a fault is reported to the node; the child keeps serving
            payload = pickle.loads(data)
            if kind == Request.POLICY:
                policy = payload
            elif kind == Request.PLANNER:
                planner = ConstrainedPlanner(policy, *payload)
                planner.prepare_sampling()  # before the first job, not in it
            elif kind == Request.SEED:
                generator.manual_seed(payload)
            elif kind == Request.JOB:
                job, same_zones = payload
                job = replace(job, zones=zones) if same_zones else job
                zones = job.zones
                # Any message while it plans makes the plan worthless (the node sends a job
                # only to an idle child): a cancel, a new seed or planner, a stop.
                chunk = plan_chunk(planner, job, generator, connection.poll)
            # Request.CANCEL: the plan it stopped is answered already
        except Interrupted:
            _send(connection, Reply.CANCELLED, (None, time.perf_counter() - began))
            continue
        except Exception as error:
            # Only a job's reply ends it.
            reply = Reply.JOB_ERROR if kind == Request.JOB else Reply.ERROR
            _send(connection, reply, (f"{type(error).__name__}: {error}",
                                      time.perf_counter() - began))
            continue
        if kind == Request.JOB:  # outside the try: a send that fails is the node gone
            _send(connection, Reply.CHUNK, (chunk, time.perf_counter() - began))


def _unread(connection: Connection) -> int:
    """Bytes sent on a socket that its peer has not read yet (0 where that cannot be told)."""
    try:
        queued = fcntl.ioctl(connection.fileno(), termios.TIOCOUTQ, bytes(4))
    except OSError:
        return 0
    return struct.unpack("i", queued)[0]


def child_command(descriptor: int, threads: int, niceness: int, idle: bool) -> list[str]:
    """The planning child's command line: a plain interpreter that runs `serve`."""
    # SIGINT ignored: Ctrl-C in a terminal reaches the whole process group, and the child ends
    # with its node (told to stop, or finding the socket closed), not with a traceback.
    code = (f"import signal; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            f"from {__name__} import serve; serve({descriptor}, {threads}, {niceness}, {idle})")
    return [sys.executable, "-c", code]


class PlanningProcess:
    """Plans one chunk at a time in a child process; results come back on a receiver thread.

    `submit` replaces a job not yet sent (only the newest matters), and with `cancel` stops the
    one in flight; a job goes to the child when it is idle, so `reseed` and `use` apply before
    the next job (they stop the one in flight too: it was for the old episode or planner).
    `on_result` is called on the receiver thread. The child runs `threads` torch threads and
    exits when the node's end of the socket closes, even if the node was killed.

    The receiver thread supervises the child: one that dies (killed, out of memory, a crash in
    torch) is started again after 0.5, 1, 2, 4, 8 s, and given the weights, the planner and
    seed in use and the job waiting, if any. The job in flight dies with it: its observations
    are old by then, and it may be what killed the child; the controller, finding the worker
    idle, asks again from its newest observations. After `restart_limit` restarts in a row with
    no plan between them it gives up and says so in `error`. Callers never wait for any of
    this: what they send meanwhile is kept for the next child. `failed` is True from a fault
    until the next plan arrives; `restarts` counts the children started again.

    The child plans at idle priority (SCHED_IDLE) where the node may take it back: any other
    task that wakes, the middleware's threads and the robot's driver included, runs at once,
    where at a nice value it would wait out the planner's time slice. A machine kept busy by
    other work would starve it there; the receiver thread watches, and a child that gets less
    than `STARVED_SHARE` of a core while planning (time it spent stopped not counted) goes to
    normal scheduling at `niceness`, and back to idle after `IDLE_RETRY_S`, a wait that doubles
    each time (a machine still busy sends it back at once). Elsewhere it plans at `niceness`
    throughout. `priority` says how the child is scheduled as the child itself reports it
    ("starting" until its report comes).
    """

    def __init__(self, planner: ConstrainedPlanner,
                 on_result: Callable[[PlanResult], None], noise_seed: int = 0,
                 threads: int = 1, niceness: int = 5, idle: bool = True,
                 name: str = "planning_process", restart_limit: int = RESTART_LIMIT,
                 restart_delay: float = RESTART_DELAY_S,
                 restart_delay_max: float = RESTART_DELAY_MAX_S) -> None:
        self._on_result, self._niceness, self._threads = on_result, niceness, threads
        self._idle = idle and may_leave_idle(niceness)
        self._restart_limit, self._restart_delay = restart_limit, restart_delay
        self._restart_delay_max = restart_delay_max
        self.priority = "starting"  # how the child is scheduled, as it reports it
        self._starvation = CpuShare(WATCH_PERIOD_S)
        self._left_idle_at: float | None = None  # monotonic s, when starving sent it off idle
        self._idle_retry = IDLE_RETRY_S
        # What every child is given before its first job: the weights pickled once (a restart
        # then costs the node no interpreter time), the planner and the seed in use.
        self._weights = _message(Request.POLICY, planner.policy)
        self._planner_args = (planner.config, planner.robot)
        self._seed = noise_seed
        package_root = str(Path(__file__).resolve().parents[2])
        self._environment = {**os.environ, "OMP_NUM_THREADS": str(threads),
                             "PYTHONPATH": os.pathsep.join(
                                 filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
        self._lock = threading.Lock()  # the state below and the sending end
        self._connection: Connection | None = None  # to a child that has what it needs
        self._in_flight: PlanJob | None = None
        self._pending: PlanJob | None = None
        self._sent_zones: RestrictedArea | None = None
        self._gave_up = False
        self._stopping = False
        self._stopped = threading.Event()  # wakes the supervisor out of a restart's wait
        self._in_a_row = 0  # restarts since the last plan arrived
        self.error: BaseException | None = None  # the last fault
        self.errors = 0  # faults so far
        self.failed = False  # a fault since the last plan arrived
        self.restarts = 0  # children started again after one died
        self.cancelled = 0  # plans stopped in flight
        self._watch_failed = False
        # The child starts its interpreter while the node goes on starting: the weights and
        # what follows go to it from the receiver thread, and a job asked for meanwhile waits.
        self._process, connection = self._spawn()
        self._receiver = threading.Thread(target=self._supervise, args=(connection, None),
                                          name=f"{name}_receiver", daemon=True)
        self._receiver.start()

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def ready(self) -> bool:
        """A child has what it needs to plan (jobs asked for before wait for it)."""
        with self._lock:
            return self._connection is not None

    @property
    def busy(self) -> bool:
        """A job is waiting or being planned."""
        with self._lock:
            return self._in_flight is not None or self._pending is not None

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        with self._lock:
            if self._gave_up:
                return  # nothing plans any more: the node reports `error`
            if self._connection is not None and self._in_flight is None:
                self._start(job)
                return
            self._pending = job  # for the child to come, if none has what it needs
            if cancel and self._in_flight is not None:  # under the lock: it reaches the child
                self._tell_locked(Request.CANCEL, None)  # before the pending job can

    def use(self, planner: ConstrainedPlanner) -> None:
        """Plan with another configuration (of the same policy) from the next job on; a few
        hundred bytes, so the caller never waits for the child to finish a plan."""
        with self._lock:
            self._planner_args = (planner.config, planner.robot)
            self._tell_locked(Request.PLANNER, self._planner_args)

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node from the next job on (like any
        message, it stops the plan in flight; a job waiting is the last episode's too). A child
        started again mid-episode starts from this seed again."""
        with self._lock:
            self._seed, self._pending = noise_seed, None
            self._tell_locked(Request.SEED, noise_seed)

    def _tell_locked(self, kind: Request, payload: object) -> None:
        """Send to the child if one is ready; else the next child gets it (the caller holds
        the lock)."""
        if self._connection is None:
            return
        try:
            _send(self._connection, kind, payload)
        except OSError as error:
            self._lost_locked(f"cannot send {str(kind)!r} to the planning process: {error}")

    def _lost_locked(self, message: str) -> None:
        """A send failed: the child is gone, or the stream is cut mid-message. It is killed to
        be sure, and the supervisor starts another; until then, what is sent waits for it."""
        self._connection = None
        self.failed = True
        LOGGER.warning("planning process: %s", message)
        with contextlib.suppress(OSError):
            self._process.kill()

    def shutdown(self, timeout: float = 5.0) -> None:
        with self._lock:
            self._stopping = True
            process, connection, self._connection = self._process, self._connection, None
            if connection is not None:
                with contextlib.suppress(OSError, ValueError):
                    _send(connection, Request.STOP, None)
        self._stopped.set()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout)
        self._receiver.join(timeout)

    def _start(self, job: PlanJob) -> None:
        """Send a job to the ready child, its zones only when they are not the ones sent last
        (the child keeps those, and what it derived from them); the caller holds the lock. A
        job that cannot be pickled is reported in `error` and dropped (the next one is asked
        for as usual); one that cannot be sent dies with the child."""
        same = job.zones is not None and job.zones is self._sent_zones
        try:
            message = _message(Request.JOB, (replace(job, zones=None) if same else job, same))
        except (pickle.PicklingError, TypeError, AttributeError) as error:
            self._fail(f"cannot send a plan to the planning process: {type(error).__name__}: "
                       f"{error}")
            return
        self._in_flight = job  # already: a send that waits for a starved child counts too
        try:
            self._connection.send_bytes(message)
        except OSError as error:
            self._lost_locked(f"cannot send a plan to the planning process: {error}")
            return
        self._sent_zones = job.zones

    def _fail(self, message: str) -> None:
        """A fault, kept in `error`: a zone check's as the `ZoneCheckError` it was in the child
        (the chunk loop says it, and stops the pusher), any other logged here."""
        zone_check = message.removeprefix(f"{ZoneCheckError.__name__}: ")
        if zone_check != message:
            self.error, self.errors, self.failed = ZoneCheckError(zone_check), self.errors + 1, True
            return
        self.error, self.errors, self.failed = RuntimeError(message), self.errors + 1, True
        LOGGER.error("planning process: %s", message)

    # -- the receiver thread: supervision, replies and the priority watch -------------------

    def _spawn(self) -> tuple[subprocess.Popen, Connection]:
        """A new child on a socket pair: a plain interpreter, not multiprocessing's spawn (that
        one would run the caller's main script again in the child); fork is unsafe beside DDS
        threads."""
        ours, theirs = socket.socketpair()
        try:
            process = subprocess.Popen(
                child_command(theirs.fileno(), self._threads, self._niceness, self._idle),
                env=self._environment, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        return process, Connection(ours.detach())

    def _supervise(self, connection: Connection, ready: bool | None) -> None:
        """Serve the child (given its weights first if `ready` is None) until it dies, then
        start another after a growing wait, until `restart_limit` restarts in a row bring no
        plan (a plan that arrives resets the count). Runs on the receiver thread: the callers
        of `submit` never wait for it."""
        process: subprocess.Popen | None = self._process
        death = ""
        if ready is None:
            ready = self._handshake(connection)
        while True:
            if process is not None:
                if ready:
                    self._receive(connection)
                death = self._bury(process, connection)
                if death is None:
                    return  # shut down
            if self._in_a_row >= self._restart_limit:
                with self._lock:
                    self._gave_up, self._pending = True, None
                self._fail(f"{death}; {self._in_a_row} restarts in a row brought no plan: gave "
                           f"up, nothing plans any more")
                return
            delay = min(self._restart_delay * 2 ** self._in_a_row, self._restart_delay_max)
            self._in_a_row += 1
            self._fail(f"{death}; restarting it in {delay:g} s ({self._in_a_row} of "
                       f"{self._restart_limit} in a row)")
            if self._stopped.wait(delay):
                return
            try:
                process, connection = self._spawn()
            except OSError as error:  # out of memory or of processes: counted as a death
                process, death = None, f"cannot start a planning process: {error}"
                continue
            with self._lock:
                stopping = self._stopping
                if not stopping:
                    self._process = process
                    self.restarts += 1
                    self.priority = "starting"
                    self._starvation, self._left_idle_at = CpuShare(WATCH_PERIOD_S), None
            if stopping:  # shut down meanwhile: the child reads the end of its socket and exits
                connection.close()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(5.0)
                return
            ready = self._handshake(connection)

    def _handshake(self, connection: Connection) -> bool:
        """Give a new child the weights, without the lock (they take a while to read: the
        callers do not wait for it); once it has read them, the planner and seed in use and the
        job waiting, which then go at once. From then on callers send to it. False if it died
        or the worker was shut down first."""
        try:
            connection.send_bytes(self._weights)
            while _unread(connection):  # whatever goes under the lock must not wait for it
                if self._stopped.wait(0.005):
                    return False
            with self._lock:
                if self._stopping:
                    return False
                _send(connection, Request.PLANNER, self._planner_args)
                _send(connection, Request.SEED, self._seed)
                self._connection, self._sent_zones = connection, None
                if self._pending is not None:
                    job, self._pending = self._pending, None
                    self._start(job)
        except OSError:
            return False
        return True

    def _bury(self, process: subprocess.Popen, connection: Connection | None) -> str | None:
        """After a child's end: forget its connection and the job it was planning (the
        controller asks again when it finds the worker idle). What it died of, or None when it
        was told to stop."""
        with self._lock:
            if self._connection is connection:
                self._connection = None
            self._in_flight = None
            stopping = self._stopping
        if connection is not None:
            connection.close()
        try:
            code = process.wait(5.0)
        except subprocess.TimeoutExpired:  # its socket closed, yet it lives: not to be trusted
            process.kill()
            code = process.wait()
        return None if stopping else f"the planning process exited (code {code})"

    def _receive(self, connection: Connection) -> None:
        """Hand over the child's replies until its end of the socket closes."""
        while True:
            try:
                ready = connection.poll(WATCH_PERIOD_S)
                self._watch_safely()
                if not ready:
                    continue
                message = connection.recv_bytes()
            except (EOFError, OSError):
                return
            try:
                kind, data = pickle.loads(message)
                payload, seconds = pickle.loads(data)
            except Exception as error:  # a reply that cannot be read: the child is replaced
                LOGGER.error("planning process: unreadable reply (%s): restarting it", error)
                with contextlib.suppress(OSError):
                    self._process.kill()
                return
            if kind == Reply.SCHEDULING:
                self.priority = payload
                continue
            if kind == Reply.CHUNK:
                self._in_a_row, self.failed = 0, False  # before the owner hears of it
                if not self._stopping:
                    self._offer(PlanResult(self._in_flight, np.asarray(payload), seconds))
            elif kind == Reply.CANCELLED:
                self.cancelled += 1
            else:
                self._fail(payload)
                if kind == Reply.ERROR:
                    continue  # a configuration or seed that failed: no job ended
            with self._lock:  # not busy until the result is handed over
                self._in_flight = None
                if (self._pending is not None and self._connection is not None
                        and not self._stopping):
                    job, self._pending = self._pending, None
                    self._start(job)

    def _offer(self, result: PlanResult) -> None:
        try:
            self._on_result(result)
        except Exception as error:  # the owner's fault: the receiver keeps serving
            LOGGER.exception("planning process: the result's handler failed")
            self.error, self.errors, self.failed = error, self.errors + 1, True

    def _watch_safely(self) -> None:
        """`_watch`, whose fault must not end the receiver thread (nor supervision with it)."""
        try:
            self._watch()
        except Exception:
            if not self._watch_failed:  # said once: it would fail every period
                LOGGER.exception("planning process: watching its priority failed")
            self._watch_failed = True

    def _watch(self) -> None:
        """At idle priority: a child starved by other work goes to normal scheduling. Off it
        after starving: back to idle once the wait is over."""
        now = time.monotonic()
        if self.priority == "idle":
            job = self._in_flight  # without the lock: a send in progress holds it
            cpu, stopped = process_sample(self.pid)
            if stopped:  # it asked for nothing: no window spans the stop
                self._starvation.share(now, cpu, job, stopped=True)
                return
            share = self._starvation.starved(now, cpu, job)
            if share is not None:
                self._leave_idle(share)
        elif self._left_idle_at is not None and now - self._left_idle_at >= self._idle_retry:
            self._return_to_idle()

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
        self._left_idle_at = time.monotonic()
        LOGGER.warning("planning process got %.0f%% of a core at idle priority (the machine "
                       "is busy): normal scheduling (%s) for %g s", 100 * share,
                       self.priority, self._idle_retry)

    def _return_to_idle(self) -> None:
        """The machine may be quiet again: idle priority once more (a task may always lower
        its own). Starved again, the child leaves it at once, and waits twice as long."""
        self._left_idle_at = None
        self._idle_retry = min(2 * self._idle_retry, IDLE_RETRY_MAX_S)
        threads: list[str] = []
        with contextlib.suppress(OSError):
            threads = os.listdir(f"/proc/{self.pid}/task")
        for thread in threads:
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setscheduler(int(thread), os.SCHED_IDLE, os.sched_param(0))
        self._starvation = CpuShare(WATCH_PERIOD_S)  # judged afresh, at idle
        with contextlib.suppress(OSError):
            self.priority = scheduling(self.pid)
        LOGGER.info("planning process: back to idle priority (%s)", self.priority)
