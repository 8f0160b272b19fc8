"""Real-time chunking: the step-indexed action queue, the committed prefix it gives the next
plan, the planning workers, and the chunk loop with a simulated delay and live."""

from __future__ import annotations

import contextlib
import logging
import math
import os
import pickle
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from samples import chunk_of_rows
from test_lockstep import CONFIG, Scripted, lockstep

from constrained_diffusion_ros.planning.action_queue import ActionQueue, committed_prefix
from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop, LoopSettings
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, plan_chunk
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import save_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.runtime.clock import ControlClock
from constrained_diffusion_ros.runtime.live_loop import live_chunk_loop, loop_status, warm_up
from constrained_diffusion_ros.runtime.os_scheduling import (
    STARVED_SHARE,
    CpuShare,
    may_leave_idle,
    request_fifo,
    scheduling,
)
from constrained_diffusion_ros.runtime.planning_child import send, serve
from constrained_diffusion_ros.runtime.planning_process import PlanningProcess
from constrained_diffusion_ros.runtime.thread_worker import PlanningThread
from constrained_diffusion_ros.sampling.sampler import Interrupted
from constrained_diffusion_ros.zones import LiveZones, rectangle
from constrained_diffusion_ros.zones.plugins import PLUGIN_MODULES_ENV, ZoneCheckError, load_area


def test_a_plan_installed_late_skips_the_waypoints_whose_time_has_passed() -> None:
    queue = ActionQueue(batch=2, n_action_steps=8)
    chunk = chunk_of_rows(2, 15)  # waypoint j of row r: (j, r)
    skipped = queue.install(np.arange(2), chunk, first_step=10, now=13)  # planned at 10, in at 13
    assert list(skipped) == [3, 3]
    np.testing.assert_array_equal(queue.at(13), [[3, 0], [3, 1]])  # not 0: those steps passed
    assert list(queue.remaining(13)) == [8, 8]  # n_action_steps after the skipped ones
    assert np.isnan(queue.at(9)).all() and np.isnan(queue.at(25)).all()
    assert queue.skipped == 6


def test_the_queue_answers_per_row_and_a_row_without_a_chunk_has_nothing() -> None:
    queue = ActionQueue(batch=3, n_action_steps=8)
    queue.install(np.array([2]), chunk_of_rows(1, 15), first_step=4, now=4)
    waypoints = queue.at(6)
    assert np.isnan(waypoints[:2]).all() and list(waypoints[2]) == [2, 0]
    assert list(queue.remaining(6)) == [0, 0, 6]
    queue.install(np.array([0]), chunk_of_rows(1, 15), first_step=0, now=10)  # very late
    assert queue.remaining(10)[0] == 5  # only the chunk's own waypoints
    upcoming = queue.upcoming(np.array([1, 2]), 5, 3)
    assert np.isnan(upcoming[0]).all()
    np.testing.assert_array_equal(upcoming[1, :, 0], [1, 2, 3])
    queue.clear()
    assert np.isnan(queue.at(6)).all()


def test_the_committed_prefix_is_the_chunk_in_force_at_the_steps_before_the_plan_arrives(
) -> None:
    """Chunk index i of a plan made at step t lies at step t - first_executed + i."""
    queue = ActionQueue(batch=2, n_action_steps=8)
    queue.install(np.array([0]), chunk_of_rows(1, 15), first_step=20, now=20)
    prefix = committed_prefix(queue, np.array([0, 1]), step=25, delay=2, soft=3,
                              first_executed=1)
    # indices 0..5 are steps 24..29: executed waypoints 4..9 of the chunk in force
    np.testing.assert_array_equal(prefix.known[0, :, 0], [4, 5, 6, 7, 8, 9])
    np.testing.assert_allclose(prefix.weights[0], [1, 1, 1, 0.75, 0.5, 0.25])
    assert not prefix.weights[1].any()  # row 1 has no chunk in force: left free
    assert committed_prefix(queue, np.array([1]), 25, 2, 3, 1) is None


def test_the_background_planner_plans_the_newest_job_on_its_own_thread() -> None:
    release, started, results, threads = threading.Event(), threading.Event(), [], []

    def plan(job: PlanJob, generator: torch.Generator, interrupt) -> np.ndarray:
        threads.append(threading.get_ident())
        started.set()
        release.wait(5)
        return np.full((16, 2), float(job.generation))

    done = threading.Semaphore(0)
    worker = PlanningThread(None, lambda r: (results.append(r), done.release()),
                            plan=lambda _, *job: plan(*job))
    try:
        job = PlanJob(1, 0, torch.zeros(1, 2, 20), None, 0, None)
        worker.submit(job)
        assert started.wait(5)  # the first job has started
        assert worker.busy
        for generation in (2, 3):  # queued while busy: only the newest is planned
            worker.submit(PlanJob(generation, 0, job.observations, None, 0, None))
        release.set()
        assert done.acquire(timeout=5) and done.acquire(timeout=5)
        assert [r.job.generation for r in results] == [1, 3]
        assert threading.get_ident() not in threads
        assert not done.acquire(timeout=0.2)
    finally:
        worker.shutdown()
    assert not worker._thread.is_alive()


def test_the_background_planner_stops_the_plan_in_flight_when_asked() -> None:
    """`submit(cancel=True)`: the plan in flight ends at its next check (a 10 s plan here),
    is not offered, and the new job is planned at once."""
    started, results, done = threading.Event(), [], threading.Semaphore(0)

    def plan(job: PlanJob, generator: torch.Generator, interrupt) -> np.ndarray:
        started.set()
        for _ in range(1000 if job.generation == 1 else 0):
            if interrupt():
                raise Interrupted("stopped")
            threading.Event().wait(0.01)
        return np.full((16, 2), float(job.generation))

    worker = PlanningThread(None, lambda r: (results.append(r), done.release()),
                            plan=lambda _, *job: plan(*job))
    try:
        worker.submit(PlanJob(1, 0, torch.zeros(1, 2, 20), None, 0, None))
        assert started.wait(5)
        worker.submit(PlanJob(2, 0, torch.zeros(1, 2, 20), None, 0, None), cancel=True)
        assert done.acquire(timeout=5)  # long before the first plan would have ended
        assert [r.job.generation for r in results] == [2] and worker.cancelled == 1
        assert worker.error is None
    finally:
        worker.shutdown()


