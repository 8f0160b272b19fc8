"""The planning process: plans in a child process of its own, supervised (`PlanningProcess`).

Denoising runs hundreds of torch calls with Python between them, all under the interpreter's
lock, which the control clock and the zone callbacks need too; a child process has an
interpreter of its own, so the node's threads never wait behind planning, and a planner that
crashes does not take the node with it, as LeRobot's asynchronous inference keeps the policy in
a server of its own. One job per module: what the child runs and the messages both sides speak
(planning_child.py), its scheduling and the watch that keeps idle priority from starving it
(priority_watch.py), which job goes to the child when (child_link.py), and here the
supervision.

Supervision: the child runs `threads` torch threads and exits when the node's end of the socket
closes, even if the node was killed. One that dies (killed, out of memory, a crash in torch) is
started again after 0.5, 1, 2, 4, 8 s, and given the weights, the planner and seed in use and
the job waiting, if any. The job in flight dies with it: its observations are old by then, and
it may be what killed the child; the controller, finding the worker idle, asks again from its
newest observations. After `restart_limit` restarts in a row with no plan between them it gives
up and says so in `error`. Callers never wait for any of this: what they send meanwhile is kept
for the next child. The child plans at idle priority (SCHED_IDLE) where the node may take it
back, watched by the receiver thread so that a busy machine does not starve it
(`PriorityWatch`); elsewhere at `niceness` throughout.
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import subprocess
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, Reply, Request
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.child_link import ChildLink
from constrained_diffusion_ros.runtime.os_scheduling import may_leave_idle
from constrained_diffusion_ros.runtime.planning_child import encode, reap, spawn, unread
from constrained_diffusion_ros.runtime.priority_watch import WATCH_PERIOD_S, PriorityWatch
from constrained_diffusion_ros.zones.plugins import ZoneCheckError

LOGGER = logging.getLogger(__name__)

RESTART_LIMIT = 5  # children started in a row with no plan between them, before giving up
RESTART_DELAY_S = 0.5  # before the first restart; doubled for each next one in a row
RESTART_DELAY_MAX_S = 8.0


@dataclass
class Restarts:
    """When a child that died is started again: after a wait that doubles with each restart in
    a row, up to `delay_max`, until `limit` restarts in a row brought no plan (a plan that
    arrives sets `in_a_row` back to 0)."""

    limit: int = RESTART_LIMIT
    delay: float = RESTART_DELAY_S
    delay_max: float = RESTART_DELAY_MAX_S
    in_a_row: int = 0

    def next_wait(self) -> float | None:
        """Seconds to wait before the next restart; None: give up."""
        if self.in_a_row >= self.limit:
            return None
        wait = min(self.delay * 2 ** self.in_a_row, self.delay_max)
        self.in_a_row += 1
        return wait


class PlanningProcess:
    """Plans one chunk at a time in a child process; results come back on a receiver thread.

    `submit` replaces a job not yet sent (only the newest matters), and with `cancel` stops the
    one in flight; a job goes to the child when it is idle, so `reseed` and `use` apply before
    the next job (they stop the one in flight too: it was for the old episode or planner).
    `on_result` is called on the receiver thread, which also supervises the child (above).
    `failed` is True from a fault until the next plan arrives, `error` holds the last fault,
    `restarts` counts the children started again; `priority` says how the child is scheduled
    as the child itself reports it ("starting" until its report comes).
    """

    def __init__(self, planner: ConstrainedPlanner,
                 on_result: Callable[[PlanResult], None], noise_seed: int = 0,
                 threads: int = 1, niceness: int = 5, idle: bool = True,
                 name: str = "planning_process", restart_limit: int = RESTART_LIMIT,
                 restart_delay: float = RESTART_DELAY_S,
                 restart_delay_max: float = RESTART_DELAY_MAX_S) -> None:
        self._on_result, self._niceness, self._threads = on_result, niceness, threads
        self._idle = idle and may_leave_idle(niceness)
        self._restarts = Restarts(restart_limit, restart_delay, restart_delay_max)
        self.watch = PriorityWatch()  # how the child is scheduled, and the starvation watch
        # The weights pickled once, for every child (a restart costs the node no interpreter
        # time); the link keeps the planner, the seed and the job waiting for it.
        self._weights = encode(Request.POLICY, planner.policy)
        self._link = ChildLink(planner, noise_seed, self._fail, self._lost)
        self._stopped = threading.Event()  # wakes the supervisor out of a restart's wait
        self.error: BaseException | None = None  # the last fault
        self.errors, self.failed = 0, False  # faults so far; one since the last plan came
        self.restarts = 0  # children started again after one died
        self.cancelled = 0  # plans stopped in flight
        # The child starts its interpreter while the node goes on starting: the weights and
        # what follows go to it from the receiver thread, and a job asked for meanwhile waits.
        self._process, connection = spawn(self._threads, self._niceness, self._idle)
        self._receiver = threading.Thread(target=self._supervise, args=(connection, None),
                                          name=f"{name}_receiver", daemon=True)
        self._receiver.start()

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def priority(self) -> str:
        """How the child is scheduled, as it reports it ("starting" until its report comes)."""
        return self.watch.priority

    @property
    def ready(self) -> bool:
        return self._link.ready

    @property
    def busy(self) -> bool:
        return self._link.busy

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        self._link.submit(job, cancel)

    def use(self, planner: ConstrainedPlanner) -> None:
        self._link.use(planner)

    def reseed(self, noise_seed: int) -> None:
        self._link.reseed(noise_seed)

    def shutdown(self, timeout: float = 5.0) -> None:
        self._link.stop()
        self._stopped.set()
        reap(self._process, timeout)
        self._receiver.join(timeout)

    def _lost(self, message: str) -> None:
        """A send failed (the child gone, or the stream cut mid-message): it is killed to be
        sure, and the supervisor starts another; what is sent meanwhile waits for it."""
        self.failed = True
        LOGGER.warning("planning process: %s", message)
        with contextlib.suppress(OSError):
            self._process.kill()

    def _fail(self, message: str) -> None:
        """A fault, kept in `error`: a zone check's as the `ZoneCheckError` it was in the child
        (the chunk loop says it, and stops the pusher), any other logged here."""
        zone_check = message.removeprefix(f"{ZoneCheckError.__name__}: ")
        if zone_check != message:
            self.error, self.errors, self.failed = ZoneCheckError(zone_check), self.errors + 1, True
            return
        self.error, self.errors, self.failed = RuntimeError(message), self.errors + 1, True
        LOGGER.error("planning process: %s", message)

    # -- the receiver thread: supervision and replies -----------------------------------------

    def _supervise(self, connection: Connection, ready: bool | None) -> None:
        """Serve the child (given its weights first if `ready` is None) until it dies, then
        start another as `Restarts` says. Runs on the receiver thread: the callers of `submit`
        never wait for it."""
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
            restarts = self._restarts
            wait = restarts.next_wait()
            if wait is None:
                self._link.give_up()
                self._fail(f"{death}; {restarts.in_a_row} restarts in a row brought no plan: "
                           f"gave up, nothing plans any more")
                return
            self._fail(f"{death}; restarting it in {wait:g} s ({restarts.in_a_row} of "
                       f"{restarts.limit} in a row)")
            if self._stopped.wait(wait):
                return
            try:
                process, connection = spawn(self._threads, self._niceness, self._idle)
            except OSError as error:  # out of memory or of processes: counted as a death
                process, death = None, f"cannot start a planning process: {error}"
                continue
            with self._link.lock:
                stopping = self._link.stopping
                if not stopping:
                    self._process = process
                    self.restarts += 1
                    self.watch.child_started()
            if stopping:  # shut down meanwhile: the child reads the end of its socket and exits
                connection.close()
                reap(process)
                return
            ready = self._handshake(connection)

    def _handshake(self, connection: Connection) -> bool:
        """Give a new child the weights, without the lock (they take a while to read: the
        callers do not wait for it); once it has read them, the planner and seed in use and the
        job waiting, which then go at once. From then on callers send to it. False if it died
        or the worker was shut down first."""
        try:
            connection.send_bytes(self._weights)
            while unread(connection):  # whatever goes under the lock must not wait for it
                if self._stopped.wait(0.005):
                    return False
            return self._link.attach(connection)
        except OSError:
            return False

    def _bury(self, process: subprocess.Popen, connection: Connection | None) -> str | None:
        """After a child's end: forget its connection and the job it was planning (the
        controller asks again when it finds the worker idle). What it died of, or None when it
        was told to stop."""
        stopping = self._link.detach(connection)
        if connection is not None:
            connection.close()
        code = reap(process)
        return None if stopping else f"the planning process exited (code {code})"

    def _receive(self, connection: Connection) -> None:
        """Hand over the child's replies until its end of the socket closes."""
        while True:
            try:
                ready = connection.poll(WATCH_PERIOD_S)
                # without the lock: a send in progress holds it
                self.watch.check(self.pid, self._link.in_flight)
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
                self.watch.priority = payload
                continue
            if kind == Reply.CHUNK:
                self._restarts.in_a_row, self.failed = 0, False  # before the owner hears of it
                if not self._link.stopping:
                    self._offer(PlanResult(self._link.in_flight, np.asarray(payload),
                                           seconds))
            elif kind == Reply.CANCELLED:
                self.cancelled += 1
            else:
                self._fail(payload)
                if kind == Reply.ERROR:
                    continue  # a configuration or seed that failed: no job ended
            self._link.done()  # not busy until the result is handed over

    def _offer(self, result: PlanResult) -> None:
        try:
            self._on_result(result)
        except Exception as error:  # the owner's fault: the receiver keeps serving
            LOGGER.exception("planning process: the result's handler failed")
            self.error, self.errors, self.failed = error, self.errors + 1, True
