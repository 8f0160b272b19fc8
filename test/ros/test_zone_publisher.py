"""zone_publisher over real DDS: latched scenario zones, a moving zone on sim time, refusals."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PolygonInstanceStamped
from ros_helpers import random_domain_id, stamp_ns, step_ns

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from msg_schemas import FRAME_ID, TOPICS

REPO = Path(__file__).resolve().parents[2]


def test_zone_publisher_latched_scenario_and_moving_zone(ros, sim, processes):
    scenarios = load_scenarios()
    processes.start("zones_static", "zone_publisher",
                    scenario="two_zones", first_id=5, rate_hz=0.0)
    processes.start("zones_moving", "zone_publisher",
                    scenario="moving_hand", first_id=20, rate_hz=0.0, follow_sim_time=True)
    processes.start("zones_homing", "zone_publisher",
                    scenario="hand_homing@200", first_id=30, rate_hz=0.0, follow_sim_time=True)
    bad, bad_log = processes.start("zones_bad", "zone_publisher",
                                   polygon="0,0;10,10;20,20")
    topic = TOPICS["zones"].name
    # Both publishers exist (and have published: they do so on creation) before we subscribe.
    assert ros.spin_until(lambda: ros.node.count_publishers(topic) >= 3)
    zones = ros.inbox("zones", PolygonInstanceStamped)
    assert ros.spin_until(lambda: {5, 6} <= {m.polygon.id for m in zones})
    static = {m.polygon.id: m for m in zones if m.polygon.id in (5, 6)}
    for zone_id, polygon in zip((5, 6), scenarios["two_zones"].polygons):
        assert static[zone_id].header.frame_id == FRAME_ID
        points = [(p.x, p.y) for p in static[zone_id].polygon.polygon.points]
        assert np.allclose(points, polygon)

    # The moving zone follows the sim's step: step it and read the zone for that step.
    moving = scenarios["moving_hand"]
    latest = stamp_ns(sim.latest().header.stamp)
    assert ros.spin_until(lambda: any(
        m.polygon.id == 20 and stamp_ns(m.header.stamp) == latest for m in zones)), \
        "moving zone never followed the sim"
    before = sim.stamps()
    for _ in range(3):
        sim.send(256.0, 256.0)
        sim.wait_new_stamps(sim.stamps(), 1)
    last = sim.stamps()[len(before):][-1]
    assert ros.spin_until(lambda: any(
        m.polygon.id == 20 and stamp_ns(m.header.stamp) == last for m in zones))
    message = next(m for m in zones if m.polygon.id == 20 and stamp_ns(m.header.stamp) == last)
    points = [(p.x, p.y) for p in message.polygon.polygon.points]
    assert np.allclose(points, moving.polygons_at(last // step_ns(1))[0], atol=1e-3)
    assert not np.allclose(points, moving.polygons_at(0)[0], atol=1e-3)

    # The homing hand waits 1 s where it is drawn, then heads for the pusher at 200 px/s.
    homing = scenarios["hand_homing@200"]
    for _ in range(12):
        sim.send(256.0, 256.0)
        sim.wait_new_stamps(sim.stamps(), 1)
    last, point = sim.stamps()[-1], sim.latest().point
    pusher = np.array([point.x, point.y])
    assert ros.spin_until(lambda: any(
        m.polygon.id == 30 and stamp_ns(m.header.stamp) == last for m in zones))
    message = next(m for m in zones if m.polygon.id == 30 and stamp_ns(m.header.stamp) == last)
    centroid = np.mean([(p.x, p.y) for p in message.polygon.polygon.points], axis=0)
    drawn = np.linalg.norm(homing.centroid - pusher)
    assert drawn - np.linalg.norm(centroid - pusher) > 50  # 0.5 s at 200 px/s, at least

    assert bad.wait(timeout=20) != 0
    log = bad_log.read_text()
    assert "collinear" in log and "Traceback" not in log


# --------------------------------------------------------------------------- recorder




def test_a_keepout_resolution_too_fine_for_a_mask_is_refused_in_one_line(tmp_path) -> None:
    """1e-9 px cells: a mask of 10**23 cells (numpy refused it only when the first mask was
    built, in its own words); at most 4096 cells a side over the 512 px workspace."""
    done = subprocess.run([sys.executable, "-m", "constrained_diffusion_ros.nodes.zone_publisher",
                           "--ros-args", "-p", "scenario:=center_0.2", "-p",
                           "keepout_resolution:=1e-9", "-p", "rate_hz:=0.0"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO),
                               "ROS_DOMAIN_ID": str(random_domain_id())})
    assert done.returncode == 2  # bad input, as a bad command line
    output = (done.stdout + done.stderr).strip().splitlines()
    assert len(output) == 1 and "keepout_resolution" in output[0], output
    assert "at least 0.125 px" in output[0] and "Traceback" not in done.stderr