def test_the_background_planner_reseeds_from_the_next_job_and_stops_the_one_in_flight() -> None:
    """A new episode while a plan draws noise: that plan is stopped, the job waiting behind it
    dropped, and the next draws what a fresh worker would, however much the stopped one drew
    after the reseed."""
    started, release, results, done = threading.Event(), threading.Event(), [], \
        threading.Semaphore(0)

    def plan(job: PlanJob, generator: torch.Generator, interrupt) -> np.ndarray:
        started.set()
        release.wait(5)
        noise = torch.rand(16, 2, generator=generator).numpy()
        if interrupt():
            raise Interrupted("stopped")
        return noise

    worker = PlanningThread(None, lambda r: (results.append(r), done.release()),
                            plan=lambda _, *job: plan(*job))
    try:
        worker.submit(PlanJob(1, 0, torch.zeros(1, 2, 20), None, 0, None))
        assert started.wait(5)
        worker.submit(PlanJob(2, 0, torch.zeros(1, 2, 20), None, 0, None))  # waiting
        worker.reseed(7)
        release.set()
        for _ in range(2500):  # the plan in flight stops, and the job waiting never starts
            if not worker.busy:
                break
            threading.Event().wait(0.002)
        assert not worker.busy and not results and worker.cancelled == 1
        worker.submit(PlanJob(3, 0, torch.zeros(1, 2, 20), None, 0, None))
        assert done.acquire(timeout=5)
        assert [r.job.generation for r in results] == [3]
        fresh = torch.rand(16, 2, generator=torch.Generator().manual_seed(7)).numpy()
        np.testing.assert_array_equal(results[0].chunk, fresh)
    finally:
        worker.shutdown()


def test_the_planning_child_answers_a_stopped_plan_and_plans_the_next(
        tiny_policy: DiffusionPolicy) -> None:
    """The child's loop: a job with a message waiting behind it (here "cancel") stops before
    its first denoising step and is answered "cancelled"; the next job is planned."""
    ours, theirs = socket.socketpair()
    node = Connection(ours.detach())
    job = PlanJob(1, 0, torch.full((1, 2, 20), 200.0), None, 0, None)
    threads = torch.get_num_threads()
    child = threading.Thread(target=serve, args=(theirs.detach(), 1, 0))  # closes its end
    child.start()
    try:
        for kind, payload in (("policy", tiny_policy), ("planner", (SAFE, PUSHT_ROBOT)),
                              ("seed", 0)):
            send(node, kind, payload)
        # The job and "cancel" in one write, framed as Connection.send_bytes frames a message
        # (a 4-byte big-endian length): "cancel" is there before the child reads the job.
        frames = b"".join(struct.pack("!i", len(m)) + m for m in (
            pickle.dumps(("job", pickle.dumps((job, False)))),
            pickle.dumps(("cancel", pickle.dumps(None)))))
        with socket.socket(fileno=os.dup(node.fileno())) as raw:
            raw.sendall(frames)
        replies = []
        while len(replies) < 2 and node.poll(30):
            replies.append(pickle.loads(node.recv_bytes())[0])
        send(node, "job", (job, False))  # nothing behind it: planned to the end
        assert node.poll(30)
        kind, data = pickle.loads(node.recv_bytes())
        assert replies == ["scheduling", "cancelled"] and kind == "chunk"
        assert np.isfinite(pickle.loads(data)[0]).all()
    finally:
        send(node, "stop", None)
        child.join(30)
        node.close()
        torch.set_num_threads(threads)  # the child's loop set this process's


def test_the_planning_process_stops_the_plan_in_flight_and_plans_the_pending_one(
        tiny_policy: DiffusionPolicy) -> None:
    """`submit(cancel=True)` while a plan is in flight (100 DDPM steps, about 0.3 s here):
    that plan is answered "cancelled" and never offered; the new job is planned and offered."""
    results, done = [], threading.Semaphore(0)
    slow = ConstraintConfig("slow", sampler="ddpm", denoising_steps=100)
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, slow, PUSHT_ROBOT),
                             lambda result: (results.append(result), done.release()))
    try:
        deadline = time.monotonic() + 60
        while not worker.ready and time.monotonic() < deadline:  # the child starts meanwhile
            time.sleep(0.01)
        worker.submit(PlanJob(1, 0, torch.full((1, 2, 20), 200.0), None, 0, None))
        worker.submit(PlanJob(2, 0, torch.full((1, 2, 20), 200.0), None, 0, None), cancel=True)
        assert done.acquire(timeout=60)
        assert [r.job.generation for r in results] == [2] and worker.cancelled == 1
        assert worker.error is None
    finally:
        worker.shutdown()


@contextlib.contextmanager
def submits_recorded(policy: DiffusionPolicy, zones: LiveZones, **options: object
                     ) -> Iterator[tuple[ChunkLoop, list[tuple[PlanJob, bool]]]]:
    """A controller with its first chunk installed, whose worker from then on only records
    what is submitted, (job, cancel), as if a plan were always in flight."""
    controller = live(ConstrainedPlanner(policy, SAFE, PUSHT_ROBOT), zones, lead=1, **options)
    worker = controller.worker
    try:
        controller.observe(0, observation_with_pusher(200, 200))
        installed(controller)
        submitted: list[tuple[PlanJob, bool]] = []
        controller.worker = SimpleNamespace(busy=True, submit=lambda job, cancel=False:
                                            submitted.append((job, cancel)))
        yield controller, submitted
    finally:
        controller.worker = worker
        controller.shutdown()


def test_a_zone_change_stops_the_plan_in_flight_once_until_the_replan_arrives(
        tiny_policy: DiffusionPolicy) -> None:
    """The first zone change that puts the rest of the chunk in a zone stops the plan in
    flight; those that follow while its replan is out neither stop nor ask (a zone
    re-published on every frame would stop every plan); once it arrives, the next may."""
    zones = LiveZones()
    with submits_recorded(tiny_policy, zones) as (controller, submitted):
        chunk = controller.queue.waypoints[0].copy()
        rest = controller.queue.upcoming(np.array([0]), 0,
                                         int(controller.queue.remaining(0)[0]))[0]
        assert len(rest) >= 6

        def zone_on(zone_id: int, waypoint: np.ndarray) -> None:
            x, y = waypoint
            zones.upsert(zone_id, rectangle(x - 2, y - 2, x + 2, y + 2), now=0.0)
            controller.zones_changed()
            controller.install_results()  # as the node does when woken

        for zone_id in (1, 2, 3):  # each on a waypoint still to come
            zone_on(zone_id, rest[zone_id])
        assert [cancel for _, cancel in submitted] == [True]
        # It arrives entering zones that came after it was asked: dropped and asked again.
        controller._on_result(PlanResult(submitted[-1][0], chunk[None], 0.1))
        controller.install_results()
        assert controller.stats.plans_dropped == 1
        assert [cancel for _, cancel in submitted] == [True, True]
        clear = chunk + np.array([0.0, 150.0])  # clear of every zone
        controller._on_result(PlanResult(submitted[-1][0], clear[None], 0.1))
        controller.install_results()
        assert controller.stats.plans_installed == 2
        rest = controller.queue.upcoming(np.array([0]), 0,
                                         int(controller.queue.remaining(0)[0]))[0]
        zone_on(4, rest[-1])
        assert [cancel for _, cancel in submitted] == [True, True, True]


