"""The one home of message <-> array and stamp <-> control-step conversions: round trips, and
the same readers for live rclpy messages and for messages read back from a bag."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_typestore

from msg_schemas import FRAME_ID
from msg_schemas.conversions import (
    path_message,
    path_of,
    point_message,
    point_of,
    polygon_message,
    polygon_of,
    pose2d_message,
    pose2d_of,
    stamp_nanoseconds,
    stamp_of_step,
    step_of_stamp,
    zone_markers,
    zone_message,
    zones_shown,
)


@pytest.mark.parametrize("control_hz", [10, 30, 7.5])
def test_stamps_name_their_control_step_exactly(control_hz: float) -> None:
    steps = [0, 1, 2, 9, 10, 11, 199, 200, 12_345, 10**7]
    stamps = [stamp_of_step(step, control_hz) for step in steps]
    assert [step_of_stamp(stamp, control_hz) for stamp in stamps] == steps
    assert all(0 <= stamp.nanosec < 1_000_000_000 for stamp in stamps)
    assert stamp_nanoseconds(stamps[1]) == round(1e9 / control_hz)


def test_the_simulator_clock_is_a_tenth_of_a_second_per_step() -> None:
    stamp = stamp_of_step(25, 10)
    assert (stamp.sec, stamp.nanosec) == (2, 500_000_000)


@pytest.mark.parametrize("rate", [0.0, -10.0, math.inf, math.nan])
def test_a_control_rate_that_makes_no_sense_is_refused(rate: float) -> None:
    with pytest.raises(ValueError, match="control rate"):
        stamp_of_step(1, rate)


def test_messages_and_arrays_round_trip_in_the_workspace_frame() -> None:
    stamp = stamp_of_step(3, 10)
    point = point_message(np.array([12.5, 400.25]), stamp)
    assert point.header.frame_id == FRAME_ID and point.header.stamp == stamp
    np.testing.assert_array_equal(point_of(point), [12.5, 400.25])
    vertices = np.array([[1.0, 2.0], [300.0, 2.0], [300.0, 250.5]])
    np.testing.assert_allclose(polygon_of(polygon_message(vertices, stamp).polygon), vertices)
    pose = np.array([200.0, 300.0, 2.5])
    np.testing.assert_allclose(pose2d_of(pose2d_message(pose, stamp)), pose, atol=1e-12)
    chunk = np.arange(32.0).reshape(16, 2)
    path = path_message(chunk, stamp)
    assert len(path.poses) == 16 and path.poses[0].pose.orientation.w == 1.0
    np.testing.assert_array_equal(path_of(path), chunk)
    zone = zone_message(7, vertices, stamp)
    assert zone.polygon.id == 7
    np.testing.assert_allclose(polygon_of(zone.polygon.polygon), vertices)
    assert len(zone_message(7, None, stamp).polygon.polygon.points) == 0  # removes id 7
    markers = zone_markers({3: vertices, 7: vertices + 50}, stamp, "/robot1/zones")
    assert zones_shown(markers) == 2 and markers.markers[0].action == markers.markers[0].DELETEALL
    added = [m for m in markers.markers if m.action == m.ADD]
    assert [m.id for m in added] == [3, 7]  # keyed by zone id
    assert {m.ns for m in added} == {"/robot1/zones"}
    assert len(added[0].points) == 4  # closed


def test_a_zone_id_beyond_int32_never_shares_a_marker_with_another_zone() -> None:
    """PolygonInstance ids are int64, marker ids int32: id 2**32 + 3 showed as marker 3,
    drawn over zone 3; ids a marker cannot hold go to a namespace of their own."""
    vertices = np.array([[1.0, 2.0], [300.0, 2.0], [300.0, 250.5]])
    markers = zone_markers({3: vertices, 2**32 + 3: vertices, "keepout/0": vertices},
                           stamp_of_step(0, 10), "/robot1/zones")
    added = [(m.ns, m.id) for m in markers.markers if m.action == m.ADD]
    assert len(set(added)) == 3 and ("/robot1/zones", 3) in added
    assert sum(m.action == m.DELETEALL for m in markers.markers) == 2  # both cleared first


def test_bag_messages_read_like_live_ones() -> None:
    """What `rosbags` deserialises has the same fields: the readers serve bags and nodes."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    stamp = stamp_of_step(41, 10)
    live = [point_message([3.0, 4.0], stamp), pose2d_message([5.0, 6.0, -1.0], stamp)]
    types = ["geometry_msgs/msg/PointStamped", "geometry_msgs/msg/PoseStamped"]
    recorded = [typestore.deserialize_cdr(serialize_message(msg), kind)
                for msg, kind in zip(live, types)]
    assert step_of_stamp(recorded[0].header.stamp, 10) == 41
    np.testing.assert_array_equal(point_of(recorded[0]), point_of(live[0]))
    np.testing.assert_array_equal(pose2d_of(recorded[1]), pose2d_of(live[1]))
