"""The thread worker: plans in a thread of the node's own process (`PlanWorker`).

Denoising runs hundreds of torch calls with Python between them, all under the interpreter's
lock, which the control clock and the zone callbacks need too: beside a planning thread they may
wait for it, which a child process with an interpreter of its own (planning_process.py) avoids.
The node plans in a child process unless `planning_process:=false`; this worker needs no second
interpreter, no pickling and no copy of the weights.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable

import numpy as np
import torch

from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, plan_chunk
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.newest_job import NewestJobThread
from constrained_diffusion_ros.sampling.sampler import Interrupted
from constrained_diffusion_ros.zones.plugins import ZoneCheckError

LOGGER = logging.getLogger(__name__)


class PlanningThread(NewestJobThread):
    """A worker thread that plans one chunk at a time, off the control thread.

    `submit` replaces any job not yet started (only the newest request matters), and with
    `cancel` stops the one in flight before its next denoising step; a result is
    offered to `on_result` with its job, whose generation the owner compares with its own to
    drop plans that a zone or configuration change made stale. The worker draws from its own
    random generator and runs at a lower CPU priority than the process's other threads, so the
    control clock is never kept waiting by planning. Owns its thread like tf2_ros's listener:
    `shutdown()` stops and joins it.
    """

    def __init__(self, planner: ConstrainedPlanner, on_result: Callable[[PlanResult], None],
                 noise_seed: int = 0, niceness: int = 5, name: str = "planning_thread",
                 plan: Callable[[ConstrainedPlanner, PlanJob, torch.Generator,
                                 Callable[[], bool]], np.ndarray] = plan_chunk) -> None:
        """`plan` plans a job (by default `plan_chunk`; tests slow it or make it fail)."""
        super().__init__(self._run, name)
        self.planner, self._plan = planner, plan
        self._on_result, self._niceness = on_result, niceness
        self.priority = f"nice {niceness}"  # how the worker thread is scheduled
        self.generator = torch.Generator().manual_seed(noise_seed)
        self._job: PlanJob | None = None
        self._seed: int | None = None  # to apply before the next job
        self._busy = False
        self._cancel = threading.Event()  # the plan in flight is no longer wanted
        self.error: BaseException | None = None  # the last fault
        self.errors = 0  # faults so far
        self.failed = False  # a fault since the last plan offered
        self.restarts = 0  # never: a fault of one plan does not end the thread
        self.cancelled = 0  # plans stopped in flight
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

    def use(self, planner: ConstrainedPlanner) -> None:
        """From the next job on (read when a job starts)."""
        self.planner = planner

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node, from the next job on. The plan in
        flight and any job waiting (the last episode's, worthless now) are dropped; the plan
        draws from the generator until it stops, so the seed waits for the next job."""
        with self._wake:
            self._seed, self._job = noise_seed, None  # a job waiting is the last episode's too
            if self._busy:
                self._cancel.set()

    def _run(self) -> None:
        if self._niceness and hasattr(os, "setpriority"):
            with contextlib.suppress(OSError):  # Linux: a thread is a process to setpriority
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self._niceness)
        while True:
            with self._wake:
                if not self._wait_for_job():
                    return
                job, self._job, self._busy = self._job, None, True
                self._cancel.clear()
                if self._seed is not None:
                    self.generator.manual_seed(self._seed)
                    self._seed = None
            try:
                began = time.perf_counter()
                chunk = self._plan(self.planner, job, self.generator, self._cancel.is_set)
                self.failed = False  # before the owner hears of it: planning works again
                self._on_result(PlanResult(job, chunk, time.perf_counter() - began))
            except Interrupted:
                self.cancelled += 1
            except ZoneCheckError as error:  # said by the chunk loop, which stops the pusher
                self.error, self.errors, self.failed = error, self.errors + 1, True
            except Exception as error:  # reported by the owner; the worker keeps serving
                self.error, self.errors, self.failed = error, self.errors + 1, True
                LOGGER.exception("planning failed")
            finally:
                with self._wake:
                    self._busy = False
