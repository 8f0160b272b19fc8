"""The chunk loop on the wall clock, as the policy node runs it: plans made in the background,
in a supervised child process (`planning_process`) or a thread of this process
(`thread_worker`). The loop's rules are the method's (`planning.chunk_loop`); what makes it
live is here, with `warm_up`, which spares the first live zone the first calls' cost, and
`loop_status`, the loop's and its worker's counters for the node's diagnostics."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop, LoopSettings, ZoneSource
from constrained_diffusion_ros.planning.plan_jobs import PlanResult, PlanWorker
from constrained_diffusion_ros.planning.planners import ChunkPlanner, ConstrainedPlanner
from constrained_diffusion_ros.runtime.planning_process import PlanningProcess
from constrained_diffusion_ros.runtime.thread_worker import PlanningThread
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.live import LiveZones
from constrained_diffusion_ros.zones.plugins import ZoneCheckError


def live_chunk_loop(planner: ConstrainedPlanner, zones: ZoneSource,
                    process_threads: int | None = 1, idle: bool = True,
                    wake: Callable[[], None] = lambda: None,
                    on_install: Callable[[], None] = lambda: None,
                    **settings: object) -> ChunkLoop:
    """The loop with plans made in a child process with `process_threads` torch threads, at
    idle priority if `idle` (`PlanningProcess`), or with None in a thread of this process
    (`PlanningThread`); `settings` are the loop's (`LoopSettings`: lead, soft, rate_hz,
    every_tick, replan_on_zone_change, noise_seed (0 by default), ...)."""
    chosen = LoopSettings(**{"noise_seed": 0, **settings})
    seed = chosen.noise_seed or 0

    def make_worker(planner: ChunkPlanner, on_result: Callable[[PlanResult], None]
                    ) -> PlanWorker:
        if process_threads is None:
            return PlanningThread(planner, on_result, seed)
        return PlanningProcess(planner, on_result, seed, process_threads, idle=idle)
    return ChunkLoop(planner, make_worker, zones, chosen, wake=wake, on_install=on_install)


def warm_up(planner: ConstrainedPlanner) -> None:
    """Runs the zone reaction's computing once on a scratch zone: a new zone is then not the
    first to pay for lazy imports and first calls, time the node's executor holds the
    interpreter while the clock waits for it. Leaves the planner as it found it (its shield
    reset)."""
    robot = planner.robot
    x_min, y_min, x_max, y_max = robot.workspace
    centre, half = np.array([(x_min + x_max) / 2, (y_min + y_max) / 2]), (x_max - x_min) / 8
    scratch = LiveZones(workspace=robot.workspace)
    scratch.apply([("warm_up", [tuple(centre + half * np.array(corner))
                                for corner in ((-1, -1), (1, -1), (1, 1), (-1, 1))])], 0.0)
    area, point = scratch.area_at(0), centre[None]
    leaves_no_room(scratch.snapshot().geometry, robot.workspace, robot.pusher_radius)
    planner.violates(torch.from_numpy(point[None]), area, np.array([0]))
    observation = np.zeros((1, planner.policy_config.obs_dim))
    planner.guard(area, observation, planner.keep_out(area, point), 0)
    planner.reset()


def loop_status(loop: ChunkLoop) -> dict[str, object]:
    """The loop's and its worker's counters for the node's diagnostics (`planning_error`: the
    worker's last fault, or None; `zone_check_error`: a plug-in zone check's last fault, or
    "", `zone_check_failed` while it stops the pushers), and the first row's state:
    `holding` its last setpoint (no waypoint), `shielded` (the setpoint is not the waypoint:
    the filter changed it), `cornered` by a moving zone. Read before the first observation
    too (the node reports on a timer)."""
    stats, worker = loop.stats, loop.worker
    started = loop.history is not None
    return {"holding": started and bool(loop.rows.waiting[0]),  # no waypoint: the last held
            "shielded": started and bool(np.any(loop.rows.setpoints[0]
                                                != loop.rows.wanted[0])),
            "plans": stats.plans_installed, "plans_dropped": stats.plans_dropped,
            "plans_cancelled": worker.cancelled,
            "waypoints_skipped": loop.skipped_before + loop.queue.skipped,
            "held_steps": stats.held_steps, "late_steps": stats.late_steps,
            "zone_reactions": stats.zone_reactions,
            "lead": loop.lead, "planning_priority": worker.priority,
            "planning_errors": worker.errors, "planning_failed": worker.failed,
            "planning_restarts": worker.restarts, "planning_error": worker.error,
            "zone_check_errors": loop.zone_check_errors,
            **_cornered(loop),
            "zone_check_failed": loop.zone_check_failed or (
                worker.failed and isinstance(worker.error, ZoneCheckError)),
            "zone_check_error": str(loop.zone_check_error or "")}


def _cornered(loop: ChunkLoop) -> dict[str, object]:
    """Whether the shield's last answer for the first row found it cornered by a moving
    zone (no free space to retreat into), and how often it was so far."""
    shield = getattr(loop.planner, "shield", None)
    if shield is None:
        return {}
    return {"cornered": bool(shield.cornered[:1].any()),
            "cornered_steps": shield.cornered_steps}
