"""A user's own restricted area: a check that is not a ZoneSet, implementing only its signed
distance, works with every query, every derived area and every shipped configuration."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from torch import Tensor

from constrained_diffusion_ros.evaluation.rollout import rollout
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import EpisodeZones, RestrictedArea, ZoneSet

RADIUS = PUSHT_ROBOT.pusher_radius


class Disc(RestrictedArea):
    """What a user writes: a disc, by its signed distance alone."""

    def __init__(self, centre: tuple[float, float], radius: float) -> None:
        self.centre, self.radius = torch.tensor(centre, dtype=torch.float64), radius

    def signed_distance(self, points: Tensor) -> Tensor:
        points = torch.as_tensor(points)
        return ((points - self.centre.to(points)).norm(dim=-1) - self.radius).to(points.dtype)


# Where the tiny random policy's setpoints pile up (the top band, see test/ros/test_trial.py)
# meets where its first chunks go: unconstrained, it commands setpoints inside this disc.
DISC = Disc((256.0, 60.0), 90.0)
SEEDS = [100001, 100006]  # scenes whose pusher starts well clear of the disc (74 and 91 px)


class Fixed:
    """A zone source that never changes."""

    def __init__(self, area: RestrictedArea) -> None:
        self.area = area

    def area_at(self, step: int) -> RestrictedArea:
        return self.area

    def version_at(self, step: int) -> int:
        return 0


def distance(points: np.ndarray | Tensor) -> np.ndarray:
    return DISC.signed_distance(torch.as_tensor(points, dtype=torch.float64)).numpy()


def test_the_defaults_answer_every_query_from_the_distance_alone() -> None:
    points = torch.tensor([[256.0, 60.0 + 50.0], [256.0 + 150.0, 60.0], [10.0, 400.0]])
    assert DISC.contains(points).tolist() == [True, False, False]
    directions = DISC.outward_direction(points)
    torch.testing.assert_close(directions[:2], torch.tensor([[0.0, 1.0], [1.0, 0.0]]),
                               atol=1e-6, rtol=0)
    out = DISC.project_out(points, margin=2.0)
    torch.testing.assert_close(out[0], torch.tensor([256.0, 60.0 + 92.0]), atol=1e-3, rtol=0)
    torch.testing.assert_close(out[1:], points[1:])  # already clear: kept
    # A segment through the centre enters where it meets the circle.
    starts, ends = torch.tensor([[256.0 - 200.0, 60.0]]), torch.tensor([[256.0 + 200.0, 60.0]])
    fraction = DISC.segment_clear_fraction(starts, ends)
    assert fraction.item() == pytest.approx(110.0 / 400.0, abs=1e-5)
    assert DISC.crosses(starts, ends).item()
    assert not DISC.crosses(torch.tensor([[0.0, 300.0]]), torch.tensor([[500.0, 300.0]])).item()


def test_derived_areas_are_closed_and_cached() -> None:
    grown = DISC.inflate(RADIUS)
    assert grown is DISC.inflate(RADIUS)  # cached on the area
    assert grown.signed_distance(torch.tensor([[256.0, 60.0 + 100.0]])).item() == \
        pytest.approx(10.0 - RADIUS, abs=1e-4)
    bounded = DISC.bounded(PUSHT_ROBOT.workspace)
    outside_workspace = torch.tensor([[-5.0, 300.0], [300.0, 520.0]])
    assert bounded.contains(outside_workspace).all() and not DISC.contains(outside_workspace).any()
    # Inside the disc by the top wall, the ways out of the two face each other: the projection
    # still finds the nearest clear point, sideways, never through the wall.
    near_wall = torch.tensor([[256.0, 5.0]], dtype=torch.float64)
    body = bounded.inflate(RADIUS)
    projected = body.project_out(near_wall, 1.0)
    assert body.signed_distance(projected).item() >= 1.0 - 1e-6
    assert torch.all((projected >= 0) & (projected <= 512))
    assert (projected - near_wall).norm().item() < 110  # not the long way round, 161 px down
    assert DISC.select_rows(torch.tensor([1, 0])) is DISC  # the same for every episode
    rows = EpisodeZones([DISC, ZoneSet.empty()], [1, 0, 1]).select_rows(torch.tensor([1]))
    assert rows.contains(torch.tensor([[[256.0, 60.0]]])).tolist() == [[True]]


CONFIGURATIONS = load_configurations(config_dir() / "configurations.yaml")


@pytest.mark.parametrize("name", list(CONFIGURATIONS))
def test_every_shipped_configuration_runs_with_a_users_area(
        name: str, make_tiny_policy, tiny_policy: DiffusionPolicy) -> None:
    config = CONFIGURATIONS[name]
    planner = ConstrainedPlanner(tiny_policy, config, PUSHT_ROBOT)
    log = rollout(planner, SEEDS, n_steps=16, zones=Fixed(DISC),
                  generator=torch.Generator().manual_seed(0))
    commanded, body = distance(log.commanded), distance(log.pusher[:, 1:])
    assert np.isfinite(commanded).all() and log.commanded.shape == (2, 16, 2)
    if not config.constrains:  # what the others are measured against: it does enter the disc
        assert (commanded < 0).any()
    if config.project and not config.shield:  # no waypoint inside (the pusher radius, inflated)
        assert commanded.min() >= (RADIUS if config.inflate else 0.0) + config.margin - 1e-3
    if config.shield:  # the last word: setpoints out, and the pusher's body stays out too
        assert commanded.min() >= 0.0 and body.min() >= RADIUS - 1e-6


def test_the_shield_acts_on_a_users_area(tiny_policy: DiffusionPolicy) -> None:
    """Heading straight through the disc: the shield keeps the body out, with the safe
    setpoint nearest the wanted one (nearer it than the pusher is)."""
    config = CONFIGURATIONS["r_g10_p_safe"]
    planner = ConstrainedPlanner(tiny_policy, config, PUSHT_ROBOT)
    observation = np.zeros((1, 20))
    observation[0, 18:] = 256.0, 60.0 + 90.0 + RADIUS + 30.0  # 30 px below the disc's body
    setpoint = np.array([[256.0, 60.0]])  # its centre
    out = planner.guard(DISC, observation, setpoint, step=0)
    assert not np.array_equal(out, setpoint) and planner.shield.corrected == 1
    assert distance(out)[0] >= RADIUS  # held back where the body stays clear
    pusher = observation[0, 18:]
    assert np.linalg.norm(out[0] - setpoint[0]) < np.linalg.norm(pusher - setpoint[0])


def test_an_area_pickles_without_its_caches_and_answers_the_same() -> None:
    """What the planning process receives: the zones, not what was derived from them."""
    zones = ZoneSet.from_polygons([[[100, 100], [200, 100], [200, 200], [100, 200]]])
    bounded = zones.inflate(15.0).bounded((0.0, 0.0, 512.0, 512.0))
    points = torch.tensor([[150.0, 150.0], [90.0, 150.0], [300.0, 300.0], [-5.0, 10.0]])
    expected = bounded.signed_distance(points)  # fills the caches
    bare = len(pickle.dumps(ZoneSet.from_polygons([[[100, 100], [200, 100], [200, 200],
                                                    [100, 200]]])))
    assert len(pickle.dumps(zones)) == bare
    copy = pickle.loads(pickle.dumps(bounded))
    torch.testing.assert_close(copy.signed_distance(points), expected)
