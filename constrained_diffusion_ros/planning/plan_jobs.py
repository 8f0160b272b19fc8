"""What a planning worker is asked and answers, the one contract between the chunk loop and its
workers: a job (`PlanJob`), its result (`PlanResult`), how a job is planned (`plan_chunk`), the
messages of the planning process's protocol (`Request`, `Reply`) and what every worker offers
(`PlanWorker`).

Three workers implement `PlanWorker`: `SimulatedPlanning` (simulated_worker.py) plans in the
caller's thread and delivers after a simulated delay, for the evaluation and lockstep mode;
`PlanningThread` (thread_worker.py) plans in a thread of the node's process, `PlanningProcess`
(planning_process.py) in a child process.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

import numpy as np
import torch

from constrained_diffusion_ros.planning.planners import ChunkPlanner, ConstrainedPlanner
from constrained_diffusion_ros.sampling.hooks import CommittedPrefix
from constrained_diffusion_ros.zones.area import RestrictedArea


@dataclass
class PlanJob:
    """One request to a planning worker: everything it needs, copied when asked."""

    generation: int
    step: int  # the control step of the newest observation in `observations`
    observations: torch.Tensor  # (R, n_obs_steps, obs_dim)
    zones: RestrictedArea | None  # the zones in force when asked, for these rows
    zone_version: np.ndarray  # (R,) their version (one for all rows: broadcast)
    prefix: CommittedPrefix | None
    rows: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))  # (R,) the
    # loop's rows (episodes) it plans for; one episode by default
    serial: int = 0  # the asking loop's number for it (1, 2, ...); 0: none given

    def __post_init__(self) -> None:
        self.zone_version = np.broadcast_to(np.asarray(self.zone_version), self.rows.shape)


@dataclass
class PlanResult:
    job: PlanJob
    chunk: np.ndarray  # (R, horizon - first_executed, 2)
    seconds: float
    ready_step: int | None = None  # a simulated delay: not before this control step


def plan_chunk(planner: ChunkPlanner, job: PlanJob, generator: torch.Generator | None,
               interrupt: Callable[[], bool] | None = None) -> np.ndarray:
    """(R, horizon - first_executed, 2) the executed part of the chunks planned for `job` and
    the rest of the horizon after it; raises `Interrupted` once `interrupt()` is true (a
    `ConstrainedPlanner`'s sampler asks it before each denoising step)."""
    with (contextlib.nullcontext() if interrupt is None
          else planner.sampler.interruptible(interrupt)):
        chunk = planner.plan(job.observations, job.zones, job.rows, generator, job.prefix)
    return chunk[:, planner.policy_config.first_executed:].numpy().astype(float)


class PlanWorker(Protocol):
    """A planning worker: where the next chunk is denoised while the current one executes, as
    `ChunkLoop` drives it.

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
