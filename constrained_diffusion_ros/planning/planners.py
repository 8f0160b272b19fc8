"""Planners: a constraint configuration applied to a policy, for the node and the evaluation.

A planner turns observation histories and the zones in force into constrained action chunks,
names the area its chunks keep their waypoints out of (so a planning loop can tell when new zones
invalidate a chunk), and, with the shield, has the last word on each executed setpoint. The
loop drives any planner through these three methods (`ChunkPlanner`), for some rows of its
batch of episodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.planning.shield import PusherShield
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.policy_config import PolicyConfig
from constrained_diffusion_ros.sampling.hooks import (
    CommittedPrefix,
    FinalProjection,
    GradientPush,
    LastUpdate,
    OnRows,
    PathRepair,
    Resampling,
    ResamplingThenPush,
    ShrinkingMargin,
    Until,
)
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler, SampleHook
from constrained_diffusion_ros.zones.area import RestrictedArea


class ChunkPlanner(Protocol):
    """What the chunk loop needs. `zones` answer for the rows asked about (a batch-aware
    area, or one area for all), or are None when no zone is in force."""

    robot: RobotModel  # where the pusher is in an observation, for holding it still

    @property
    def policy_config(self) -> PolicyConfig: ...

    def plan(self, observations: Tensor, zones: RestrictedArea | None, rows: np.ndarray,
             generator: torch.Generator | None, prefix: CommittedPrefix | None = None) -> Tensor:
        """(R, n_obs_steps, obs_dim) histories of rows `rows` -> (R, horizon, 2) chunks; with
        `prefix`, their first waypoints continue the chunks in force (real-time chunking)."""
        ...

    def violates(self, waypoints: Tensor, zones: RestrictedArea | None,
                 rows: np.ndarray) -> Tensor:
        """Bool (R, N): which waypoints (R, N, 2) of rows `rows` lie where its plans keep
        waypoints out of, or outside the workspace (where zones that left no free space may
        have pushed them)."""
        ...

    def keep_out(self, zones: RestrictedArea | None, points: np.ndarray,
                 rows: np.ndarray | None = None) -> np.ndarray:
        """(R, 2) waypoints of rows `rows` planned before `zones` came -> the same, those
        inside the area its plans keep waypoints out of moved just outside it."""
        ...

    def guard(self, zones: RestrictedArea | None, observations: np.ndarray,
              setpoints: np.ndarray, step: int) -> np.ndarray:
        """(B, 2) setpoints about to be executed at control step `step`, for the whole batch
        (latest observations (B, obs_dim)) -> the setpoints to execute."""
        ...

    def reset(self) -> None:
        """A new episode begins."""
        ...


class ConstrainedPlanner:
    """One configuration applied to one policy: the same code path for evaluation and nodes."""

    def __init__(self, policy: DiffusionPolicy, config: ConstraintConfig,
                 robot: RobotModel) -> None:
        self.policy, self.config, self.robot = policy, config, robot
        # The filter before (slide: false) is kept as it was, for the side-by-side comparison.
        self.shield = (PusherShield(robot, slide=config.slide, late=config.slide)
                       if config.shield else None)

    @cached_property
    def sampler(self) -> DenoisingSampler:
        """Built at the first plan, or by `prepare_sampling`: a planner that only guards
        setpoints, as the live node's does while its planning process plans, never builds a
        scheduler and so never imports diffusers, a slow import at start-up."""
        c = self.config
        return DenoisingSampler(self.policy, c.sampler, c.denoising_steps, c.timestep_spacing,
                                c.eta, c.zone_guidance)

    def prepare_sampling(self) -> None:
        """Builds the sampler now, so that the first plan does not wait for it (nor import
        diffusers on a planning thread while the control clock waits for the interpreter)."""
        _ = self.sampler

    @property
    def policy_config(self) -> PolicyConfig:
        return self.policy.config

    def effective_area(self, zones: RestrictedArea, radius: float | None = None
                       ) -> RestrictedArea:
        """The area the hooks see: the zones plus the outside of the workspace, grown by
        `radius` (default: the pusher radius if the configuration inflates, else 0). Derived
        areas are cached by the zones themselves."""
        if radius is None:
            radius = self.robot.pusher_radius if self.config.inflate else 0.0
        return zones.bounded(self.robot.workspace).inflate(radius)

    def planning_area(self, zones: RestrictedArea) -> RestrictedArea:
        """The area the hooks steer a chunk against: `effective_area`, with zones that move
        forecast to where they will be when each waypoint runs (`MovingZones.ahead`;
        waypoint `first_executed` runs at the observation, one more each control step)."""
        area = self.effective_area(zones)
        ahead = getattr(area, "ahead", None)
        if ahead is None:
            return area
        config = self.policy.config
        steps = (torch.arange(config.horizon, dtype=torch.float64)
                 - config.first_executed).clamp_min(0.0)
        return ahead(steps / self.robot.control_hz)

    def hooks(self, area: RestrictedArea, pusher: Tensor) -> list[SampleHook]:
        c, first = self.config, self.policy.config.first_executed
        guidance: list[SampleHook] = []
        if c.resample and c.push > 0:
            guidance.append(ResamplingThenPush(area, c.push))
        elif c.resample:
            guidance.append(Resampling(area))
        elif c.push > 0:
            guidance.append(GradientPush(area, c.push))
        if c.margin_shrink > 0:
            guidance = [ShrinkingMargin(g, c.margin_shrink) for g in guidance]
        hooks = guidance if c.guide_until >= 1.0 else [Until(g, c.guide_until) for g in guidance]
        if c.project:
            hooks.append(FinalProjection(area, c.margin))
        if c.path_repair:
            hooks.append(PathRepair(area, pusher, first, c.margin, c.repair_from, c.slide))
        return hooks

    def plan(self, observations: Tensor, zones: RestrictedArea | None,
             rows: np.ndarray | None = None, generator: torch.Generator | None = None,
             prefix: CommittedPrefix | None = None) -> Tensor:
        """(B, n_obs_steps, obs_dim) -> (B, horizon, 2) workspace setpoints. The prefix hook
        runs before the constraint hooks (see `CommittedPrefix`)."""
        first: list[SampleHook] = [] if prefix is None else [prefix]
        if zones is None or not self.config.constrains:
            return self.sampler.sample(observations, generator, first)
        area = self.planning_area(zones)
        if self.config.from_scratch:
            return self._from_scratch(observations, zones, area, generator)
        if self.config.candidates > 1:
            return self._best_of(observations, zones, generator, prefix)
        pusher = self.robot.pusher(observations[:, -1])
        return self.sampler.sample(observations, generator, first + self.hooks(area, pusher),
                                   zones)

    def violates(self, waypoints: Tensor, zones: RestrictedArea | None,
                 rows: np.ndarray | None = None) -> Tensor:
        outside = torch.from_numpy(self.robot.outside(waypoints.numpy()))
        if zones is None or not self.config.constrains:
            return outside
        return outside | self.effective_area(zones).contains(waypoints)

    def keep_out(self, zones: RestrictedArea | None, points: np.ndarray,
                 rows: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) waypoints planned before `zones` came: those inside the area its plans keep
        waypoints out of move just outside it. Fast, for the zone callback: one step along the
        way out, and the full projection only where that step is not enough."""
        if zones is None or not self.config.constrains:
            return points
        area, margin = self.effective_area(zones), self.config.margin + 1e-3
        p = torch.from_numpy(np.asarray(points, float))
        depth = area.signed_distance(p)
        inside = depth < self.config.margin
        if not inside.any():
            return points
        stepped = p + (margin - depth)[:, None] * area.outward_direction(p)
        stuck = inside & (area.signed_distance(stepped) < self.config.margin)
        if stuck.any():
            stepped[stuck] = area.project_out(p[stuck], margin)
        return torch.where(inside[:, None], stepped, p).numpy()

    def guard(self, zones: RestrictedArea | None, observations: np.ndarray,
              setpoints: np.ndarray, step: int) -> np.ndarray:
        if self.shield is None:
            return setpoints
        positions = self.robot.pusher(observations).astype(float)
        # The shield keeps the pusher's body out: it always sees the zones grown by its radius.
        body = None if zones is None else self.effective_area(zones, self.robot.pusher_radius)
        return self.shield(body, positions, setpoints, step)

    def reset(self) -> None:
        """A new episode: the shield forgets the last one."""
        if self.shield is not None:
            self.shield.reset()

    def _best_of(self, observations: Tensor, zones: RestrictedArea,
                 generator: torch.Generator | None, prefix: CommittedPrefix | None) -> Tensor:
        """Candidate selection (as DPCC chooses by projection cost): `candidates` chunks per
        episode, denoised in one batch with all the hooks; keep the one whose executed
        waypoints the final projection and path repair moved least, the one the policy's
        own plan least disagrees with the zones (ties: the first)."""
        k, batch = self.config.candidates, len(observations)
        rows = torch.arange(batch).repeat_interleave(k)
        zones = zones.select_rows(rows)
        area = self.planning_area(zones)
        hooks = self.hooks(area, self.robot.pusher(observations[rows, -1]))
        steering = [h for h in hooks if not isinstance(h, FinalProjection | PathRepair)]
        last = LastUpdate()
        first = [] if prefix is None else [prefix.repeated(k)]
        chunks = self.sampler.sample(observations[rows], generator,
                                     first + steering + [last] + hooks[len(steering):],
                                     zones)
        start = self.policy.config.first_executed
        executed = slice(start, start + self.policy.config.n_action_steps)
        moved = (chunks - last.sample)[:, executed].norm(dim=-1).sum(dim=-1)
        choice = moved.reshape(batch, k).argmin(dim=1)
        return chunks.reshape(batch, k, *chunks.shape[1:])[torch.arange(batch), choice]

    def _from_scratch(self, observations: Tensor, zones: RestrictedArea,
                      area: RestrictedArea, generator: torch.Generator | None) -> Tensor:
        """The baseline the paper argues against: N whole chunks per episode in one batch; keep
        the first whose executed waypoints all lie outside, else the one with fewest inside."""
        n, (batch, *rest) = self.config.from_scratch, observations.shape
        repeated = observations[:, None].expand(batch, n, *rest).reshape(batch * n, *rest)
        chunks = self.sampler.sample(repeated, generator, (),
                                     zones.select_rows(torch.arange(batch).repeat_interleave(n))
                                     ).reshape(batch, n, -1, 2)
        first = self.policy.config.first_executed
        executed = slice(first, first + self.policy.config.n_action_steps)
        inside = area.contains(chunks)[:, :, executed].sum(dim=-1)  # (batch, n)
        # Fewest violations; ties go to the earliest candidate ("the first that fits").
        order = inside * n + torch.arange(n)
        chosen = chunks[torch.arange(batch), order.argmin(dim=1)]
        return area.project_out(chosen, self.config.margin) if self.config.project else chosen