def test_a_stopped_plan_that_arrives_anyway_is_dropped_without_asking_again(
        tiny_policy: DiffusionPolicy) -> None:
    """A plan that ends as its stop is sent still arrives. It enters the new zone, so it is
    dropped; the replan already asked for covers it, so no other plan is asked. A plan
    dropped with no replan coming asks for one."""
    zones = LiveZones()
    with submits_recorded(tiny_policy, zones) as (controller, submitted):
        chunk = controller.queue.waypoints[0].copy()
        controller._ask(np.array([0]))  # the plan in flight, before the zone
        x, y = controller.queue.upcoming(np.array([0]), 0, 2)[0, 1]
        zones.upsert(1, rectangle(x - 2, y - 2, x + 2, y + 2), now=0.0)
        controller.zones_changed()
        controller.install_results()
        (stopped, _), (replan, cancel) = submitted
        assert cancel and controller.rows.replanning[0] == replan.serial
        controller._on_result(PlanResult(stopped, chunk[None], 0.1))  # its stop came too late
        controller.install_results()
        assert controller.stats.plans_dropped == 1 and len(submitted) == 2
        zones.upsert(2, rectangle(x - 3, y - 3, x + 3, y + 3), now=0.0)  # after the replan
        controller._on_result(PlanResult(replan, chunk[None], 0.1))
        controller.install_results()
        assert controller.stats.plans_dropped == 2 and len(submitted) == 3


def test_with_replan_on_zone_change_any_zone_asks_for_a_plan_that_knows_it(
        tiny_policy: DiffusionPolicy) -> None:
    """`replan_on_zone_change` (the node's default): a zone far from the chunk still stops the
    plan in flight and asks for one planned with it, once while that one is out. The plan
    that arrives planned before a later zone, entering it, is installed (guarded as the chunk
    in force is) rather than dropped, and the plan that knows the later zone is asked then."""
    zones = LiveZones()
    with submits_recorded(tiny_policy, zones, replan_on_zone_change=True) as (
            controller, submitted):
        chunk = controller.queue.waypoints[0].copy()
        zones.upsert(1, rectangle(480, 10, 500, 30), now=0.0)  # far from every waypoint
        controller.zones_changed()
        controller.install_results()
        assert [cancel for _, cancel in submitted] == [True]
        replan = submitted[0][0]
        assert replan.zone_version[0] == zones.version_at(0)  # planned with the zone
        x, y = controller.queue.upcoming(np.array([0]), 0, 2)[0, 1]
        zones.upsert(2, rectangle(x - 2, y - 2, x + 2, y + 2), now=0.0)  # on the chunk
        controller.zones_changed()
        controller.install_results()
        assert len(submitted) == 1  # the replan is out: not asked twice
        controller._on_result(PlanResult(replan, chunk[None], 0.1))  # enters zone 2
        controller.install_results()
        assert controller.stats.plans_dropped == 0 and controller.stats.plans_installed == 2
        assert [cancel for _, cancel in submitted] == [True, True]
        assert submitted[1][0].zone_version[0] == zones.version_at(0)
        assert controller.queue.remaining(0)[0] > 0  # waypoints to execute meanwhile


def test_a_first_plan_that_arrives_after_all_its_waypoints_passed_is_asked_for_again(
        tiny_policy: DiffusionPolicy) -> None:
    """A planning process still starting delivers the episode's first plan seconds late: every
    waypoint's time has passed, so it is not installed (nothing of it could execute) and a new
    plan is asked at once; the steps meanwhile are held, and none counts as late (there was no
    usable first plan yet)."""
    controller = live(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), LiveZones())
    worker, submitted = controller.worker, []
    controller.worker = SimpleNamespace(busy=True, submit=lambda job, cancel=False:
                                        submitted.append(job))
    try:
        controller.observe(0, observation_with_pusher(200, 200))
        for step in range(1, 30):
            controller.observe(step, observation_with_pusher(200, 200))
        assert len(submitted) == 1
        chunk = np.full((1, 15, 2), 200.0)
        controller._on_result(PlanResult(submitted[0], chunk, 0.2))
        controller.worker.busy = False
        controller.observe(30, observation_with_pusher(200, 200))
        assert controller.stats.plans_installed == 0 and controller.stats.plans_dropped == 1
        assert len(submitted) == 2 and submitted[1].step == 30  # asked again, from now
        assert controller.stats.late_steps == 0 and controller.stats.held_steps == 31
    finally:
        controller.worker = worker
        controller.shutdown()


def test_the_measured_lead_leaves_room_for_a_plan_stopped_and_made_again(
        tiny_policy: DiffusionPolicy) -> None:
    """Asked `lead` steps before the chunk runs out, a plan that a zone stops at its end and
    that is made again takes two planning times: lead covers them and a step."""
    controller = live_chunk_loop(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), LiveZones(),
                                None, rate_hz=10.0)
    try:
        for seconds, lead in ((0.03, 2), (0.21, 6), (0.5, 8)):
            controller.plan_seconds = seconds
            assert controller.lead == lead
    finally:
        controller.shutdown()


def test_a_replan_that_never_comes_is_asked_again_and_does_not_block_the_next(
        tiny_policy: DiffusionPolicy) -> None:
    """A replan that failed leaves the worker idle without a result: it is not waited for. The
    next observation asks again while the rest of the chunk still enters the zone, stopping
    what is in flight."""
    zones = LiveZones()
    with submits_recorded(tiny_policy, zones) as (controller, submitted):
        rest = controller.queue.upcoming(np.array([0]), 0,
                                         int(controller.queue.remaining(0)[0]))[0]
        x, y = rest[3]
        zones.upsert(1, rectangle(x - 2, y - 2, x + 2, y + 2), now=0.0)
        controller.zones_changed()
        controller.install_results()
        assert [cancel for _, cancel in submitted] == [True]  # the plan in flight stopped
        controller.observe(1, observation_with_pusher(200, 200))
        assert len(submitted) == 1  # the replan is on its way: not asked twice
        controller.worker.busy = False  # the replan failed: nothing in flight, no result
        controller.observe(2, observation_with_pusher(200, 200))
        assert [cancel for _, cancel in submitted] == [True, True]  # asked again


