"""A policy that sees the zones (issue 43): the raster it is given, the zones it is trained
with, and a network made zone-aware that starts as exactly the policy it was."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.policy_config import PolicyConfig
from constrained_diffusion_ros.policy.weights import load_policy, save_policy
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler
from constrained_diffusion_ros.training import train
from constrained_diffusion_ros.training.dataset import WindowSampler, load_demonstrations
from constrained_diffusion_ros.training.zone_shapes import (
    FRAME_PX,
    KINDS,
    ShapeBank,
    ZoneSampler,
    policy_routes,
    random_shape,
)
from constrained_diffusion_ros.zones import EpisodeZones, ZoneSet
from constrained_diffusion_ros.zones.raster import fine_cell_px, zone_raster

WORKSPACE = (0.0, 0.0, 512.0, 512.0)
RADIUS = 15.0


def test_the_raster_is_the_share_of_each_cell_the_zones_cover() -> None:
    """A 32 px square on 16 px cells covers four cells whole; half a cell is half covered;
    each episode of a batch-aware area gets its own raster."""
    square = ZoneSet([shapely.box(64.0, 96.0, 96.0, 128.0)])
    raster = zone_raster(square, 2, 32, WORKSPACE)
    assert raster.shape == (2, 32, 32)
    assert torch.equal(raster[0], raster[1])
    assert torch.nonzero(raster[0] == 1.0).tolist() == [[6, 4], [6, 5], [7, 4], [7, 5]]
    assert float(raster[0].sum()) == 4.0
    half = zone_raster(ZoneSet([shapely.box(0.0, 0.0, 8.0, 16.0)]), 1, 32, WORKSPACE)
    assert float(half[0, 0, 0]) == 0.5 and float(half.sum()) == 0.5
    both = EpisodeZones([square, ZoneSet([])], [1, 0, 1])
    per_row = zone_raster(both, 3, 32, WORKSPACE)
    assert float(per_row[0].sum()) == 0.0 and float(per_row[1].sum()) == 4.0
    assert zone_raster(both, 3, 32, WORKSPACE) is per_row  # kept with the area

    class Unhashable(ZoneSet):  # a plug-in area that defines equality: no weak key
        __eq__ = object.__eq__
        __hash__ = None

    plug_in = Unhashable([shapely.box(64.0, 96.0, 96.0, 128.0)])
    assert torch.equal(zone_raster(plug_in, 2, 32, WORKSPACE), raster)


@pytest.fixture(scope="module")
def bank() -> ShapeBank:
    return ShapeBank.build(len(KINDS) * 20, 0, fine_cell_px(WORKSPACE, 32), RADIUS)


@pytest.fixture(scope="module")
def paths(dataset_path: Path) -> torch.Tensor:
    demos = load_demonstrations(dataset_path)
    windows = WindowSampler(demos, 16, 2, 8)
    obs, actions = windows.batch(torch.randperm(len(windows),
                                                generator=torch.Generator().manual_seed(0))[:64])
    return torch.cat([obs[..., -2:], actions], dim=1)


def test_every_kind_of_shape_is_drawn_valid_and_within_its_frame() -> None:
    rng = np.random.default_rng(0)
    for kind in KINDS:
        for _ in range(10):
            shape = random_shape(kind, rng)
            assert shape.is_valid and shape.area > 0, kind
            grown = shape.buffer(RADIUS + 3)
            assert max(abs(v) for v in grown.bounds) < FRAME_PX / 2, kind


@pytest.mark.parametrize("with_routes", [False, True])
def test_training_zones_keep_clear_of_each_demonstration_path(bank, paths,
                                                              with_routes: bool) -> None:
    """Every zone placed for a window keeps the pusher's disc clear of the window's path (the
    exact shapes, not the masks), whether or not it was anchored on a route of the policy's
    (here: the path moved 60 px aside); most windows get zones, many near the path."""
    sampler = ZoneSampler(bank, 32, WORKSPACE, 0.0, torch.Generator().manual_seed(1))
    routes = paths[:, 2:] + torch.tensor([60.0, 0.0]) if with_routes else None
    ids, corners, placed = sampler.place(paths, paths[:, 1], routes)
    assert placed.any(1).float().mean() > 0.8
    cell = fine_cell_px(WORKSPACE, 32)
    nearest = []
    for b, s in torch.nonzero(placed).tolist():
        anchor = corners[b, s].numpy() * cell + FRAME_PX / 2
        shape = shapely.affinity.translate(bank.shapes[ids[b, s]], *anchor)
        gaps = shapely.distance(shape, shapely.points(paths[b].numpy()))
        assert gaps.min() >= RADIUS, (b, s, gaps.min())
        nearest.append(gaps.min())
    assert np.mean(np.array(nearest) < 60) > 0.3  # many near enough to matter
    raster = sampler.paint(ids, corners, placed)
    assert raster.shape == (64, 32, 32) and float(raster.max()) <= 1.0
    painted = raster.sum((1, 2)) > 0
    assert not (painted & ~placed.any(1)).any()  # nothing painted where none was placed
    assert painted.float().mean() > 0.8  # (a zone anchored past the edge may paint nothing)


def test_dropped_windows_get_no_zones(bank, paths) -> None:
    sampler = ZoneSampler(bank, 32, WORKSPACE, 1.0, torch.Generator().manual_seed(1))
    assert float(sampler.rasters(paths, paths[:, 1]).abs().sum()) == 0.0


def zone_aware(policy: DiffusionPolicy) -> PolicyConfig:
    data = {**policy.config.to_dict(), "zone_grid": 32}
    return PolicyConfig.from_dict(json.loads(json.dumps(data)))


def test_a_zone_aware_config_checks_its_fields_and_survives_json(tiny_policy) -> None:
    config = zone_aware(tiny_policy)
    assert config.sees_zones and config.global_cond_dim == 40 + 64
    assert config.zone_workspace == WORKSPACE
    with pytest.raises(ValueError, match="zone_grid must be 0 or one of"):
        PolicyConfig.from_dict({**config.to_dict(), "zone_grid": 30})
    with pytest.raises(ValueError, match="zone_workspace must be"):
        PolicyConfig.from_dict({**config.to_dict(), "zone_workspace": [0, 0, 0, 512]})


def test_a_policy_made_zone_aware_starts_as_it_was_and_plans_with_the_zones(
        tiny_policy, tmp_path: Path, dataset_path: Path) -> None:
    """`--init-from` with `--zones`: before any training step the zone-aware network predicts
    what the policy did, whatever the zones; a zone-aware policy saved and loaded plans with
    the zones in its condition (a sampler given zones differs from one given none)."""
    save_policy(tiny_policy, tmp_path / "base")
    args = train.build_parser().parse_args(["--dataset", str(dataset_path), "--output",
                                            str(tmp_path / "out"), "--zones", "--init-from",
                                            str(tmp_path / "base")])
    policy = train.starting_policy(args, None).eval()
    assert policy.config.sees_zones
    generator = torch.Generator().manual_seed(0)
    obs = torch.rand(3, 2, 20, generator=generator) * 512
    sample = torch.randn(3, 16, 2, generator=generator)
    raster = torch.rand(3, 32, 32, generator=generator)
    with torch.no_grad():
        expected = tiny_policy.unet(sample, torch.tensor(10), tiny_policy.condition(obs))
        got = policy.unet(sample, torch.tensor(10), policy.condition(obs, raster))
    assert torch.allclose(got, expected, atol=1e-6)

    with torch.no_grad():  # trained a little: the zone part now matters
        for block in policy.unet.blocks():
            block.film[-1].weight[:, -64:].normal_(0, 0.1, generator=generator)
    save_policy(policy, tmp_path / "aware")
    loaded = load_policy(tmp_path / "aware")
    sampler = DenoisingSampler(loaded, "ddim", 3)
    zones = ZoneSet([shapely.box(200.0, 200.0, 300.0, 300.0)])
    plans = [sampler.sample(obs, torch.Generator().manual_seed(5), (), area)
             for area in (None, zones, zones)]
    assert torch.equal(plans[1], plans[2]) and not torch.allclose(plans[0], plans[1])
    blind = sampler.sample(obs, torch.Generator().manual_seed(5), (), zones,
                           torch.tensor([False, True, False]))
    assert torch.equal(blind[[0, 2]], plans[0][[0, 2]]) and torch.equal(blind[1], plans[1][1])


def test_zone_guidance_weighs_what_the_zones_change(tiny_policy, tmp_path: Path,
                                                    dataset_path: Path) -> None:
    """Classifier-free guidance over the zones: weight 0 plans as without them, 1 as with them
    alone, 2 further along the same difference (DDIM with one step: the chunk is linear in the
    noise predicted)."""
    save_policy(tiny_policy, tmp_path / "base")
    args = train.build_parser().parse_args(["--dataset", str(dataset_path), "--output",
                                            str(tmp_path / "out"), "--zones", "--init-from",
                                            str(tmp_path / "base")])
    aware = train.starting_policy(args, None)
    policy = DiffusionPolicy(dataclasses.replace(aware.config, clip_sample=False)).eval()
    policy.unet.load_state_dict(aware.unet.state_dict())  # no clipping: linear in the noise
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for block in policy.unet.blocks():
            block.film[-1].weight[:, -64:].normal_(0, 0.1, generator=generator)
    obs = torch.rand(2, 2, 20, generator=generator) * 512
    zones = ZoneSet([shapely.box(150.0, 150.0, 350.0, 350.0)])

    def plan(weight: float, area=zones) -> torch.Tensor:
        sampler = DenoisingSampler(policy, "ddim", 1, "trailing", zone_guidance=weight)
        return sampler.sample(obs, torch.Generator().manual_seed(7), (), area)

    blind, seeing = plan(1.0, None), plan(1.0)
    assert torch.allclose(plan(0.0), blind, atol=1e-4)
    assert not torch.allclose(seeing, blind, atol=1e-2)
    assert torch.allclose(plan(2.0), blind + 2 * (seeing - blind), atol=1e-3)


def test_the_routes_zones_are_anchored_on_are_the_policy_plans_executed_waypoints(
        tiny_policy, dataset_path: Path) -> None:
    demos = load_demonstrations(dataset_path)
    windows = WindowSampler(demos, 16, 2, 8)

    class FirstWindows:
        def __len__(self) -> int:
            return 5

        def batch(self, ids: torch.Tensor):
            return windows.batch(ids)

    routes = policy_routes(tiny_policy, FirstWindows(), 3, 0, batch=4, quiet=True)
    assert routes.shape == (5, 3 * 8, 2) and bool(torch.isfinite(routes).all())
    again = policy_routes(tiny_policy, FirstWindows(), 3, 0, batch=7, quiet=True)
    assert torch.allclose(routes, again, atol=1e-4)  # seeded, whatever the batch
