"""How scenario zones move (waypoints, speeds, pauses, homing), and the contact metrics a
moving zone is judged by."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from constrained_diffusion_ros.evaluation.runner import ScenarioZones, unavoidable
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.evaluation.zone_paths import ZoneMover, ZonePath
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.geometry import ZoneSet, rectangle
from constrained_diffusion_ros.zones.motion import FLOOR, HEADROOM, MovingZones

STEP_S = 1.0 / PUSHT_ROBOT.control_hz


def test_a_path_goes_at_its_speed_and_pauses_at_its_waypoints() -> None:
    path = ZonePath(np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 50.0]]), 50.0, (1.0, 0.5, 0.0))
    assert path.path_s == pytest.approx(1.0 + 2.0 + 0.5 + 1.0)
    for seconds, expected in ((0.5, (0, 0)), (2.0, (50, 0)), (3.2, (100, 0)),
                              (4.0, (100, 25)), (9.0, (100, 50))):
        np.testing.assert_allclose(path.offset_at(seconds), expected, atol=1e-9)


def test_the_hands_come_at_each_of_their_speeds() -> None:
    scenarios = load_scenarios()
    for speed in (50, 100, 200, 300):
        for kind in ("hand_crossing", "hand_reaching", "hand_homing"):
            hand = scenarios[f"{kind}@{speed}"]
            assert hand.moving and hand.motion.speed == speed and str(speed) in hand.label
        crossing = scenarios[f"hand_crossing@{speed}"]
        moved = crossing.offset_at(20) - crossing.offset_at(10)  # 1 s after its 1 s wait
        assert np.linalg.norm(moved) == pytest.approx(speed, rel=1e-6)
    assert "hand_crossing" not in scenarios  # only its variants
    assert scenarios["hand_homing@100"].homes and not scenarios["hand_reaching@100"].homes


@pytest.mark.parametrize(("motion", "fault"), [
    ({"path": [[0, 0], [10, 0]], "speed": -5}, "speed"),
    ({"path": [[0, 0], [10, 0]], "speed": 5, "pauses": [1]}, "pauses"),
    ({"path": [[0, 0]], "speed": 5, "home_s": -1}, "home_s"),
    ({"path": [[0, 0]], "speed": 5, "sideways": 1}, "mapping of"),
])
def test_a_malformed_motion_is_refused_naming_the_scenario(tmp_path, motion: dict,
                                                           fault: str) -> None:
    import yaml
    path = tmp_path / "scenarios.yaml"
    path.write_text(yaml.safe_dump({"hand": {"zones": [{"square": {"center": [0, 0],
                                                                   "side": 10}}],
                                         "motion": motion}}))
    with pytest.raises(ValueError, match=f"scenario 'hand' motion: .*{fault}"):
        load_scenarios(path)


def test_a_homing_zone_heads_for_each_pusher_then_goes_back() -> None:
    path = ZonePath(np.array([[0.0, 0.0]]), 100.0, (1.0,), home_s=1.0)
    mover = ZoneMover(path, np.array([0.0, 0.0]), 2)
    pushers = np.array([[300.0, 0.0], [0.0, -300.0]])
    for step in range(11):  # the 1 s wait
        np.testing.assert_array_equal(mover.at(step, pushers), 0.0)
    for step in range(11, 21):  # 1 s homing: 10 px a step, each toward its own pusher
        offsets = mover.at(step, pushers)
    np.testing.assert_allclose(offsets, [[100.0, 0.0], [0.0, -100.0]], atol=1e-9)
    for step in range(21, 40):  # back to the last waypoint
        offsets = mover.at(step, pushers)
    np.testing.assert_allclose(offsets, 0.0, atol=1e-9)


def test_the_evaluation_takes_a_hand_as_the_node_takes_live_zones() -> None:
    """Still until it moves, then its own bound (HEADROOM x its speed, at least FLOOR), as
    `MovingZones` the shield checks against; each homing row's zone where its pusher drew it."""
    hand = load_scenarios()["hand_homing@200"]
    zones = ScenarioZones([hand], np.zeros(2, dtype=int))
    pushers = np.array([[100.0, 100.0], [400.0, 400.0]])
    for step in range(15):
        zones.follow(step, pushers)
        area = zones.area_at(step)
    assert isinstance(area, MovingZones)
    expected = min(300.0, max(FLOOR, HEADROOM * 200.0))
    np.testing.assert_allclose(area.speed.numpy(), [expected, expected])
    first, second = zones.offsets[14] + hand.centroid
    assert np.linalg.norm(first - pushers[0]) < np.linalg.norm(second - pushers[0])


def test_zones_shown_late_are_where_they_were_then_and_aged_by_the_lag() -> None:
    """`late` (the stress test of a tracker and a node behind): the zone, its speed and its
    velocity as they were `late` steps before, with that age; the same hand shown on time is
    where it is, at age 0."""
    hand = load_scenarios()["hand_crossing@200"]
    on_time = ScenarioZones([hand], np.zeros(1, dtype=int))
    late = ScenarioZones([hand], np.zeros(1, dtype=int), late=3)
    pushers = np.array([[256.0, 256.0]])
    for step in range(20):  # the 1 s wait, then 10 steps across at 20 px a step
        for zones in (on_time, late):
            zones.follow(step, pushers)
            zones.area_at(step)
    shown, truth = late.area_at(19), on_time.area_at(19)
    assert float(shown.age_s) == pytest.approx(0.3) and float(truth.age_s) == 0.0
    then = torch.from_numpy(np.asarray(hand.centroid + on_time.offsets[16]))
    assert shown.moving.signed_distance(then).item() < 0  # where it was 3 steps before,
    assert truth.moving.signed_distance(then).item() > 0  # not where it is
    np.testing.assert_allclose(shown.drift[0][1].numpy(),
                               (on_time.offsets[16] - on_time.offsets[15]) * 10.0)
    assert shown.speed.item() == pytest.approx(truth.speed.item())  # seen moving, both
    assert truth.speed.item() > 0


def test_a_contact_is_unavoidable_only_where_the_zone_covers_all_the_pusher_can_reach() -> None:
    reach = PUSHT_ROBOT.reach(STEP_S)
    corner = np.array([[20.0, 20.0]])
    everything = ZoneSet.from_polygons([rectangle(-10, -10, reach + 60, reach + 60)])
    small = ZoneSet.from_polygons([rectangle(0, 0, 40, 40)])
    assert unavoidable(corner, everything)[0]
    assert not unavoidable(corner, small)[0]
    assert unavoidable(corner, everything.select_rows(torch.tensor([0]))).shape == (1,)
