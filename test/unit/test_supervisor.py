"""The planning child supervised: a child that dies is started again (a bounded number of times
in a row, with growing waits), what was in use is given to the new one, and `failed` holds until
a plan comes again; a child that was stopped is not taken for a starved one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.runtime import planning_child, priority_watch
from constrained_diffusion_ros.runtime.os_scheduling import (
    CpuShare,
    may_leave_idle,
    process_sample,
    scheduling,
)
from constrained_diffusion_ros.runtime.planning_process import (
    RESTART_DELAY_MAX_S,
    RESTART_DELAY_S,
    RESTART_LIMIT,
    PlanningProcess,
)
from constrained_diffusion_ros.runtime.thread_worker import PlanningThread
from constrained_diffusion_ros.zones import LiveZones

FAST = ConstraintConfig("fast", sampler="ddim", denoising_steps=3)
SLOW = ConstraintConfig("slow", sampler="ddpm", denoising_steps=100)  # a plan to kill or stop


def job(generation: int) -> PlanJob:
    return PlanJob(generation, 0, torch.full((1, 2, 20), 200.0), None, 0, None)


def until(condition: Callable[[], bool], timeout: float = 60.0) -> bool:
    """Whether `condition` came true within `timeout` s (looked at every 10 ms)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        threading.Event().wait(0.01)
    return True


def state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_a_killed_planning_child_is_started_again_and_plans_what_is_asked_after(
        tiny_policy: DiffusionPolicy) -> None:
    """SIGKILL mid-plan: the plan in flight dies with the child (never offered); `failed` holds
    from the death until a plan arrives, which is asked for after the kill and planned by a new
    child, given the weights, planner and seed again."""
    results: list[tuple[int, bool]] = []  # (generation, `failed` as the owner hears of it)
    arrived = threading.Semaphore(0)

    def on_result(result: PlanResult) -> None:
        results.append((result.job.generation, worker.failed))
        arrived.release()

    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, SLOW, PUSHT_ROBOT), on_result)
    try:
        worker.submit(job(1))
        assert arrived.acquire(timeout=60) and not worker.failed
        first = worker.pid
        worker.submit(job(2))
        os.kill(first, signal.SIGKILL)
        assert until(lambda: worker.errors == 1)  # the death is seen
        assert worker.failed and "exited (code -9)" in str(worker.error)
        worker.submit(job(3))  # kept for the next child
        assert worker.busy
        assert arrived.acquire(timeout=60)
        assert worker.pid != first and worker.restarts == 1
        assert results == [(1, False), (3, False)] and not worker.failed
        worker.submit(job(4))  # the new child serves on
        assert arrived.acquire(timeout=60) and worker.errors == 1
    finally:
        worker.shutdown()
    assert worker._process.returncode == 0


def test_the_controller_plans_again_after_its_planning_child_is_killed(
        tiny_policy: DiffusionPolicy) -> None:
    """The controller does not wait for the plan that died: it finds the worker idle and asks
    again, and the new child's plans are installed."""
    woken = threading.Event()
    controller = ChunkLoop(ConstrainedPlanner(tiny_policy, FAST, PUSHT_ROBOT),
                           lambda planner, on_result: PlanningProcess(planner, on_result, 0, 1),
                           LiveZones(), wake=woken.set)
    observation = np.full(20, 256.0, dtype=np.float32)
    steps = iter(range(1, 100_000))

    def run_until(condition: Callable[[], bool], timeout: float = 60.0) -> bool:
        """Observations at the controller's pace, plans installed when they arrive."""
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            woken.wait(0.1)
            woken.clear()
            controller.install_results()
            controller.observe(next(steps), observation)
        return condition()

    try:
        controller.observe(0, observation)
        assert run_until(lambda: controller.stats.plans_installed >= 1)
        first = controller.worker.pid
        os.kill(first, signal.SIGKILL)
        assert run_until(lambda: controller.worker.restarts == 1)
        installed = controller.stats.plans_installed
        assert run_until(lambda: controller.stats.plans_installed > installed)
        assert controller.worker.pid != first and not controller.worker.failed
    finally:
        controller.shutdown()