def test_a_zone_that_moves_the_held_setpoint_stops_the_plan_in_flight(
        tiny_policy: DiffusionPolicy) -> None:
    """The pusher held at the end of its chunk has no rest of the chunk for a zone to enter;
    a zone on its setpoint still stops the plan in flight (planned for what no longer holds).
    Removing that zone moves the setpoint back and stops nothing."""
    zones = LiveZones()
    with submits_recorded(tiny_policy, zones) as (controller, submitted):
        step = 0
        while controller.queue.remaining(step)[0] > 0:  # the chunk runs out
            step += 1
            held = controller.observe(step, observation_with_pusher(200, 200))
        assert controller.queue.remaining(step)[0] == 0 and not submitted
        x, y = held
        zones.upsert(1, rectangle(x - 5, y - 5, x + 5, y + 5), now=0.0)
        assert controller.zones_changed() is not None  # the held setpoint moved
        controller.install_results()
        assert [cancel for _, cancel in submitted] == [True]
        controller.rows.replanning[:] = 0  # as if the replan had arrived
        zones.remove(1)
        np.testing.assert_array_equal(controller.zones_changed(), held)  # back, nothing asked
        controller.install_results()
        assert len(submitted) == 1


def test_a_planning_error_is_kept_and_the_worker_keeps_serving() -> None:
    calls, done, failed = [], threading.Semaphore(0), threading.Event()

    def plan(job: PlanJob, generator: torch.Generator, interrupt) -> np.ndarray:
        calls.append(job.generation)
        if job.generation == 1:
            failed.set()
            raise RuntimeError("boom")
        return np.zeros((16, 2))

    worker = PlanningThread(None, lambda r: done.release(),
                            plan=lambda _, *job: plan(*job))
    try:
        worker.submit(PlanJob(1, 0, torch.zeros(1, 2, 20), None, 0, None))
        assert failed.wait(5)
        for _ in range(500):  # the error is kept once the plan has raised
            if worker.error is not None:
                break
            threading.Event().wait(0.01)
        worker.submit(PlanJob(2, 0, torch.zeros(1, 2, 20), None, 0, None))
        assert done.acquire(timeout=5)
        assert isinstance(worker.error, RuntimeError) and calls == [1, 2]
    finally:
        worker.shutdown()


def test_the_planning_process_plans_what_the_thread_would_in_a_process_of_its_own(
        tiny_policy: DiffusionPolicy) -> None:
    zones = LiveZones()
    zones.upsert(1, rectangle(150, 150, 250, 250), now=0.0)
    job = PlanJob(1, 0, torch.full((1, 2, 20), 200.0), zones.snapshot(), 0, None)
    planner = ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT)
    other = ConstrainedPlanner(tiny_policy, ConstraintConfig("free", sampler="ddim",
                                                             denoising_steps=3), PUSHT_ROBOT)
    expected = [plan_chunk(p, job, torch.Generator().manual_seed(3)) for p in (planner, other)]
    results, done = [], threading.Semaphore(0)
    worker = PlanningProcess(planner, lambda r: (results.append(r), done.release()),
                             noise_seed=3)
    try:
        assert worker.pid != os.getpid()
        worker.submit(job)
        assert worker.busy and done.acquire(timeout=60)
        worker.reseed(3)  # a new episode: the same noise again
        worker.use(other)
        worker.submit(job)
        assert done.acquire(timeout=60)
        worker.submit(PlanJob(2, 0, torch.zeros(1, 5, 3), None, 0, None))  # a bad job
        for _ in range(3000):
            if worker.error is not None and not worker.busy:
                break
            threading.Event().wait(0.01)
        assert isinstance(worker.error, RuntimeError) and str(worker.error)
        worker.reseed(3)
        worker.use(planner)
        worker.submit(job)  # the error is reported and the child keeps serving
        assert done.acquire(timeout=60)
    finally:
        worker.shutdown()
    assert worker._process.returncode == 0
    assert [r.job.generation for r in results] == [1, 1, 1]
    for result, want in zip(results, [expected[0], expected[1], expected[0]], strict=True):
        np.testing.assert_array_equal(result.chunk, want)


def test_cpu_share_judges_only_the_time_spent_on_one_job() -> None:
    watch, job, other = CpuShare(0.5), object(), object()
    assert watch.share(0.0, 1.0, job) is None  # the first sample
    assert watch.share(0.3, 1.1, job) is None  # too soon to judge
    assert watch.share(0.6, 1.15, job) == pytest.approx(0.25)  # 0.15 s of a core in 0.6 s
    assert watch.share(1.2, 1.15, other) is None  # another job: a new window
    assert watch.share(1.4, 1.15, None) is None  # between jobs a planner rightly uses nothing
    assert watch.share(1.5, 1.15, other) is None  # so the window starts again
    assert watch.share(2.1, 1.75, other) == pytest.approx(1.0)
    assert watch.share(2.7, None, other) is None  # unreadable: not judged


def test_cpu_share_calls_a_planner_starved_under_a_quarter_of_a_core() -> None:
    watch, job = CpuShare(0.5), object()
    assert STARVED_SHARE == 0.25
    assert watch.starved(0.0, 0.0, job) is None
    assert watch.starved(1.0, 0.5, job) is None  # half a core: slow, not starved
    assert watch.starved(2.0, 0.75, job) is None  # the bound itself is enough
    assert watch.starved(3.0, 0.875, job) == 0.125


