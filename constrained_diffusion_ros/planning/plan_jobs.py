"""What a background planner is asked and answers, the one contract between the real-time
controller and its workers: a job (`PlanJob`), its result (`PlanResult`), how a job is planned
(`plan_chunk`), the messages of the planning process's protocol (`Request`, `Reply`) and what every
worker offers (`PlanWorker`).

Two workers implement `PlanWorker`: `PlanningThread` (thread_worker.py) plans in a thread of
the node's process, `PlanningProcess` (planning_process.py) in a child process.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

import numpy as np
import torch

from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.sampling.hooks import CommittedPrefix
from constrained_diffusion_ros.zones.area import RestrictedArea


@dataclass
class PlanJob:
    """One request to the background planner: everything it needs, copied when asked."""

    generation: int
    step: int  # the control step of the newest observation in `observations`
    observations: torch.Tensor  # (1, n_obs_steps, obs_dim)
    zones: RestrictedArea | None  # the zones in force when asked
    zone_version: int
    prefix: CommittedPrefix | None


@dataclass
class PlanResult:
    job: PlanJob
    chunk: np.ndarray  # (horizon, 2)
    seconds: float


def plan_chunk(planner: ConstrainedPlanner, job: PlanJob, generator: torch.Generator,
               interrupt: Callable[[], bool] = lambda: False) -> np.ndarray:
    """(horizon - first_executed, 2) the executed part of a chunk planned for `job` and the
    rest of the horizon after it; raises `Interrupted` once `interrupt()` is true."""
    with planner.sampler.interruptible(interrupt):
        chunk = planner.plan(job.observations, job.zones, None, generator, job.prefix)
    return chunk[0, planner.policy_config.first_executed:].numpy().astype(float)


class PlanWorker(Protocol):
    """A background planner: where the next chunk is denoised while the current one executes,
    as `RealtimeController` drives it.

    `submit` replaces a job not yet started (only the newest request matters), and with
    `cancel` stops the one in flight; a result goes to the owner's `on_result` with its job,
    whose generation the owner compares with its own to drop plans that a zone or configuration
    change made stale. `use` and `reseed` apply from the next job on; `shutdown` stops and joins
    (like tf2_ros's listener, each worker owns its thread). For the node's diagnostics a worker
    keeps `error` (the last fault), `errors` (faults so far), `failed` (a fault since the last
    plan that arrived: nothing may be planning), `restarts` (children started again after
    dying), `cancelled` (plans stopped in flight) and `priority` (how its planning is
    scheduled, in words).
    """

    error: BaseException | None
    errors: int
    failed: bool
    restarts: int
    cancelled: int
    priority: str

    @property
    def busy(self) -> bool:
        """A job is waiting or being planned."""
        ...

    def submit(self, job: PlanJob, cancel: bool = False) -> None:
        """Plan `job` next, in place of any job not yet started; `cancel`: stop the one in
        flight too."""
        ...

    def use(self, planner: ConstrainedPlanner) -> None:
        """Plan with `planner` (another configuration of the same policy) from the next job
        on."""
        ...

    def reseed(self, noise_seed: int) -> None:
        """A new episode: the same noise as a fresh node from the next job on; the plan in
        flight and any job waiting are the last episode's, and dropped."""
        ...

    def shutdown(self, timeout: float = 5.0) -> None:
        """Stop planning and join the worker's threads (and its child, if any)."""
        ...


class Request(StrEnum):
    """What the node sends the planning child: each message is the pickled pair (kind, pickled
    payload), the kind as a plain string, so it always reads back, even where the payload
    cannot (a class the other side cannot import)."""

    POLICY = "policy"  # the policy's weights, once per child, before anything else
    PLANNER = "planner"  # (constraint configuration, robot model) to plan with
    SEED = "seed"  # the noise seed, applied before the next job
    JOB = "job"  # (PlanJob, same_zones): plan it; with same_zones its zones are the last ones
    CANCEL = "cancel"  # stop the plan in flight (any message does; this one does nothing else)
    STOP = "stop"  # exit


class Reply(StrEnum):
    """What the planning child answers, framed as `Request` is; every payload is (payload,
    seconds the message took in the child). A job ends with exactly one of `CHUNK`,
    `CANCELLED` or `JOB_ERROR`."""

    SCHEDULING = "scheduling"  # how the child is scheduled, as it found it (`scheduling()`)
    CHUNK = "chunk"  # the chunk planned for the job (`plan_chunk`)
    CANCELLED = "cancelled"  # the job was stopped by a message that came while it planned
    JOB_ERROR = "job_error"  # the job failed: the fault, in words
    ERROR = "error"  # another message failed (a planner or seed): the fault; no job ended
