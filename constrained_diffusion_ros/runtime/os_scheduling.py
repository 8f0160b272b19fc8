"""Everything that asks the operating system how a thread or process is scheduled, or tells it.

The control clock and the node's executor ask for real-time priority (SCHED_FIFO, as
ros2_control's controller manager does), so a tick is sent on time however busy the machine; the
planning process asks for idle priority (SCHED_IDLE), so planning never delays them. Idle
priority can starve a planner on a machine kept busy by other work, so the /proc probes here tell
how much of a core a process got (`CpuShare`, `process_sample`) and whether idle priority may be
left again (`may_leave_idle`). Calls only Linux has are guarded: without them a request reports
that it was not granted, and a probe that it cannot tell.
"""

from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path

CLOCK_PRIORITY = 50  # SCHED_FIFO priority of the control clock where allowed (ros2_control's)
EXECUTOR_PRIORITY = 40  # the node's executor thread, which reacts to zones: below the clock
STARVED_SHARE = 0.25  # of a core, while planning: below it, idle priority starves the planner


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


def lower_own_priority(niceness: int, idle: bool) -> None:
    """This process's nice value raised by `niceness` (kept if it goes back from idle to
    normal scheduling), and SCHED_IDLE with `idle`; what is not allowed is left as it was.
    Threads started afterwards inherit it."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(niceness)
        if idle:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def schedule_process(pid: int, idle: bool) -> None:
    """Every thread of process `pid` to SCHED_IDLE (`idle`) or normal scheduling. Threads that
    end meanwhile are passed over, and nothing is done for a process that is gone; a change
    not allowed raises OSError."""
    try:
        threads = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return
    policy = os.SCHED_IDLE if idle else os.SCHED_OTHER
    for thread in threads:
        with contextlib.suppress(ProcessLookupError):
            os.sched_setscheduler(int(thread), policy, os.sched_param(0))


def scheduling(pid: int = 0) -> str:
    """How a process (0: this one) is scheduled: "idle" (SCHED_IDLE) or "nice <n>"."""
    if hasattr(os, "SCHED_IDLE") and os.sched_getscheduler(pid) == os.SCHED_IDLE:
        return "idle"
    return f"nice {os.getpriority(os.PRIO_PROCESS, pid)}"


class CpuShare:
    """The share of a core a process got while it worked on one job, over `period` s or more
    (its CPU time against the wall clock's); windows that span two jobs, or time without one,
    are not judged: between jobs a planner rightly uses nothing. Nor is a window in which the
    process was seen stopped (SIGSTOP, a debugger): it got nothing because it asked for
    nothing, and the window starts again once it runs."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._since: tuple[float, float, object] | None = None  # (wall s, CPU s, job)

    def share(self, now: float, cpu: float | None, job: object | None,
              stopped: bool = False) -> float | None:
        """Fed a sample (wall s, CPU s, the job in flight or None, whether the process is
        stopped); the share since the last sample of the same job at least `period` ago, with
        no stopped sample between, else None."""
        since = self._since
        if job is None or cpu is None or stopped:
            self._since = None
        elif since is None or since[2] is not job:
            self._since = (now, cpu, job)
        elif now - since[0] >= self.period:
            self._since = (now, cpu, job)
            return (cpu - since[1]) / (now - since[0])
        return None

    def starved(self, now: float, cpu: float | None, job: object | None,
                stopped: bool = False) -> float | None:
        """`share`, when it is under `STARVED_SHARE` (a planner starved); else None."""
        share = self.share(now, cpu, job, stopped)
        return share if share is not None and share < STARVED_SHARE else None


def process_sample(pid: int) -> tuple[float | None, bool]:
    """(CPU s a process has used, all its threads; whether it is stopped): (None, False) if
    /proc cannot tell."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
    except (OSError, IndexError, ValueError):
        return None, False
    return cpu, fields[0] in ("T", "t")  # stopped by a signal, or by a tracer