@pytest.mark.parametrize("idle", [True, False])
def test_the_planning_process_plans_at_idle_priority_until_it_starves(
        tiny_policy: DiffusionPolicy, idle: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the node may raise it again, the child plans at SCHED_IDLE; starved, it goes to
    normal scheduling at nice 5 (all its threads). Elsewhere, or not asked to, it is at nice 5
    from the start. What the worker reports is what the system says of the child."""
    # When it is starved is the watch's business (the CpuShare tests): on a busy machine the
    # child would be, at once, and the idle state would be gone before it is checked.
    monkeypatch.setattr(CpuShare, "starved", lambda self, now, cpu, job: None)
    done = threading.Semaphore(0)
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT),
                             lambda result: done.release(), idle=idle)
    nice = min(19, os.getpriority(os.PRIO_PROCESS, 0) + 5)
    threads = Path(f"/proc/{worker.pid}/task")
    try:
        worker.submit(PlanJob(1, 0, torch.full((1, 2, 20), 200.0), None, 0, None))
        assert done.acquire(timeout=60)  # the child has set its scheduling before it planned
        if idle and may_leave_idle(5):
            assert worker.priority == "idle" == scheduling(worker.pid)
            assert os.sched_getscheduler(worker.pid) == os.SCHED_IDLE
            worker.watch.leave_idle(worker.pid, 0.1)  # what the watch does when starved
        assert worker.priority == f"nice {nice}" == scheduling(worker.pid)
        for thread in threads.iterdir():
            assert os.sched_getscheduler(int(thread.name)) == os.SCHED_OTHER
            assert os.getpriority(os.PRIO_PROCESS, int(thread.name)) == nice
    finally:
        worker.shutdown()


def test_a_starved_planner_that_may_not_leave_idle_priority_says_so(
        tiny_policy: DiffusionPolicy, monkeypatch: pytest.MonkeyPatch) -> None:
    """Refused (no CAP_SYS_NICE after all): the status tells the truth and the watch stops."""
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT),
                             lambda result: None, idle=False)
    try:
        def refuse(*_) -> None:
            raise PermissionError(1, "Operation not permitted")

        # The child's own report of its scheduling first, so it cannot overwrite the verdict.
        deadline = time.monotonic() + 30
        while worker.priority == "starting" and time.monotonic() < deadline:
            time.sleep(0.01)
        monkeypatch.setattr(os, "sched_setscheduler", refuse)
        worker.watch.leave_idle(worker.pid, 0.02)
        assert worker.priority == "idle (starved: could not leave it)"
    finally:
        monkeypatch.undo()
        worker.shutdown()


def test_the_planning_process_exits_when_the_node_is_killed(make_tiny_policy, tmp_path) -> None:
    """SIGKILL to the node's process: its end of the socket closes with it, and the child,
    reading it, exits instead of lingering."""
    model = save_policy(make_tiny_policy(0), tmp_path / "model")
    node = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from constrained_diffusion_ros.planning.planners import ConstrainedPlanner\n"
        "from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig\n"
        "from constrained_diffusion_ros.runtime.planning_process import PlanningProcess\n"
        "from constrained_diffusion_ros.policy.weights import load_policy\n"
        "from constrained_diffusion_ros.pusht import PUSHT_ROBOT\n"
        f"policy = load_policy({str(model)!r})\n"
        "planner = ConstrainedPlanner(policy, ConstraintConfig('free'), PUSHT_ROBOT)\n"
        "worker = PlanningProcess(planner, lambda result: None)\n"
        "print(worker.pid, flush=True)\n"
        "time.sleep(120)\n")], stdout=subprocess.PIPE, text=True)
    try:
        child = int(node.stdout.readline())
    finally:
        node.kill()
        node.wait()

    assert until(lambda: exited(child), timeout=60)


def test_a_planning_child_whose_node_is_killed_mid_plan_exits_without_a_traceback(
        make_tiny_policy, tmp_path) -> None:
    """Found by finding 7 of issue 41: after `kill -9` of the node, its child, planning,
    found the socket closed, stopped the plan and printed a 25-line BrokenPipeError traceback
    sending the answer. It exits quietly now; its stderr is the node's (here a file)."""
    model = save_policy(make_tiny_policy(0), tmp_path / "model")
    stderr = tmp_path / "stderr.txt"
    with stderr.open("w") as errors:
        node = subprocess.Popen([sys.executable, "-c", (
            "import time, torch\n"
            "from constrained_diffusion_ros.planning.planners import ConstrainedPlanner\n"
            "from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig\n"
            "from constrained_diffusion_ros.planning.plan_jobs import PlanJob\n"
            "from constrained_diffusion_ros.runtime.planning_process import PlanningProcess\n"
            "from constrained_diffusion_ros.policy.weights import load_policy\n"
            "from constrained_diffusion_ros.pusht import PUSHT_ROBOT\n"
            f"policy = load_policy({str(model)!r})\n"
            "config = ConstraintConfig('slow', sampler='ddpm', denoising_steps=100)\n"
            "worker = PlanningProcess(ConstrainedPlanner(policy, config, PUSHT_ROBOT),\n"
            "                         lambda result: None)\n"
            "while not worker.ready:\n"
            "    time.sleep(0.01)\n"
            "worker.submit(PlanJob(1, 0, torch.full((1, 2, 20), 200.0), None, 0, None))\n"
            "print(worker.pid, flush=True)\n"  # the job is sent: the child reads it, and plans
            "time.sleep(120)\n")], stdout=subprocess.PIPE, stderr=errors, text=True,
            env={**os.environ, "OMP_NUM_THREADS": "1"})
        try:
            child = int(node.stdout.readline())
        finally:
            node.kill()
            node.wait()

    assert until(lambda: exited(child), timeout=30)
    printed = stderr.read_text()
    assert "Traceback" not in printed and len(printed.splitlines()) <= 1, printed


def exited(pid: int) -> bool:
    """Whether process `pid` has exited (gone, or a zombie its parent has not reaped)."""
    try:
        return "State:\tZ" in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True


def until(condition, timeout: float) -> bool:
    """Whether `condition()` came true within `timeout` s (looked at every 20 ms)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        threading.Event().wait(0.02)
    return True


TURNS_NAN = """
import torch
from constrained_diffusion_ros.zones import RestrictedArea


class TurnsNaN(RestrictedArea):
    \"\"\"A disc at (256, 256) whose distances turn NaN after `after` queries.\"\"\"

    def __init__(self, after):
        self.after, self.calls = after, 0

    def signed_distance(self, points):
        self.calls += 1
        distance = (points - 256.0).norm(dim=-1) - 60.0
        return distance if self.calls <= self.after else torch.full_like(distance, torch.nan)
"""
TURNS_NAN_SPEC = "turns_nan_zones:TurnsNaN"


@pytest.fixture
def turns_nan(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """TURNS_NAN as a user's plug-in module, allowed, importable here and by a planning child."""
    (tmp_path / "turns_nan_zones.py").write_text(TURNS_NAN)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv(PLUGIN_MODULES_ENV, "turns_nan_zones")


def test_a_zone_check_that_turns_nan_stops_the_pushers_and_is_said_once(
        tiny_policy: DiffusionPolicy, turns_nan: None, caplog: pytest.LogCaptureFixture) -> None:
    """Found by finding 5 of issue 41: a plug-in that turned NaN after the load probe held the
    pusher (NaN waypoints read as none) or was taken for no zone at all, and nothing named it.
    The loop stops every pusher where it is while the check fails, keeps the fault (named) for
    the status, logs it once however often it recurs, and moves again once it answers; a
    fault the worker met planning is taken up too."""
    area = load_area(TURNS_NAN_SPEC, {"after": 10**9})
    zones = LiveZones(fixed=area, workspace=PUSHT_ROBOT.workspace)
    loop = ChunkLoop.simulated(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), zones,
                               torch.Generator().manual_seed(0), noise_seed=0)
    observation = np.full(CONFIG.obs_dim, 100.0, dtype=np.float32)  # the pusher at (100, 100)
    moving = [loop.observe(step, observation) for step in range(3)]
    assert not loop_status(loop)["zone_check_failed"] and np.isfinite(moving).all()
    assert any((setpoint != 100.0).any() for setpoint in moving)
    area.plugin.after = area.plugin.calls  # NaN from the next query on
    with caplog.at_level(logging.ERROR, logger="constrained_diffusion_ros.planning.chunk_loop"):
        stopped = [loop.observe(step, observation) for step in range(3, 13)]
    assert np.array_equal(stopped, np.full((10, 2), 100.0))
    status = loop_status(loop)
    assert status["zone_check_failed"] and status["holding"]
    assert status["zone_check_errors"] == 10
    assert status["zone_check_error"].startswith(
        f"zone check {TURNS_NAN_SPEC!r}: signed_distance returned NaN at (")
    said = [record.getMessage() for record in caplog.records]
    assert len(said) == 1 and said[0].startswith(status["zone_check_error"][:60]), said
    area.plugin.after = math.inf  # it answers again
    loop.observe(13, observation)
    status = loop_status(loop)
    assert not status["zone_check_failed"] and status["zone_check_errors"] == 10
    loop.worker.error = ZoneCheckError(f"zone check {TURNS_NAN_SPEC!r}: contains failed")
    loop.observe(14, observation)
    assert loop_status(loop)["zone_check_errors"] == 11
    assert loop_status(loop)["zone_check_error"].endswith("contains failed")


