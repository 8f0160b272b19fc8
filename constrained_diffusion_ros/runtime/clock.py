"""The control clock: threads of their own that send the setpoint already computed on every
tick, on absolute deadlines, at real-time priority where the system grants it."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from constrained_diffusion_ros.runtime.os_scheduling import CLOCK_PRIORITY, request_fifo

LATENESS_WINDOW = 100  # ticks over which the clock's lateness is kept (the diagnostics')


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

    def status(self) -> dict[str, object]:
        return {"ticks": self.ticks, "ticks_missed": self.missed,
                "tick_late_p99_ms": f"{1000 * self.late_p99():.1f}",
                "clock_realtime": self.realtime}

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
