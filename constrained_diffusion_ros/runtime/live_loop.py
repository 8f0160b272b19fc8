"""The chunk loop on the wall clock, as the policy node runs it: plans made in the background,
in a supervised child process (`planning_process`) or a thread of this process
(`thread_worker`). The loop's rules are the method's (`planning.chunk_loop`); what makes it
live is here."""

from __future__ import annotations

from collections.abc import Callable

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop, LoopSettings, ZoneSource
from constrained_diffusion_ros.planning.plan_jobs import PlanResult, PlanWorker
from constrained_diffusion_ros.planning.planners import ChunkPlanner, ConstrainedPlanner
from constrained_diffusion_ros.runtime.planning_process import PlanningProcess
from constrained_diffusion_ros.runtime.thread_worker import PlanningThread


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