def test_a_rollout_whose_zone_check_fails_in_use_stops_in_one_line(
        tiny_policy: DiffusionPolicy, turns_nan: None) -> None:
    """The loop stops the pushers where a plug-in check fails; offline that would count as an
    episode of a pusher that stood still. The rollout (so `evaluate`) stops instead, naming it."""
    from constrained_diffusion_ros.evaluation.rollout import rollout

    area = load_area(TURNS_NAN_SPEC, {"after": 30})
    zones = LiveZones(fixed=area, workspace=PUSHT_ROBOT.workspace)
    with pytest.raises(ValueError, match=r"zone check 'turns_nan_zones:TurnsNaN'.*no figures"):
        rollout(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), [100000], n_steps=40,
                zones=zones, generator=torch.Generator().manual_seed(0))


def test_a_zone_check_fault_in_the_planning_process_comes_back_as_one(
        tiny_policy: DiffusionPolicy, turns_nan: None) -> None:
    """The child plans with the zones it was sent; a check failing there comes back as the
    `ZoneCheckError` it was, so the loop knows it for what it is."""
    area = load_area(TURNS_NAN_SPEC, {"after": 8})  # the load probe's 8: NaN at the next
    worker = PlanningProcess(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT),
                             lambda result: None, idle=False)
    try:
        worker.submit(PlanJob(1, 0, torch.full((1, 2, 20), 200.0), area, 0, None))
        deadline = time.monotonic() + 60
        while worker.errors == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert isinstance(worker.error, ZoneCheckError) and worker.failed
        assert str(worker.error).startswith(
            f"zone check {TURNS_NAN_SPEC!r}: signed_distance returned NaN at (")
    finally:
        worker.shutdown()


def observations_at(step: int, batch: int = 2) -> np.ndarray:
    return np.full((batch, CONFIG.obs_dim), float(step), dtype=np.float32)


def run(executor: ChunkLoop, steps: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    actions, handovers = [], []
    for step in range(steps):
        actions.append(executor.observe(step, observations_at(step)))
        handovers.append(executor.rows.handed_over.copy())
    return actions, handovers


def test_async_plans_ahead_and_skips_the_steps_that_passed_while_it_planned() -> None:
    planner = Scripted()
    actions, handovers = run(lockstep(planner, delay=2, handover="async"), 20)
    # Asked at step 0 (nothing to execute: hold), ready at 2 with waypoints 0, 1 skipped; each
    # chunk executes n_action_steps waypoints after the skipped ones.
    assert [call[0] for call in planner.calls] == [0, 8, 16]  # d steps before each chunk ends
    x = [a[0, 0] - 0.5 for a in actions[2:]]  # the guard adds 0.5
    assert x[:8] == [3, 4, 5, 6, 7, 8, 9, 10]  # chunk index first_executed + j at step j
    assert x[8:10] == [1003, 1004]  # chunk 1 planned at 8, installed at 10, 2 skipped
    assert [bool(h[0]) for h in handovers[:12]] == [False, False, True] + [False] * 7 + [True,
                                                                                           False]


def test_sync_waits_for_the_plan_holding_the_last_setpoint() -> None:
    planner = Scripted()
    actions, _ = run(lockstep(planner, delay=2, handover="sync"), 14)
    x = [a[0, 0] for a in actions]
    assert x[0] == 0.5 and x[1] == 0.5 + 0.5  # the pusher held where it was (then guarded)
    assert [v - 0.5 for v in x[2:10]] == [1, 2, 3, 4, 5, 6, 7, 8]  # the chunk from its start
    assert x[10] == x[9] + 0.5 and x[11] == x[10] + 0.5  # waiting again (the guard's 0.5)
    assert x[12] - 0.5 == 1001  # then chunk 1 from its start


def test_every_tick_plans_from_each_observation_with_the_steps_before_it_arrives_committed(
        ) -> None:
    """every_tick: a plan asked at every step that has none on its way. At d = 0 each step
    executes a chunk planned from its own observation; at d = 2 a plan every 2 steps, each
    skipping the 2 that passed, and the prefix holds the waypoints executed and due before it
    arrives (first_executed + d of them), not the chunk's whole rest."""
    planner = Scripted()
    actions, _ = run(lockstep(planner, delay=0, handover="every_tick"), 6)
    assert [call[0] for call in planner.calls] == [0, 1, 2, 3, 4, 5]
    assert [a[0, 0] - 0.5 for a in actions] == [1000 * c + 1 for c in range(6)]
    planner, prefixes = Scripted(), []
    plan = planner.plan
    planner.plan = lambda observations, zones, rows, generator, prefix=None: (
        prefixes.append(prefix), plan(observations, zones, rows, generator, prefix))[1]
    actions, _ = run(lockstep(planner, delay=2, handover="every_tick"), 9)
    assert [call[0] for call in planner.calls] == [0, 2, 4, 6, 8]
    assert [a[0, 0] - 0.5 for a in actions[2:7]] == [3, 4, 1003, 1004, 2003]
    held = prefixes[2].weights[0]  # asked at step 4, with chunk 1 (asked at 2) in force
    assert held[:CONFIG.first_executed + 2].eq(1).all() and held[CONFIG.first_executed + 2] < 1
    with pytest.raises(ValueError, match="every_tick"):
        LoopSettings(handover="sync", every_tick=True)


def test_zero_delay_is_the_lockstep_executor_whatever_the_handover() -> None:
    runs = []
    for handover in ("sync", "async", "async_prefix"):
        actions, _ = run(lockstep(Scripted(), delay=0, handover=handover), 20)
        runs.append(np.stack(actions))
    np.testing.assert_array_equal(runs[0], runs[1])
    np.testing.assert_array_equal(runs[0], runs[2])
    with pytest.raises(ValueError, match="handover"):
        lockstep(Scripted(), handover="later")


# -- The live loop (what the policy node runs in real time), with a tiny policy -----------------

SAFE = ConstraintConfig("safe", sampler="ddim", denoising_steps=3, resample=True, push=10,
                        project=True, inflate=True, path_repair=True, shield=True)


def observation_with_pusher(x: float, y: float) -> np.ndarray:
    obs = np.full(CONFIG.obs_dim, 256.0, dtype=np.float32)
    obs[18:20] = (x, y)
    return obs


def live(planner: ConstrainedPlanner, zones: LiveZones, lead: int | None = None,
         process_threads: int | None = None, **options: object) -> ChunkLoop:
    """The loop as the node runs it live: plans from a thread (or a process), warmed up."""
    warm_up(planner)
    return live_chunk_loop(planner, zones, process_threads, lead=lead, **options)


def installed(controller: ChunkLoop) -> None:
    """Wait for the worker's plan and install it, as the node does when woken."""
    for _ in range(5000):
        if not controller.worker.busy:
            break
        threading.Event().wait(0.002)
    controller.install_results()


def held_planner(policy: DiffusionPolicy) -> tuple[ConstrainedPlanner, threading.Event,
                                                  threading.Event]:
    """A planner whose plans wait for `release` (and say `started`): a plan held in flight
    while the test moves the controller on, whatever the machine's speed."""
    started, release = threading.Event(), threading.Event()
    planner = ConstrainedPlanner(policy, SAFE, PUSHT_ROBOT)
    plan = planner.plan

    def held_plan(*args, **kwargs):
        started.set()
        release.wait(5)
        return plan(*args, **kwargs)

    planner.plan = held_plan
    return planner, started, release


def test_the_status_reads_before_the_first_observation_and_across_episodes(
        tiny_policy: DiffusionPolicy) -> None:
    """The node reports on a timer, which may come before any observation."""
    controller = live(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), LiveZones(), lead=1)
    try:
        status = loop_status(controller)
        assert (status["plans"], status["held_steps"], status["waypoints_skipped"]) == (0, 0, 0)
        controller.observe(3, observation_with_pusher(100, 100))
        installed(controller)
        controller.observe(0, observation_with_pusher(100, 100))  # a new episode
        assert loop_status(controller)["plans"] >= 1
    finally:
        controller.shutdown()


