"""Constraint hooks on hand-made samples, through the sampler, and through the planner."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
from constrained_diffusion_ros.sampling.constraints import (
    ConstrainedPlanner,
    ConstraintConfig,
    MixedPlanner,
    load_configurations,
)
from constrained_diffusion_ros.sampling.hooks import (
    FinalProjection,
    GradientPush,
    PathRepair,
    Resampling,
)
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler, DenoisingStep
from constrained_diffusion_ros.zones import ZoneSet, rectangle
from constrained_diffusion_ros.zones.episodes import EpisodeZones
from sim_bridge import AGENT_RADIUS

NORMALIZER = MinMaxNormalizer(torch.tensor([0.0, 0.0]), torch.tensor([512.0, 512.0]))
SQUARE = ZoneSet.from_polygons([rectangle(100, 100, 200, 200)])
L_SHAPE = ZoneSet.from_polygons([[[150, 150], [300, 150], [300, 200], [200, 200], [200, 330],
                                  [150, 330]]])
OVERLAPPING = ZoneSet.from_polygons([rectangle(60, 300, 260, 380), rectangle(200, 240, 300, 460)])
LEFT_BAND = ZoneSet.from_polygons([rectangle(0, 0, 256, 512)])
CENTRE = ZoneSet.from_polygons([rectangle(64, 64, 448, 448)])


def make_step(index: int, total: int = 5, seed: int = 7) -> DenoisingStep:
    return DenoisingStep(index=index, total=total, timestep=total - 1 - index,
                         generator=torch.Generator().manual_seed(seed), normalizer=NORMALIZER)


def observations(batch: int, seed: int = 1) -> torch.Tensor:
    return torch.rand(batch, 2, 20, generator=torch.Generator().manual_seed(seed)) * 512


def executed(policy: DiffusionPolicy, chunks: torch.Tensor) -> torch.Tensor:
    first = policy.config.first_executed
    return chunks[..., first: first + policy.config.n_action_steps, :]


# -- Resampling ----------------------------------------------------------------------------------

# Two episodes of four waypoints; those at x in (100, 200) and y in (100, 200) are inside SQUARE.
HAND_MADE = torch.tensor([[[150.0, 150.0], [20.0, 30.0], [199.0, 101.0], [400.0, 150.0]],
                          [[300.0, 300.0], [120.0, 180.0], [250.0, 90.0], [101.0, 199.0]]])
HAND_MADE_INSIDE = torch.tensor([[True, False, True, False], [False, True, False, True]])


def test_hand_made_sample_has_the_expected_inside_waypoints() -> None:
    assert torch.equal(SQUARE.contains(HAND_MADE), HAND_MADE_INSIDE)


def test_resampling_replaces_inside_waypoints_by_the_fresh_draw_at_the_first_step() -> None:
    step = make_step(0)
    assert step.progress == 0.0
    out = Resampling(SQUARE)(HAND_MADE.clone(), step)
    fresh = NORMALIZER.unnormalize(
        torch.randn(HAND_MADE.shape, generator=torch.Generator().manual_seed(7)))
    inside = HAND_MADE_INSIDE
    assert torch.equal(out[inside], fresh[inside])
    assert torch.equal(out[~inside], HAND_MADE[~inside])
    # The draw is centred on the action space: N(0, 1) normalised is 256 +- 256 px here.
    assert not torch.equal(out[inside], HAND_MADE[inside])


def test_resampling_leaves_the_sample_unchanged_at_the_last_step() -> None:
    step = make_step(4)
    assert step.progress == 1.0
    out = Resampling(SQUARE)(HAND_MADE.clone(), step)
    assert torch.equal(out, HAND_MADE)


def test_resampling_blends_linearly_in_between() -> None:
    out = Resampling(SQUARE)(HAND_MADE.clone(), make_step(1, total=5))  # progress 1/4: w = 3/4
    fresh = NORMALIZER.unnormalize(
        torch.randn(HAND_MADE.shape, generator=torch.Generator().manual_seed(7)))
    expected = 0.75 * fresh + 0.25 * HAND_MADE
    inside = HAND_MADE_INSIDE
    torch.testing.assert_close(out[inside], expected[inside])
    assert torch.equal(out[~inside], HAND_MADE[~inside])


def test_resampling_draws_nothing_when_no_waypoint_is_inside() -> None:
    outside = HAND_MADE[:, :2][~HAND_MADE_INSIDE[:, :2]].reshape(2, 1, 2)  # one per episode
    assert not SQUARE.contains(outside).any()
    step = make_step(0)
    out = Resampling(SQUARE)(outside, step)
    assert torch.equal(out, outside)
    # The generator was not advanced: its next draw is its first.
    assert torch.equal(torch.randn(3, generator=step.generator),
                       torch.randn(3, generator=torch.Generator().manual_seed(7)))


# -- Gradient push -------------------------------------------------------------------------------

def test_gradient_push_moves_inside_points_lambda_toward_the_nearest_edge() -> None:
    points = torch.tensor([[[105.0, 150.0], [150.0, 196.0], [50.0, 150.0], [205.0, 150.0]]])
    out = GradientPush(SQUARE, 3.0)(points.clone(), make_step(2))
    torch.testing.assert_close(out[0, 0] - points[0, 0], torch.tensor([-3.0, 0.0]))
    torch.testing.assert_close(out[0, 1] - points[0, 1], torch.tensor([0.0, 3.0]))
    assert torch.equal(out[0, 2:], points[0, 2:])  # outside: untouched


def test_gradient_push_in_a_concave_zone_heads_for_the_nearest_boundary() -> None:
    points = torch.tensor([[190.0, 190.0],  # nearest boundary: the notch vertex (200, 200)
                           [250.0, 180.0],  # horizontal arm, nearest its lower edge y = 200
                           [170.0, 300.0]])  # vertical arm, nearest its left edge x = 150
    assert L_SHAPE.contains(points).all()
    step_size = 4.0
    out = GradientPush(L_SHAPE, step_size)(points.clone(), make_step(0))
    diagonal = 1 / math.sqrt(2)
    expected = torch.tensor([[diagonal, diagonal], [0.0, 1.0], [-1.0, 0.0]]) * step_size
    torch.testing.assert_close(out - points, expected)
    # A push that heads for the centroid of the L (about (208, 213)) would go the other way.
    assert (out[0] - points[0] > 0).all()


# -- Final projection ----------------------------------------------------------------------------

def test_final_projection_acts_only_at_the_last_step() -> None:
    hook = FinalProjection(SQUARE, margin=2.0)
    for index in range(4):
        assert torch.equal(hook(HAND_MADE.clone(), make_step(index)), HAND_MADE)
    out = hook(HAND_MADE.clone(), make_step(4))
    assert not SQUARE.contains(out).any()
    assert torch.equal(out[~HAND_MADE_INSIDE], HAND_MADE[~HAND_MADE_INSIDE])


@pytest.mark.parametrize("margin", [0.0, 1.0, 5.0])
@pytest.mark.parametrize("area", [SQUARE, L_SHAPE, OVERLAPPING, LEFT_BAND, CENTRE],
                         ids=["square", "l_shape", "overlapping", "left_band", "centre"])
def test_final_projection_leaves_no_waypoint_inside_or_closer_than_the_margin(
        area: ZoneSet, margin: float) -> None:
    generator = torch.Generator().manual_seed(3)
    sample = torch.rand(64, 16, 2, generator=generator) * 512
    assert area.contains(sample).any()  # otherwise the test proves nothing
    out = FinalProjection(area, margin)(sample.clone(), make_step(9, total=10))
    assert not area.contains(out).any()
    assert area.signed_distance(out).min() >= margin - 1e-4
    far = area.signed_distance(sample) >= margin
    assert torch.equal(out[far], sample[far])


# -- Path repair ---------------------------------------------------------------------------------

def path_segments(start: torch.Tensor, path: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Segments start -> path[0] -> path[1] -> ... per episode."""
    return torch.cat([start[:, None], path[:, :-1]], dim=1), path


