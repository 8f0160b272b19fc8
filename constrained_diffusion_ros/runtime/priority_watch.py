"""How the planning child is scheduled, and the watch that keeps idle priority from starving it.

The child plans at idle priority (SCHED_IDLE) where the node may take it back: any other task
that wakes, the middleware's threads and the robot's driver included, runs at once, where at a
nice value it would wait out the planner's time slice. A machine kept busy by other work would
starve it there. `PriorityWatch.check`, called by the planning process's receiver thread every
`WATCH_PERIOD_S`, sends a child that gets less than `STARVED_SHARE` (os_scheduling.py) of a
core while planning (time it spent stopped not counted) to normal scheduling at its nice value,
and back to idle after `IDLE_RETRY_S`, a wait that doubles each time (a machine still busy sends
it back at once). What it asks of the operating system, os_scheduling.py does.
"""

from __future__ import annotations

import contextlib
import logging
import time

from constrained_diffusion_ros.runtime.os_scheduling import (
    CpuShare,
    process_sample,
    schedule_process,
    scheduling,
)

LOGGER = logging.getLogger(__name__)

WATCH_PERIOD_S = 0.5  # how often the node looks at what the planning process gets
IDLE_RETRY_S = 60.0  # at normal scheduling after starving, before idle priority is tried again
IDLE_RETRY_MAX_S = 960.0  # the wait doubles at each try, up to this


class PriorityWatch:
    """The planning child's scheduling as it reports it (`priority`: "starting" until its
    report comes, then "idle" or "nice <n>"), and the starvation watch over it. Used from the
    receiver thread only (its reads of `priority` elsewhere are of a string)."""

    def __init__(self) -> None:
        self.priority = "starting"
        self.idle_retry = IDLE_RETRY_S  # the next wait off idle priority
        self._share = CpuShare(WATCH_PERIOD_S)
        self._left_idle_at: float | None = None  # monotonic s, when starving sent it off idle
        self._failed = False  # the watch raised once: said, and not again

    def child_started(self) -> None:
        """A new child: its scheduling unknown until it reports, its share judged afresh (the
        wait off idle keeps growing: the machine is the same)."""
        self.priority = "starting"
        self._share, self._left_idle_at = CpuShare(WATCH_PERIOD_S), None

    def check(self, pid: int, job: object | None) -> None:
        """At idle priority: a child starved by other work while planning `job` goes to normal
        scheduling. Off it after starving: back to idle once the wait is over. A fault of its
        own is logged once and never ends the caller (the receiver, which supervises)."""
        try:
            self._check(pid, job)
        except Exception:
            if not self._failed:  # said once: it would fail every period
                LOGGER.exception("planning process: watching its priority failed")
            self._failed = True

    def _check(self, pid: int, job: object | None) -> None:
        now = time.monotonic()
        if self.priority == "idle":
            cpu, stopped = process_sample(pid)
            if stopped:  # it asked for nothing: no window spans the stop
                self._share.share(now, cpu, job, stopped=True)
                return
            share = self._share.starved(now, cpu, job)
            if share is not None:
                self.leave_idle(pid, share)
        elif self._left_idle_at is not None and now - self._left_idle_at >= self.idle_retry:
            self.return_to_idle(pid)

    def leave_idle(self, pid: int, share: float) -> None:
        """The child got `share` of a core at idle priority: normal scheduling, all its
        threads."""
        try:
            schedule_process(pid, idle=False)
        except OSError as error:  # not allowed after all: say so, and stop trying
            self.priority = "idle (starved: could not leave it)"
            LOGGER.error("planning process starved at idle priority (%.0f%% of a core) and "
                         "could not leave it: %s", 100 * share, error)
            return
        with contextlib.suppress(OSError):
            self.priority = scheduling(pid)
        self._left_idle_at = time.monotonic()
        LOGGER.warning("planning process got %.0f%% of a core at idle priority (the machine "
                       "is busy): normal scheduling (%s) for %g s", 100 * share,
                       self.priority, self.idle_retry)

    def return_to_idle(self, pid: int) -> None:
        """The machine may be quiet again: idle priority once more (a task may always lower
        its own). Starved again, the child leaves it at once, and waits twice as long."""
        self._left_idle_at = None
        self.idle_retry = min(2 * self.idle_retry, IDLE_RETRY_MAX_S)
        with contextlib.suppress(OSError):  # the child is gone: the receiver says so
            schedule_process(pid, idle=True)
        self._share = CpuShare(WATCH_PERIOD_S)  # judged afresh, at idle
        with contextlib.suppress(OSError):
            self.priority = scheduling(pid)
        LOGGER.info("planning process: back to idle priority (%s)", self.priority)