def test_on_install_is_called_whichever_call_installs_the_plan(
        tiny_policy: DiffusionPolicy) -> None:
    """A plan that arrives just before an observation is installed by `observe`, not by the
    wake-up's `install_results`: the node must hear of it all the same (it times the reply
    to a zone and publishes the plan from there)."""
    calls = []
    controller = live(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), LiveZones(), lead=1,
                      on_install=lambda: calls.append(controller.stats.plans_installed))
    try:
        controller.observe(0, observation_with_pusher(100, 100))
        for _ in range(5000):  # the plan arrives; no one installs it before the next step
            if not controller.worker.busy and controller._results:
                break
            threading.Event().wait(0.002)
        controller.observe(1, observation_with_pusher(100, 100))  # takes the plan that came
        assert calls == [1]
        assert controller.install_results() is None  # nothing left: no second call
        assert calls == [1]
        controller.use_planner(controller.planner)  # asks for a plan at once
        installed(controller)
        assert calls == [1, 2]
    finally:
        controller.shutdown()


def test_the_controller_installs_a_late_plan_without_the_steps_that_passed(
        tiny_policy: DiffusionPolicy) -> None:
    planner, started, release = held_planner(tiny_policy)
    controller = live(planner, LiveZones())
    try:
        assert controller.step is None  # nothing observed yet
        controller.observe(0, observation_with_pusher(100, 100))
        held = controller.rows.setpoints[0]  # no chunk yet: the pusher held where it is; plan asked
        np.testing.assert_allclose(held, [100, 100])
        assert started.wait(5)
        for step in (1, 2, 3):  # the plan takes three steps to come in
            controller.observe(step, observation_with_pusher(100, 100))
        release.set()
        installed(controller)
        assert controller.stats.plans_installed == 1
        assert controller.queue.skipped == 3
        chunk = controller.queue.waypoints[0]
        np.testing.assert_allclose(controller.rows.setpoints[0], chunk[3])  # step 3's, not step 0's
    finally:
        controller.shutdown()


@pytest.mark.parametrize("process_threads", [None, 1], ids=["thread", "process"])
def test_a_zone_arriving_mid_chunk_gets_a_safe_setpoint_before_the_next_tick(
        tiny_policy: DiffusionPolicy, process_threads: int | None) -> None:
    zones = LiveZones()  # lead 1: no plan asked for the chunk running out, however slow plans
    controller = live(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT), zones, lead=1,
                      process_threads=process_threads)
    try:
        controller.observe(0, observation_with_pusher(200, 200))
        installed(controller)
        setpoint = controller.rows.setpoints[0]
        x, y = setpoint
        zones.upsert(1, rectangle(x - 20, y - 20, x + 20, y + 20), now=0.0)  # on the setpoint
        safe = controller.zones_changed()
        assert safe is not None and controller.stats.zone_reactions == 1
        controller.install_results()  # as the node does when woken
        inflated = zones.snapshot().inflate(PUSHT_ROBOT.pusher_radius)
        assert inflated.signed_distance(torch.tensor(safe[None])).item() > 0
        assert controller.stats.plans_asked == 2  # the rest of the chunk was replanned
        installed(controller)
        held = torch.tensor(controller.rows.setpoints[0][None])
        assert zones.snapshot().signed_distance(held) > 0
        zones.upsert(2, rectangle(400, 400, 450, 450), now=0.0)  # far away: nothing to do
        assert controller.zones_changed() is None
    finally:
        controller.shutdown()