def test_path_repair_pulls_a_crossing_path_back_before_the_zone() -> None:
    zone = ZoneSet.from_polygons([rectangle(200, 200, 300, 300)])
    start = torch.tensor([[100.0, 250.0], [100.0, 100.0]])
    xs = torch.linspace(140.0, 460.0, 8)
    crossing = torch.stack([xs, torch.full_like(xs, 250.0)], dim=-1)  # straight through it
    clear = torch.stack([xs, torch.full_like(xs, 100.0)], dim=-1)  # parallel, above it
    head = torch.tensor([[[250.0, 250.0]], [[250.0, 250.0]]])  # not executed: left alone
    sample = torch.cat([head, torch.stack([crossing, clear])], dim=1)  # (2, 9, 2)
    first_starts, first_ends = path_segments(start, sample[:, 1:])
    assert zone.crosses(first_starts, first_ends)[0].any()
    assert not zone.crosses(first_starts, first_ends)[1].any()

    hook = PathRepair(zone, start, first_index=1, margin=1.0)
    assert torch.equal(hook(sample.clone(), make_step(0)), sample)  # only after the last update
    out = hook(sample.clone(), make_step(4))

    assert torch.equal(out[:, :1], sample[:, :1])
    assert torch.equal(out[1], sample[1])  # the clear path is unchanged
    starts, ends = path_segments(start, out[:, 1:])
    assert not zone.crosses(starts, ends).any()
    assert not zone.contains(out[0, 1:]).any()
    # Waypoints before the crossing stay; the rest stop just short of the entry at x = 200.
    before = xs < 200
    assert torch.equal(out[0, 1:][before], crossing[before])
    torch.testing.assert_close(out[0, 1:][~before][:, 0],
                               torch.full((int((~before).sum()),), 199.0), atol=1e-3, rtol=0)


