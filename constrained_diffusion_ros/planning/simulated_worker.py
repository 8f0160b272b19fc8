"""The simulated worker: plans in the caller's thread and delivers the plan `delay` control steps
after it was asked for (`PlanWorker`), so the evaluation, the delay study and lockstep mode run
the chunk loop the node runs, deterministically, with planning taking a chosen number of steps
(0: the plan is in force at the step it was asked for, the reference's lockstep execution).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from constrained_diffusion_ros.planning.plan_jobs import PlanJob, PlanResult, plan_chunk
from constrained_diffusion_ros.planning.planners import ChunkPlanner


class SimulatedPlanning:
    """Plans each job at once, with `generator` (None: torch's default), and hands the result
    to `on_result` marked ready `delay` steps after the job's step. Nothing is ever in flight,
    so nothing is cancelled, and nothing fails in the background: a planning error is raised
    to the caller."""

    priority = "the caller's thread"
    error: BaseException | None = None
    errors = restarts = cancelled = 0
    failed = False
    busy = False

    def __init__(self, planner: ChunkPlanner, on_result: Callable[[PlanResult], None],
                 generator: torch.Generator | None = None, delay: int = 0) -> None:
        if delay < 0:
            raise ValueError(f"delay must be >= 0, got {delay}")
        self.planner, self.on_result, self.generator, self.delay = \
            planner, on_result, generator, delay

    @classmethod
    def factory(cls, generator: torch.Generator | None = None, delay: int = 0
                ) -> Callable[[ChunkPlanner, Callable[[PlanResult], None]], SimulatedPlanning]:
        """What `ChunkLoop` takes: a worker for its planner and result callback."""
        return lambda planner, on_result: cls(planner, on_result, generator, delay)

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        began = time.perf_counter()
        chunk = plan_chunk(self.planner, job, self.generator)
        self.on_result(PlanResult(job, chunk, time.perf_counter() - began,
                                  ready_step=job.step + self.delay))

    def use(self, planner: ChunkPlanner) -> None:
        self.planner = planner

    def reseed(self, noise_seed: int) -> None:
        if self.generator is not None:
            self.generator.manual_seed(noise_seed)

    def shutdown(self, timeout: float = 5.0) -> None:
        """Nothing runs in the background."""