def test_warming_up_leaves_the_planner_as_a_fresh_one(tiny_policy: DiffusionPolicy) -> None:
    """The zone reaction runs once before the clock starts (first calls paid before a real
    zone); the shield it touched is reset, so the setpoints that follow are a fresh planner's."""
    fresh, warmed = (ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT) for _ in range(2))
    warm_up(warmed)
    zones = LiveZones()
    zones.upsert(1, rectangle(180, 180, 220, 220), now=0.0)
    target = np.array([[210.0, 200.0]])  # inside: each guard moves it
    for step, x in enumerate((150, 155, 160)):
        observation = observation_with_pusher(x, 200)[None]
        expected = fresh.guard(zones.area_at(step), observation, target, step)
        assert not np.array_equal(expected, target)
        np.testing.assert_array_equal(warmed.guard(zones.area_at(step), observation, target,
                                                   step), expected)


def test_a_new_configuration_stops_the_plan_in_flight(tiny_policy: DiffusionPolicy) -> None:
    """The first configuration's plan is held in flight until the configuration has changed:
    it stops before its first denoising step, and the new configuration's plan goes in."""
    old, started, release = held_planner(tiny_policy)
    controller = live(old, LiveZones(), lead=1)
    try:
        controller.observe(0, observation_with_pusher(100, 100))
        assert started.wait(5)
        controller.use_planner(ConstrainedPlanner(tiny_policy, SAFE, PUSHT_ROBOT))
        release.set()
        installed(controller)
        stats = controller.stats
        assert (stats.plans_asked, stats.plans_dropped, stats.plans_installed) == (2, 0, 1)
        assert controller.worker.cancelled == 1
    finally:
        controller.shutdown()


def test_a_new_episode_stops_the_plan_in_flight_and_never_installs_one_from_before(
        tiny_policy: DiffusionPolicy) -> None:
    """The simulator resets (an earlier step comes) while a plan is in flight: that plan is
    stopped and the new episode's first plan asked at once. One from before that ends anyway
    (its stop came too late) is dropped: its generation is the old one."""
    planner, started, release = held_planner(tiny_policy)
    controller = live(planner, LiveZones(), lead=1)
    try:
        controller.observe(5, observation_with_pusher(100, 100))
        assert started.wait(5)
        controller.observe(0, observation_with_pusher(300, 300))  # the sim was reset
        # held, none from before
        np.testing.assert_allclose(controller.rows.setpoints[0], [300, 300])
        release.set()
        installed(controller)
        stats = controller.stats
        assert (stats.plans_asked, stats.plans_dropped, stats.plans_installed) == (2, 0, 1)
        assert controller.worker.cancelled == 1
        stale = PlanJob(controller.generation - 1, 5, controller.history.tensor(), None, 0, None)
        controller._on_result(PlanResult(stale, controller.queue.waypoints.copy(), 0.1))
        controller.install_results()
        assert (stats.plans_dropped, stats.plans_installed) == (1, 1)
    finally:
        controller.shutdown()


def test_a_zone_stops_the_first_plan_of_an_episode_like_any_other(
        tiny_policy: DiffusionPolicy) -> None:
    """The episode's first plan is asked at its first observation, knowing none of the zones
    that come while it is planned: a zone on the held setpoint stops it, and the replan goes in."""
    planner, started, release = held_planner(tiny_policy)
    zones = LiveZones()
    controller = live(planner, zones, lead=1)
    try:
        controller.observe(0, observation_with_pusher(100, 100))
        assert started.wait(5)
        zones.upsert(1, rectangle(95, 95, 105, 105), now=0.0)
        assert controller.zones_changed() is not None  # moved off the zone at once
        controller.install_results()  # as the node does when woken: the replan asked
        release.set()
        installed(controller)
        stats = controller.stats
        assert controller.worker.cancelled == 1
        assert (stats.plans_asked, stats.plans_dropped, stats.plans_installed) == (2, 0, 1)
    finally:
        controller.shutdown()


def test_fifo_priority_is_for_the_asking_thread_only_and_not_for_processes_it_starts() -> None:
    assert not request_fifo(0)
    seen: dict[str, object] = {}

    def ask() -> None:
        seen["granted"] = request_fifo(10)
        seen["policy"] = os.sched_getscheduler(0)
        child = "import os; print(os.sched_getscheduler(0))"
        seen["child"] = int(subprocess.run([sys.executable, "-c", child], capture_output=True,
                                           text=True, check=True).stdout)

    thread = threading.Thread(target=ask)
    thread.start()
    thread.join()
    if not seen["granted"]:
        pytest.skip("SCHED_FIFO is not allowed here")
    assert seen["policy"] & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO
    assert seen["child"] == os.SCHED_OTHER  # reset on fork: a planning process starts normal
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the test's own thread is untouched


def test_the_control_clock_ticks_on_its_own_threads_and_outlives_a_failing_tick() -> None:
    threads: list[str] = []
    three = threading.Event()

    def on_tick() -> None:
        threads.append(threading.current_thread().name)
        if len(threads) == 1:
            raise RuntimeError("a send that failed")
        if len(threads) == 3:
            three.set()

    clock = ControlClock(200.0, on_tick)
    try:
        assert three.wait(5)
    finally:
        clock.shutdown()
    assert all(name.startswith("control_clock_") for name in threads)
    assert threading.current_thread().name not in threads


class HeldUp(ControlClock):
    """A clock whose first thread always wakes 10 periods late, as on a CPU the hypervisor
    has taken away."""

    def _wait(self, seconds: float) -> bool:
        if threading.current_thread().name.endswith("_0"):
            seconds += 10 * self.period
        return super()._wait(seconds)


def test_a_clock_thread_woken_late_leaves_the_tick_to_the_other_and_none_is_sent_twice(
        ) -> None:
    sent: list[str] = []
    enough = threading.Event()

    def on_tick() -> None:
        sent.append(threading.current_thread().name)
        if len(sent) == 10:
            enough.set()

    clock = HeldUp(20.0, on_tick, threads=2)  # 50 ms periods: a busy CI machine misses none
    try:
        assert enough.wait(5)
    finally:
        clock.shutdown()
    assert set(sent) == {"control_clock_1"}  # the late thread found each tick sent
    assert clock.missed == 0 and clock.ticks == len(sent)


def test_a_clock_held_up_drops_the_ticks_it_missed_instead_of_bursting() -> None:
    """At 100 Hz a tick that takes 0.3 s misses about 30 deadlines; they are counted and
    dropped, so the clock resumes one tick per period instead of firing 30 at once."""
    count = 0
    resumed = threading.Event()

    def on_tick() -> None:
        nonlocal count
        count += 1
        if count == 1:
            threading.Event().wait(0.3)
        elif count == 2:
            resumed.set()

    clock = ControlClock(100.0, on_tick)
    try:
        assert resumed.wait(5)
        missed = clock.missed
        threading.Event().wait(0.05)  # 5 more periods: about 5 ticks, not the 30 missed
        ticks = clock.ticks
    finally:
        clock.shutdown()
    assert missed >= 20 and ticks < 15
