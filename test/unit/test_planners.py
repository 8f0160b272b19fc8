"""Planners: a configuration's hooks on a policy, mixed batches, from scratch, per-episode zones."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from samples import CENTRE, executed, observations

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner, MixedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import EpisodeZones, ZoneSet, rectangle

AGENT_RADIUS = PUSHT_ROBOT.pusher_radius


# -- The planner ---------------------------------------------------------------------------------

def ddim(name: str, **fields: object) -> ConstraintConfig:
    return ConstraintConfig(name, sampler="ddim", denoising_steps=5, **fields)


def planner_for(policy: DiffusionPolicy, config: ConstraintConfig) -> ConstrainedPlanner:
    return ConstrainedPlanner(policy, config, PUSHT_ROBOT)


def seeded() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def test_planner_with_projection_plans_no_waypoint_inside(tiny_policy: DiffusionPolicy) -> None:
    obs = observations(6)
    free = planner_for(tiny_policy, ddim("none")).plan(obs, CENTRE, generator=seeded())
    assert CENTRE.contains(free).any()
    projecting = planner_for(tiny_policy, ddim("p", project=True))
    planned = projecting.plan(obs, CENTRE, generator=seeded())
    assert not CENTRE.contains(planned).any()
    assert CENTRE.signed_distance(planned).min() >= 1.0 - 1e-4  # the default margin


def test_planner_with_inflation_keeps_the_pusher_radius_clear(tiny_policy: DiffusionPolicy) -> None:
    obs = observations(6)
    plain = planner_for(tiny_policy, ddim("p", project=True)).plan(
        obs, CENTRE, generator=seeded())
    inflated = planner_for(tiny_policy, ddim("pi", project=True, inflate=True)).plan(
        obs, CENTRE, generator=seeded())
    assert CENTRE.signed_distance(plain).min() < AGENT_RADIUS  # inflation is what makes it hold
    assert CENTRE.signed_distance(inflated).min() >= AGENT_RADIUS


def test_a_mixed_batch_constrains_each_configuration_on_its_own_rows(
        tiny_policy: DiffusionPolicy) -> None:
    owner = np.array([0, 1, 0, 1, 0, 1])
    mixed = MixedPlanner(tiny_policy, [ddim("none"), ddim("p", project=True)], PUSHT_ROBOT, owner)
    plan = mixed.plan(observations(6), CENTRE, np.arange(6), seeded())
    plain = planner_for(tiny_policy, ddim("none")).plan(observations(6), None, generator=seeded())
    inside = CENTRE.contains(executed(tiny_policy, plan)).any(dim=1).numpy()
    assert not inside[owner == 1].any()  # projected
    free = torch.from_numpy(owner == 0)  # left alone, up to the hooks' pixel round trips
    torch.testing.assert_close(plan[free], plain[free], atol=1e-3, rtol=0.0)
    assert inside[owner == 0].any()


def test_a_mixed_batch_needs_one_sampler(tiny_policy: DiffusionPolicy) -> None:
    with pytest.raises(ValueError, match="one sampler"):
        MixedPlanner(tiny_policy, [ddim("a"), ConstraintConfig("b", project=True)],
                     PUSHT_ROBOT, np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match="one sampler"):
        MixedPlanner(tiny_policy, [ddim("a"), ddim("b", from_scratch=4)], PUSHT_ROBOT,
                     np.zeros(2, dtype=int))


def test_from_scratch_keeps_the_candidate_with_fewest_violations(
        tiny_policy: DiffusionPolicy) -> None:
    n, obs = 8, observations(4)
    planner = planner_for(tiny_policy, ddim("scratch", from_scratch=n))
    repeated = obs[:, None].expand(4, n, 2, 20).reshape(4 * n, 2, 20)
    candidates = planner.sampler.sample(repeated, torch.Generator().manual_seed(0))
    candidates = candidates.reshape(4, n, 16, 2)

    most = ZoneSet.from_polygons([rectangle(0, 0, 400, 512)])
    counts = most.contains(executed(tiny_policy, candidates)).sum(dim=-1)  # (4, n)
    assert (counts.amin(dim=1) < counts.amax(dim=1)).all()  # the choice matters in every row
    chosen = planner.plan(obs, most, generator=seeded())
    expected = counts.argmin(dim=1)  # argmin returns the first of equal minima
    assert torch.equal(chosen, candidates[torch.arange(4), expected])
    assert torch.equal(most.contains(executed(tiny_policy, chosen)).sum(dim=-1),
                       counts.amin(dim=1))

    # Nothing violates a tiny zone far from every candidate: the first candidate fits.
    tiny = ZoneSet.from_polygons([rectangle(300, 300, 301, 301)])
    assert not tiny.contains(candidates).any()
    chosen = planner.plan(obs, tiny, generator=seeded())
    assert torch.equal(chosen, candidates[:, 0])


def test_candidate_selection_keeps_the_chunk_the_projection_moved_least(
        tiny_policy: DiffusionPolicy) -> None:
    """Every candidate is steered and projected; the one kept needed the least change, and no
    waypoint of it is inside (the guarantee of the projection stays)."""
    k, obs = 4, observations(3)
    rows = torch.arange(3).repeat_interleave(k)
    most = ZoneSet.from_polygons([rectangle(0, 0, 400, 512)])
    steered = dict(resample=True, push=10.0)
    projected = planner_for(tiny_policy, ddim("p", project=True, **steered)).plan(
        obs[rows], most, generator=seeded())
    raw = planner_for(tiny_policy, ddim("s", **steered)).plan(obs[rows], most,
                                                              generator=seeded())
    moved = (executed(tiny_policy, projected) - executed(tiny_policy, raw)).norm(dim=-1)
    moved = moved.sum(dim=-1).reshape(3, k)
    assert (moved.amin(dim=1) < moved.amax(dim=1)).all()  # the choice matters in every row
    chosen = planner_for(tiny_policy, ddim("best", project=True, candidates=k, **steered)
                         ).plan(obs, most, generator=seeded())
    expected = projected.reshape(3, k, 16, 2)[torch.arange(3), moved.argmin(dim=1)]
    torch.testing.assert_close(chosen, expected)
    assert not most.contains(chosen).any()


def test_each_episode_is_constrained_by_its_own_zone(tiny_policy: DiffusionPolicy) -> None:
    # Halves of the plane (beyond the walls too, so the only way out is across x = 256).
    left = ZoneSet.from_polygons([rectangle(-2000, -2000, 256, 2000)])
    right = ZoneSet.from_polygons([rectangle(256, -2000, 2000, 2000)])
    areas = EpisodeZones([left, right], [0, 1])
    planner = planner_for(tiny_policy, ddim("p", project=True, margin=2.0))
    obs = observations(2)
    free = planner.plan(obs, None, generator=seeded())
    assert (free[0, :, 0] < 256).any() and (free[1, :, 0] > 256).any()
    planned = planner.plan(obs, areas, generator=seeded())
    assert (planned[0, :, 0] >= 258 - 1e-3).all()  # row 0: out of the left band only
    assert (planned[1, :, 0] <= 254 + 1e-3).all()  # row 1: out of the right band only


def test_planner_without_constraints_ignores_the_zone(tiny_policy: DiffusionPolicy) -> None:
    planner = planner_for(tiny_policy, ddim("none"))
    obs = observations(3)
    with_zone = planner.plan(obs, CENTRE, generator=seeded())
    without = planner.plan(obs, None, generator=seeded())
    assert torch.equal(with_zone, without)



def test_planner_projection_never_leaves_the_workspace_for_a_zone_on_the_wall(
    tiny_policy: DiffusionPolicy,
) -> None:
    """A band against the left wall: the way out is its right edge, never through the wall."""
    band = load_scenarios()["left_0.5"].zones_at(0)
    for inflate in (False, True):
        planner = planner_for(tiny_policy, ddim("p", project=True, inflate=inflate))
        obs = observations(16)
        obs[..., 0::2] = obs[..., 0::2] * 0.4  # observations on the left: plans go there
        chunks = planner.plan(obs, band, generator=seeded())
        clearance = 15.0 if inflate else 0.0
        assert not band.contains(chunks).any()
        assert torch.all(chunks >= clearance) and torch.all(chunks <= 512.0 - clearance)
        assert torch.all(chunks[..., 0] >= 256.0 + clearance)


def test_a_waypoint_outside_the_workspace_violates_with_or_without_zones(
        tiny_policy: DiffusionPolicy) -> None:
    """Where zones that left no free space pushed a chunk, it is replanned once they go."""
    waypoints = torch.tensor([[[-5.0, 30.0], [30.0, 30.0], [256.0, 256.0]]],
                             dtype=torch.float64)
    for config in (ddim("none"), ddim("p", project=True)):
        planner = planner_for(tiny_policy, config)
        assert planner.violates(waypoints, None).tolist() == [[True, False, False]]
    projected = planner_for(tiny_policy, ddim("p", project=True))
    assert projected.violates(waypoints, CENTRE).tolist() == [[True, False, True]]
    mixed = MixedPlanner(tiny_policy, [ddim("none"), ddim("p", project=True)], PUSHT_ROBOT,
                         np.array([0]))
    assert mixed.violates(waypoints, None, np.array([0])).tolist() == [[True, False, False]]


GUARD_ONLY = """
import sys
import numpy as np
import constrained_diffusion_ros.nodes.policy_node_impl  # what the node imports
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.runtime.live_loop import warm_up
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
config = load_configurations(config_dir() / "configurations.yaml")["ddim10_r_g10_p_safe"]
planner = ConstrainedPlanner(load_policy(default_model_dir()), config, PUSHT_ROBOT)
warm_up(planner)
print(sorted(m for m in ("diffusers", "torch._dynamo") if m in sys.modules))
planner.prepare_sampling()
print(sorted(m for m in ("diffusers", "torch._dynamo") if m in sys.modules))
"""


def test_a_planner_that_only_guards_does_not_import_diffusers() -> None:
    """The live node guards setpoints while its planning process plans: it loads the policy and
    builds its planner without importing diffusers and torch's compiler (slow imports before its
    first setpoint); they come when the planner first needs its sampler."""
    result = subprocess.run([sys.executable, "-c", GUARD_ONLY], capture_output=True, text=True,
                            timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("\n")[:2] == ["[]", "['diffusers', 'torch._dynamo']"]
