"""Simulated time: the sim publishes /clock; with use_sim_time the realtime sim still steps and
the policy ages zones on sim time (a zone stamped with sim time would be ancient on wall
time, so it shows only if sim time is used, and expires after its lifetime of sim time)."""

from __future__ import annotations

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, PolygonInstanceStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import shown_zone_ids
from rosgraph_msgs.msg import Clock
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.zones import rectangle
from msg_schemas import TOPICS, qos_profile
from msg_schemas.conversions import stamp_nanoseconds, zone_message


def test_with_use_sim_time_the_realtime_sim_steps_and_a_lifetime_expires_on_sim_time(
        ros, processes, tiny_model, configurations_file) -> None:
    clock: list[int] = []
    pushers: list[PointStamped] = []
    markers: list[MarkerArray] = []
    node = ros.node
    node.create_subscription(Clock, TOPICS["clock"].name,
                             lambda m: clock.append(stamp_nanoseconds(m.clock)),
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    node.create_subscription(PointStamped, TOPICS["pusher"].name, pushers.append,
                             qos_profile(TOPICS["pusher"]))
    node.create_subscription(MarkerArray, TOPICS["zone_markers"].name, markers.append,
                             qos_profile(TOPICS["zone_markers"]))
    zones = node.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                  qos_profile(TOPICS["zones"], "publisher"))
    processes.start("sim_node", mode="realtime", use_sim_time=True)
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_project", use_sim_time=True, zone_lifetime=3.0)
    assert ros.spin_until(lambda: zones.get_subscription_count() == 2 and len(clock) >= 20), \
        processes.logs()
    assert clock == sorted(clock) and clock[-1] - clock[0] >= 1.5e9  # 10 steps a second
    assert any(stamp_nanoseconds(m.header.stamp) in clock for m in pushers)  # sim-time stamps

    sim_now = clock[-1]
    sec, nanosec = divmod(sim_now, 10**9)
    zones.publish(zone_message(3, rectangle(10, 10, 40, 40), Time(sec=sec, nanosec=nanosec)))

    # Fresh on sim time (on wall time its stamp would be ancient), then gone.
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [3], 10.0), processes.logs()
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [], 15.0), "the zone never expired"
