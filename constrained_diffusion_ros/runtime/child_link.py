"""The node's side of the conversation with a planning child: which job goes when, and what
waits for the next child (`ChildLink`).

Kept apart from the supervision (planning_process.py), which starts children and reads their
replies on a thread of its own: here is the state both sides change, under one lock, and the
rules for it. Only the newest job matters, so a job waits in one slot until the child is idle;
the planner and seed in use are kept, so that a child started again gets them; and nothing a
caller sends ever waits for a child to be started or to read.
"""

from __future__ import annotations

import contextlib
import pickle
import threading
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection

from constrained_diffusion_ros.planning.plan_jobs import PlanJob, Request
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.planning_child import encode, send
from constrained_diffusion_ros.zones.area import RestrictedArea


class ChildLink:
    """Jobs, planner and seed for the child that is ready, or kept for the next one.

    `on_fault(message)` hears of a job that cannot be pickled (it is dropped: the next one is
    asked for as usual); `on_lost(message)` of a send that failed (the child is gone, or the
    stream is cut mid-message: the supervisor replaces it). Both are called under the lock.
    """

    def __init__(self, planner: ConstrainedPlanner, noise_seed: int,
                 on_fault: Callable[[str], None], on_lost: Callable[[str], None]) -> None:
        self._on_fault, self._on_lost = on_fault, on_lost
        self.planner_args = (planner.config, planner.robot)
        self.seed = noise_seed
        self.lock = threading.Lock()  # the state below and the sending end
        self._connection: Connection | None = None  # to a child that has what it needs
        self.in_flight: PlanJob | None = None  # read without the lock by the watch
        self._pending: PlanJob | None = None
        self._sent_zones: RestrictedArea | None = None
        self.gave_up = False
        self.stopping = False

    @property
    def ready(self) -> bool:
        """A child has what it needs to plan (jobs asked for before wait for it)."""
        with self.lock:
            return self._connection is not None

    @property
    def busy(self) -> bool:
        """A job is waiting or being planned."""
        with self.lock:
            return self.in_flight is not None or self._pending is not None

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        """Send `job` if the child is idle, else keep it in place of the one waiting; with
        `cancel`, stop the one in flight."""
        with self.lock:
            if self.gave_up:
                return  # nothing plans any more: the owner reports it
            if self._connection is not None and self.in_flight is None:
                self._start(job)
                return
            self._pending = job  # for the child to come, if none has what it needs
            if cancel and self.in_flight is not None:  # under the lock: it reaches the child
                self._tell(Request.CANCEL, None)  # before the pending job can

    def use(self, planner: ConstrainedPlanner) -> None:
        """Plan with another configuration (of the same policy) from the next job on; a few
        hundred bytes, so the caller never waits for the child to finish a plan."""
        with self.lock:
            self.planner_args = (planner.config, planner.robot)
            self._tell(Request.PLANNER, self.planner_args)

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node from the next job on (like any
        message, it stops the plan in flight; a job waiting is the last episode's too). A child
        started again mid-episode starts from this seed again."""
        with self.lock:
            self.seed, self._pending = noise_seed, None
            self._tell(Request.SEED, noise_seed)

    def attach(self, connection: Connection) -> bool:
        """A new child has read its weights: give it the planner and seed in use and the job
        waiting, and send to it from now on. False if the link is stopping. OSError if the
        child died meanwhile."""
        with self.lock:
            if self.stopping:
                return False
            send(connection, Request.PLANNER, self.planner_args)
            send(connection, Request.SEED, self.seed)
            self._connection, self._sent_zones = connection, None
            self._start_pending()
        return True

    def detach(self, connection: Connection | None) -> bool:
        """A child ended: forget its connection and the job it was planning (the controller
        asks again when it finds the worker idle). Whether the link is stopping."""
        with self.lock:
            if self._connection is connection:
                self._connection = None
            self.in_flight = None
            return self.stopping

    def done(self) -> None:
        """The job in flight ended (a plan, a cancellation, a fault): the one waiting goes."""
        with self.lock:
            self.in_flight = None
            if not self.stopping:
                self._start_pending()

    def give_up(self) -> None:
        with self.lock:
            self.gave_up, self._pending = True, None

    def stop(self) -> None:
        """Tell the child to stop (if one is ready) and send nothing more."""
        with self.lock:
            self.stopping = True
            connection, self._connection = self._connection, None
            if connection is not None:
                with contextlib.suppress(OSError, ValueError):
                    send(connection, Request.STOP, None)

    def _start_pending(self) -> None:
        if self._pending is not None and self._connection is not None:
            job, self._pending = self._pending, None
            self._start(job)

    def _start(self, job: PlanJob) -> None:
        """Send a job to the ready child, its zones only when they are not the ones sent last
        (the child keeps those, and what it derived from them). A job that cannot be sent dies
        with the child."""
        same = job.zones is not None and job.zones is self._sent_zones
        try:
            sent = encode(Request.JOB, (replace(job, zones=None) if same else job, same))
        except (pickle.PicklingError, TypeError, AttributeError) as error:
            self._on_fault(f"cannot send a plan to the planning process: "
                           f"{type(error).__name__}: {error}")
            return
        self.in_flight = job  # already: a send that waits for a starved child counts too
        try:
            self._connection.send_bytes(sent)
        except OSError as error:
            self._lose(f"cannot send a plan to the planning process: {error}")
            return
        self._sent_zones = job.zones

    def _tell(self, kind: Request, payload: object) -> None:
        """Send to the child if one is ready; else the next child gets it."""
        if self._connection is None:
            return
        try:
            send(self._connection, kind, payload)
        except OSError as error:
            self._lose(f"cannot send {str(kind)!r} to the planning process: {error}")

    def _lose(self, message: str) -> None:
        self._connection = None
        self._on_lost(message)
