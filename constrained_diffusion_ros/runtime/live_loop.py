"""The chunk loop on the wall clock, as the policy node runs it: plans made in the background,
in a supervised child process (`planning_process`) or a thread of this process
(`thread_worker`). The loop's rules are the method's (`planning.chunk_loop`); what makes it
live is here."""

from __future__ import annotations

from collections.abc import Callable

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop, ZoneSource
from constrained_diffusion_ros.planning.plan_jobs import PlanResult, PlanWorker
from constrained_diffusion_ros.planning.planners import ChunkPlanner, ConstrainedPlanner
from constrained_diffusion_ros.runtime.planning_process import PlanningProcess
from constrained_diffusion_ros.runtime.thread_worker import PlanningThread


def live_chunk_loop(planner: ConstrainedPlanner, zones: ZoneSource,
                    process_threads: int | None = 1, idle: bool = True, noise_seed: int = 0,
                    **options: object) -> ChunkLoop:
    """The loop with plans made in a child process with `process_threads` torch threads, at
    idle priority if `idle` (`PlanningProcess`), or with None in a thread of this process
    (`PlanningThread`); `options` are the loop's (lead, soft, rate_hz, wake, every_tick,
    replan_on_zone_change, on_install)."""
    def make_worker(planner: ChunkPlanner, on_result: Callable[[PlanResult], None]
                    ) -> PlanWorker:
        if process_threads is None:
            return PlanningThread(planner, on_result, noise_seed)
        return PlanningProcess(planner, on_result, noise_seed, process_threads, idle=idle)
    return ChunkLoop(planner, make_worker, zones, noise_seed=noise_seed, **options)