class MixedPlanner:
    """Configurations with one `sampler_key`, planned as one batch: a single network call per
    denoising step for all their episodes, each configuration's hooks and shield on its own
    rows (`owner[b]` is the configuration of row b). One batch for all, because the network's
    cost per sample falls as the batch grows (in a batch of hundreds, about half what it is in
    one of tens)."""

    def __init__(self, policy: DiffusionPolicy, configs: Sequence[ConstraintConfig],
                 robot: RobotModel, owner: np.ndarray) -> None:
        if len({c.sampler_key for c in configs}) != 1:
            raise ValueError("a mixed batch needs configurations with one sampler and no "
                             "from-scratch sampling among several")
        self.planners = [ConstrainedPlanner(policy, c, robot) for c in configs]
        self.owner, self.robot = np.asarray(owner), robot

    @property
    def policy_config(self) -> PolicyConfig:
        return self.planners[0].policy_config

    def _by_config(self, rows: np.ndarray):
        """(planner, positions within `rows` that are its) per configuration that constrains."""
        owner = self.owner[rows]
        for index, planner in enumerate(self.planners):
            mine = np.nonzero(owner == index)[0]
            if len(mine) and planner.config.constrains:
                yield planner, mine

    def plan(self, observations: Tensor, zones: RestrictedArea | None, rows: np.ndarray,
             generator: torch.Generator | None = None,
             prefix: CommittedPrefix | None = None) -> Tensor:
        if len(self.planners) == 1:
            return self.planners[0].plan(observations, zones, rows, generator, prefix)
        hooks: list[SampleHook] = [] if prefix is None else [prefix]
        seen_by = torch.zeros(len(observations), dtype=torch.bool)  # rows that constrain
        for planner, mine in self._by_config(rows) if zones is not None else ():
            area = planner.planning_area(zones.select_rows(mine))
            pusher = self.robot.pusher(observations[mine, -1])
            mine_rows = torch.from_numpy(mine)
            hooks += [OnRows(hook, mine_rows) for hook in planner.hooks(area, pusher)]
            seen_by[mine_rows] = True
        return self.planners[0].sampler.sample(observations, generator, hooks, zones, seen_by)

    def violates(self, waypoints: Tensor, zones: RestrictedArea | None,
                 rows: np.ndarray) -> Tensor:
        inside = torch.from_numpy(self.robot.outside(waypoints.numpy()))
        for planner, mine in self._by_config(rows) if zones is not None else ():
            inside[mine] |= planner.violates(waypoints[mine], zones.select_rows(mine))
        return inside

    def keep_out(self, zones: RestrictedArea | None, points: np.ndarray,
                 rows: np.ndarray | None = None) -> np.ndarray:
        rows = np.arange(len(points)) if rows is None else np.asarray(rows)
        out = np.array(points, dtype=float)
        for planner, mine in self._by_config(rows) if zones is not None else ():
            out[mine] = planner.keep_out(zones.select_rows(mine), out[mine])
        return out

    def guard(self, zones: RestrictedArea | None, observations: np.ndarray,
              setpoints: np.ndarray, step: int) -> np.ndarray:
        out = setpoints.copy()
        for planner, rows in self._by_config(np.arange(len(self.owner))):
            if planner.shield is not None:
                own = None if zones is None else zones.select_rows(rows)
                out[rows] = planner.guard(own, observations[rows], setpoints[rows], step)
        return out

    def reset(self) -> None:
        for planner in self.planners:
            planner.reset()