def test_a_child_that_keeps_dying_is_restarted_a_bounded_number_of_times_then_given_up(
        tiny_policy: DiffusionPolicy, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each restart waits twice as long as the one before (up to the cap); past the bound the
    worker says it gave up, its supervisor ends (nothing spins) and jobs are refused."""
    assert (RESTART_LIMIT, RESTART_DELAY_S, RESTART_DELAY_MAX_S) == (5, 0.5, 8.0)
    started: list[float] = []

    def dying(*_: object) -> list[str]:
        started.append(time.monotonic())
        return [sys.executable, "-c", "raise SystemExit(3)"]

    monkeypatch.setattr(planning_child, "child_command", dying)
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, FAST, PUSHT_ROBOT),
                             lambda result: None, restart_limit=3, restart_delay=0.1,
                             restart_delay_max=0.3)
    try:
        worker.submit(job(1))  # waits for a child that never comes
        worker._receiver.join(30)
        assert not worker._receiver.is_alive()
        assert len(started) == 4 and worker.restarts == 3 and worker.errors == 4
        for gap, delay in zip(np.diff(started), [0.1, 0.2, 0.3], strict=True):
            assert gap >= delay
        assert "gave up" in str(worker.error) and "code 3" in str(worker.error)
        assert worker.failed and not worker.busy  # the job waiting went with it
        worker.submit(job(2))
        assert not worker.busy
    finally:
        worker.shutdown()


def test_the_thread_worker_reports_a_fault_until_the_next_plan() -> None:
    """The same diagnostics on the thread worker, which is never restarted."""
    arrived, failing = threading.Semaphore(0), threading.Event()

    def plan(job: PlanJob, generator: torch.Generator, interrupt) -> np.ndarray:
        if job.generation == 1:
            failing.set()
            raise RuntimeError("boom")
        return np.zeros((16, 2))

    seen: list[bool] = []
    worker = PlanningThread(None, lambda r: (seen.append(worker.failed), arrived.release()),
                            plan=lambda _, *job: plan(*job))
    try:
        assert not worker.failed and worker.restarts == 0
        worker.submit(job(1))
        assert failing.wait(5) and until(lambda: worker.failed, 5)
        worker.submit(job(2))
        assert arrived.acquire(timeout=5)
        assert seen == [False] and not worker.failed and worker.restarts == 0
        assert worker.errors == 1
    finally:
        worker.shutdown()


def test_cpu_share_does_not_count_time_stopped_as_starved() -> None:
    """A window with the process seen stopped is not judged, however long the stop; the next
    window starts once it runs, and is judged as any other."""
    watch, job = CpuShare(0.5), object()
    assert watch.starved(0.0, 1.0, job) is None
    assert watch.starved(0.5, 1.0, job, stopped=True) is None  # nothing got: it was stopped
    assert watch.starved(5.0, 1.0, job, stopped=True) is None
    assert watch.starved(5.5, 1.0, job) is None  # running again: a new window
    assert watch.starved(6.0, 1.4, job) is None  # 0.8 of a core
    assert watch.starved(6.5, 1.45, job) == pytest.approx(0.1)  # starved while running


def test_a_stopped_process_reads_as_stopped() -> None:
    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        assert until(lambda: process_sample(sleeper.pid)[0] is not None, 5)
        assert process_sample(sleeper.pid)[1] is False
        os.kill(sleeper.pid, signal.SIGSTOP)
        assert until(lambda: process_sample(sleeper.pid)[1], 5)
        os.kill(sleeper.pid, signal.SIGCONT)
        assert until(lambda: not process_sample(sleeper.pid)[1], 5)
    finally:
        sleeper.kill()
        sleeper.wait()
    assert process_sample(sleeper.pid) == (None, False)  # gone


def test_a_planning_child_stopped_mid_plan_is_not_judged_starved(
        tiny_policy: DiffusionPolicy) -> None:
    """SIGSTOP for 2 s (four watch windows) while a plan is in flight: the child stays at idle
    priority, and the plan arrives after SIGCONT."""
    if not may_leave_idle(5):
        pytest.skip("idle priority would be one way here: the child plans at a nice value")
    arrived = threading.Semaphore(0)
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, SLOW, PUSHT_ROBOT),
                             lambda result: arrived.release())
    try:
        worker.submit(job(1))
        assert arrived.acquire(timeout=60)  # the child is up and has said how it runs
        worker.submit(job(2))
        os.kill(worker.pid, signal.SIGSTOP)
        try:
            assert until(lambda: state(worker.pid) in ("T", "t"), 5)
            if worker.priority != "idle":
                pytest.skip("the machine starved the child before the stop took hold")
            threading.Event().wait(2.0)  # the stop itself
            assert worker.priority == "idle" == scheduling(worker.pid)
        finally:
            os.kill(worker.pid, signal.SIGCONT)
        assert arrived.acquire(timeout=60)
        assert worker.error is None and worker.restarts == 0
    finally:
        worker.shutdown()


def test_a_child_that_left_idle_priority_returns_to_it_after_a_while(
        tiny_policy: DiffusionPolicy, monkeypatch: pytest.MonkeyPatch) -> None:
    """Starving is not for good: after the wait the child (all its threads) is at idle
    priority again, and the next wait is twice as long."""
    if not may_leave_idle(5):
        pytest.skip("idle priority would be one way here: the child plans at a nice value")
    # When it starves is the watch's business (the CpuShare tests): on a busy machine the
    # child would, at once, and be sent off idle again before it is checked.
    monkeypatch.setattr(CpuShare, "starved", lambda self, now, cpu, job, stopped=False: None)
    monkeypatch.setattr(priority_watch, "IDLE_RETRY_S", 0.2)
    arrived = threading.Semaphore(0)
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, FAST, PUSHT_ROBOT),
                             lambda result: arrived.release())
    try:
        worker.submit(job(1))
        assert arrived.acquire(timeout=60) and worker.priority == "idle"
        worker.watch.leave_idle(worker.pid, 0.1)  # what the watch does when starved
        assert worker.priority.startswith("nice")
        assert until(lambda: worker.priority == "idle", 10)
        assert scheduling(worker.pid) == "idle"
        for thread in Path(f"/proc/{worker.pid}/task").iterdir():
            assert os.sched_getscheduler(int(thread.name)) == os.SCHED_IDLE
        assert worker.watch.idle_retry == pytest.approx(0.4)
        worker.submit(job(2))
        assert arrived.acquire(timeout=60)
    finally:
        worker.shutdown()