# -- Through the sampler -------------------------------------------------------------------------

def test_final_projection_through_the_sampler_keeps_every_waypoint_out(
        tiny_policy: DiffusionPolicy) -> None:
    sampler = DenoisingSampler(tiny_policy, "ddim", 5)
    obs = observations(8)
    free = sampler.sample(obs, torch.Generator().manual_seed(0))
    assert CENTRE.contains(free).any()
    out = sampler.sample(obs, torch.Generator().manual_seed(0), hooks=[FinalProjection(CENTRE)])
    assert out.shape == (8, 16, 2)
    assert not CENTRE.contains(out).any()


def test_hooks_see_workspace_pixels_once_per_denoising_step(tiny_policy: DiffusionPolicy) -> None:
    seen: list[tuple[int, int, tuple[int, ...], torch.Tensor]] = []
    generator = torch.Generator().manual_seed(0)

    def record(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        assert step.generator is generator and step.normalizer is tiny_policy.action_normalizer
        seen.append((step.index, step.total, tuple(sample.shape), sample.clone()))
        return sample

    out = DenoisingSampler(tiny_policy, "ddim", 5).sample(observations(3), generator, [record])
    assert [s[0] for s in seen] == [0, 1, 2, 3, 4]
    assert {s[1] for s in seen} == {5}
    assert {s[2] for s in seen} == {(3, 16, 2)}
    # The last sample the hook saw is the output, in pixels (normalised values would be ~256x off).
    torch.testing.assert_close(seen[-1][3], out, atol=1e-3, rtol=0)
    assert out.max() > 100


def test_a_hook_changes_what_the_next_denoising_step_starts_from(
        tiny_policy: DiffusionPolicy) -> None:
    """A hook's output is fed back: a hook that pins every waypoint pins the result."""
    def pin(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        return torch.full_like(sample, 300.0) if step.index == step.total - 1 else sample

    out = DenoisingSampler(tiny_policy, "ddim", 5).sample(observations(2),
                                                          torch.Generator().manual_seed(0), [pin])
    torch.testing.assert_close(out, torch.full_like(out, 300.0))


# -- The planner ---------------------------------------------------------------------------------

def ddim(name: str, **fields: object) -> ConstraintConfig:
    return ConstraintConfig(name, sampler="ddim", denoising_steps=5, **fields)


def test_planner_with_projection_plans_no_waypoint_inside(tiny_policy: DiffusionPolicy) -> None:
    obs = observations(6)
    free = ConstrainedPlanner(tiny_policy, ddim("none")).plan(
        obs, CENTRE, torch.Generator().manual_seed(0))
    assert CENTRE.contains(free).any()
    planned = ConstrainedPlanner(tiny_policy, ddim("p", project=True)).plan(
        obs, CENTRE, torch.Generator().manual_seed(0))
    assert not CENTRE.contains(planned).any()
    assert CENTRE.signed_distance(planned).min() >= 1.0 - 1e-4  # the default margin


def test_planner_with_inflation_keeps_the_pusher_radius_clear(tiny_policy: DiffusionPolicy) -> None:
    obs = observations(6)
    plain = ConstrainedPlanner(tiny_policy, ddim("p", project=True)).plan(
        obs, CENTRE, torch.Generator().manual_seed(0))
    inflated = ConstrainedPlanner(tiny_policy, ddim("pi", project=True, inflate=True)).plan(
        obs, CENTRE, torch.Generator().manual_seed(0))
    assert CENTRE.signed_distance(plain).min() < AGENT_RADIUS  # inflation is what makes it hold
    assert CENTRE.signed_distance(inflated).min() >= AGENT_RADIUS


def test_a_mixed_batch_constrains_each_configuration_on_its_own_rows(
        tiny_policy: DiffusionPolicy) -> None:
    mixed = MixedPlanner(tiny_policy, [ddim("none"), ddim("p", project=True)])
    owner = np.array([0, 1, 0, 1, 0, 1])
    areas = [None, EpisodeZones([CENTRE], [0, 0, 0])]
    plan = mixed.plan(observations(6), areas, owner, torch.Generator().manual_seed(0))
    plain = ConstrainedPlanner(tiny_policy, ddim("none")).plan(
        observations(6), None, torch.Generator().manual_seed(0))
    inside = CENTRE.contains(executed(tiny_policy, plan)).any(dim=1).numpy()
    assert not inside[owner == 1].any()  # projected
    free = torch.from_numpy(owner == 0)  # left alone, up to the hooks' pixel round trips
    torch.testing.assert_close(plan[free], plain[free], atol=1e-3, rtol=0.0)
    assert inside[owner == 0].any()


def test_a_mixed_batch_needs_one_sampler(tiny_policy: DiffusionPolicy) -> None:
    with pytest.raises(ValueError, match="one sampler"):
        MixedPlanner(tiny_policy, [ddim("a"), ConstraintConfig("b", project=True)])
    with pytest.raises(ValueError, match="one sampler"):
        MixedPlanner(tiny_policy, [ddim("a"), ddim("b", from_scratch=4)])


def test_from_scratch_keeps_the_candidate_with_fewest_violations(
        tiny_policy: DiffusionPolicy) -> None:
    n, obs = 8, observations(4)
    planner = ConstrainedPlanner(tiny_policy, ddim("scratch", from_scratch=n))
    repeated = obs[:, None].expand(4, n, 2, 20).reshape(4 * n, 2, 20)
    candidates = planner.sampler.sample(repeated, torch.Generator().manual_seed(0))
    candidates = candidates.reshape(4, n, 16, 2)

    most = ZoneSet.from_polygons([rectangle(0, 0, 400, 512)])
    counts = most.contains(executed(tiny_policy, candidates)).sum(dim=-1)  # (4, n)
    assert (counts.amin(dim=1) < counts.amax(dim=1)).all()  # the choice matters in every row
    chosen = planner.plan(obs, most, torch.Generator().manual_seed(0))
    expected = counts.argmin(dim=1)  # argmin returns the first of equal minima
    assert torch.equal(chosen, candidates[torch.arange(4), expected])
    assert torch.equal(most.contains(executed(tiny_policy, chosen)).sum(dim=-1),
                       counts.amin(dim=1))

    # Nothing violates a tiny zone far from every candidate: the first candidate fits.
    tiny = ZoneSet.from_polygons([rectangle(300, 300, 301, 301)])
    assert not tiny.contains(candidates).any()
    chosen = planner.plan(obs, tiny, torch.Generator().manual_seed(0))
    assert torch.equal(chosen, candidates[:, 0])


def test_each_episode_is_constrained_by_its_own_zone(tiny_policy: DiffusionPolicy) -> None:
    # Halves of the plane (beyond the walls too, so the only way out is across x = 256).
    left = ZoneSet.from_polygons([rectangle(-2000, -2000, 256, 2000)])
    right = ZoneSet.from_polygons([rectangle(256, -2000, 2000, 2000)])
    areas = EpisodeZones([left, right], [0, 1])
    planner = ConstrainedPlanner(tiny_policy, ddim("p", project=True, margin=2.0))
    obs = observations(2)
    free = planner.plan(obs, None, torch.Generator().manual_seed(0))
    assert (free[0, :, 0] < 256).any() and (free[1, :, 0] > 256).any()
    planned = planner.plan(obs, areas, torch.Generator().manual_seed(0))
    assert (planned[0, :, 0] >= 258 - 1e-3).all()  # row 0: out of the left band only
    assert (planned[1, :, 0] <= 254 + 1e-3).all()  # row 1: out of the right band only


def test_planner_without_constraints_ignores_the_zone(tiny_policy: DiffusionPolicy) -> None:
    planner = ConstrainedPlanner(tiny_policy, ddim("none"))
    obs = observations(3)
    with_zone = planner.plan(obs, CENTRE, torch.Generator().manual_seed(0))
    without = planner.plan(obs, None, torch.Generator().manual_seed(0))
    assert torch.equal(with_zone, without)


# -- Configurations ------------------------------------------------------------------------------

def test_load_configurations_reads_every_entry_of_the_shipped_file() -> None:
    path = config_dir() / "configurations.yaml"
    configs = load_configurations(path)
    assert list(configs) == list(yaml.safe_load(path.read_text()))
    assert all(name == config.name for name, config in configs.items())
    assert sum(c.paper for c in configs.values()) == 6
    paper_table = yaml.safe_load((config_dir() / "paper_table1.yaml").read_text())
    for row in paper_table.values():
        assert set(row) == {name for name, c in configs.items() if c.paper}
    assert not configs["none"].constrains
    r_g10 = configs["r_g10"]
    assert r_g10.resample and r_g10.push == 10 and not r_g10.project
    assert configs["ddim10_scratch_8"].from_scratch == 8
    assert configs["ddim10_scratch_8"].sampler == "ddim"


def test_an_unknown_configuration_key_is_refused_by_name(tmp_path: Path) -> None:
    path = tmp_path / "configurations.yaml"
    path.write_text("ok: {resample: true}\nbad: {resample: true, lambda: 3}\n")
    with pytest.raises(ValueError, match="lambda"):
        load_configurations(path)


@pytest.mark.parametrize("entry", [{"push": -1.0}, {"from_scratch": 4, "resample": True},
                                   {"sampler": "euler"}, {"scenarios": "some"}])
def test_inconsistent_configurations_are_refused(entry: dict) -> None:
    with pytest.raises(ValueError, match="'bad'"):
        ConstraintConfig("bad", **entry)


def test_step_progress_runs_evenly_from_0_to_1() -> None:
    progress = [make_step(i, total=5).progress for i in range(5)]
    np.testing.assert_allclose(progress, [0.0, 0.25, 0.5, 0.75, 1.0])
    assert make_step(0, total=1).progress == 0.0


def test_planner_projection_never_leaves_the_workspace_for_a_zone_on_the_wall(
    tiny_policy: DiffusionPolicy,
) -> None:
    """A band against the left wall: the way out is its right edge, never through the wall."""
    band = load_scenarios()["left_0.5"].zones_at(0)
    for inflate in (False, True):
        planner = ConstrainedPlanner(tiny_policy, ddim("p", project=True, inflate=inflate))
        obs = observations(16)
        obs[..., 0::2] = obs[..., 0::2] * 0.4  # observations on the left: plans go there
        chunks = planner.plan(obs, band, torch.Generator().manual_seed(0))
        clearance = 15.0 if inflate else 0.0
        assert not band.contains(chunks).any()
        assert torch.all(chunks >= clearance) and torch.all(chunks <= 512.0 - clearance)
        assert torch.all(chunks[..., 0] >= 256.0 + clearance)
