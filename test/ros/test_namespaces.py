"""ROS names and zones the ROS way: two namespaced stacks side by side in one domain, zones from
volatile and transient-local publishers, and a restarted policy that neither loses a zone in
force nor revives one whose lifetime has passed."""

from __future__ import annotations

import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PolygonInstanceStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy
from ros_helpers import DISCOVERY_S, shown_zone_ids
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.zones import rectangle
from constrained_diffusion_ros.zones.grid import rasterize
from msg_schemas import SERVICES, TOPICS, qos_profile
from msg_schemas.conversions import occupancy_grid, zone_message

ROBOTS = ("/robot1", "/robot2")
SQUARE = rectangle(100, 100, 140, 140)


@pytest.fixture(autouse=True)
def own_endpoints(ros):
    """The test node lives for the module: a latched zone publisher left from one test would
    hand its zones to the next test's policy."""
    before = set(ros.node.publishers) | set(ros.node.subscriptions)
    yield
    for publisher in set(ros.node.publishers) - before:
        ros.node.destroy_publisher(publisher)
    for subscription in set(ros.node.subscriptions) - before:
        ros.node.destroy_subscription(subscription)


def zone_publisher(ros, namespace: str = "/pusht", durability=DurabilityPolicy.TRANSIENT_LOCAL):
    profile = qos_profile(TOPICS["zones"], "publisher")
    profile.durability = durability
    return ros.node.create_publisher(PolygonInstanceStamped,
                                     TOPICS["zones"].resolved(namespace), profile)


def markers_of(ros, namespace: str = "/pusht") -> list[MarkerArray]:
    received: list[MarkerArray] = []
    ros.node.create_subscription(MarkerArray, TOPICS["zone_markers"].resolved(namespace),
                                 received.append, qos_profile(TOPICS["zone_markers"]))
    return received


def publish(ros, publisher, zone_id: int, offset: float = 0.0) -> None:
    stamp = ros.node.get_clock().now().to_msg()
    publisher.publish(zone_message(zone_id, SQUARE + offset, stamp))


def test_two_namespaced_stacks_side_by_side_each_obey_only_their_own_zones(
        ros, processes, tiny_model, configurations_file) -> None:
    for namespace in ROBOTS:
        name = namespace.strip("/")
        processes.start(f"sim_{name}", "sim_node", remap={"__ns": namespace}, autostart=False)
        processes.start(f"policy_{name}", "policy_node", remap={"__ns": namespace},
                        model=tiny_model, configurations_file=configurations_file,
                        configuration="fast_project")
    markers = {namespace: markers_of(ros, namespace) for namespace in ROBOTS}
    zones = zone_publisher(ros, "/robot1")
    graph = ros.node

    def stacks_up() -> bool:
        names = dict(graph.get_service_names_and_types())
        return zones.get_subscription_count() == 2 and all(
            graph.count_publishers(TOPICS["pusher"].resolved(ns)) == 1
            and graph.count_subscribers(TOPICS["pusher"].resolved(ns)) == 1
            and graph.count_subscribers(TOPICS["setpoint"].resolved(ns)) == 1
            and TOPICS["zones"].resolved(ns) in dict(graph.get_topic_names_and_types())
            and f"{ns}/reset" in names and f"{ns}/clear_zones" in names for ns in ROBOTS)

    def graph_state() -> str:
        return str([(ns, graph.count_publishers(TOPICS["pusher"].resolved(ns)),
                     graph.count_subscribers(TOPICS["pusher"].resolved(ns)),
                     graph.count_subscribers(TOPICS["setpoint"].resolved(ns))) for ns in ROBOTS]
                   + [zones.get_subscription_count(), graph.get_service_names_and_types()])

    assert ros.spin_until(stacks_up, 3 * DISCOVERY_S), graph_state() + processes.logs()
    # Each policy listens to its own simulator only (one publisher per pusher topic, one
    # subscriber), and nothing is left in the default namespace.
    assert graph.count_publishers(TOPICS["pusher"].resolved()) == 0
    publish(ros, zones, 5)
    assert ros.spin_until(lambda: shown_zone_ids(markers["/robot1"]) == [5])
    ros.spin_for(1.0)
    assert shown_zone_ids(markers["/robot2"]) in (None, [])
    latest = markers["/robot1"][-1].markers
    assert {m.ns for m in latest if m.action == m.ADD} == {"/robot1/zones"}
    assert all(m.ns.startswith("/robot1/zones") for m in latest)


def test_zones_from_a_volatile_and_a_transient_local_publisher_are_both_obeyed(
        ros, processes, tiny_model, configurations_file) -> None:
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_project")
    markers = markers_of(ros)
    volatile = zone_publisher(ros, durability=DurabilityPolicy.VOLATILE)
    latched = zone_publisher(ros)
    assert ros.spin_until(lambda: volatile.get_subscription_count() == 1
                          and latched.get_subscription_count() == 2), processes.logs()
    publish(ros, volatile, 1)
    publish(ros, latched, 2, offset=100.0)
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [1, 2]), shown_zone_ids(markers)


def test_a_restarted_policy_keeps_the_zones_in_force_and_not_the_expired_ones(
        ros, processes, tiny_model, configurations_file) -> None:
    """zone_lifetime 30 (an integer, taken for the double): zone 7 carries a stamp 60 s old,
    zone 8 a fresh one, each published once on a latched topic. The policy shows 8 only (age
    counts from the stamp); restarted, it gets both from the latched history alone (nothing
    is published again) and still shows 8, never 7."""
    markers = markers_of(ros)
    zones = zone_publisher(ros)

    def start() -> None:
        processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                        configuration="fast_project", zone_lifetime=30)

    start()
    assert ros.spin_until(lambda: zones.get_subscription_count() == 2), processes.logs()
    old = ros.node.get_clock().now() - Duration(seconds=60)
    zones.publish(zone_message(7, SQUARE, old.to_msg()))
    publish(ros, zones, 8, offset=100.0)
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [8]), processes.logs()
    assert processes.stop("policy_node") == 0
    before = len(markers)
    start()
    assert ros.spin_until(lambda: len(markers) > before and shown_zone_ids(markers) == [8]), \
        processes.logs()
    assert all(7 not in (shown_zone_ids([m]) or []) for m in markers)  # never shown, never revived


def test_a_restarted_policy_does_not_revive_a_cleared_zone(
        ros, processes, tiny_model, configurations_file) -> None:
    """Zone 5 is published once on a latched topic and cleared by the service; restarted, the
    policy gets it again from the latched history and keeps it gone (the clear is remembered
    under ROS_HOME), while zone 6, published after the clear, is in force."""
    markers = markers_of(ros)
    zones = zone_publisher(ros)
    clear = ros.node.create_client(Trigger, SERVICES["clear_zones"].resolved("/pusht"))

    def start() -> None:
        processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                        configuration="fast_project")

    start()
    assert ros.spin_until(lambda: zones.get_subscription_count() == 2), processes.logs()
    publish(ros, zones, 5)
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [5]), processes.logs()
    assert clear.wait_for_service(timeout_sec=DISCOVERY_S)
    future = clear.call_async(Trigger.Request())
    assert ros.spin_until(future.done) and future.result().message == "cleared 1 zones"
    publish(ros, zones, 6, offset=100.0)
    assert ros.spin_until(lambda: shown_zone_ids(markers) == [6]), processes.logs()
    assert processes.stop("policy_node") == 0
    before = len(markers)
    start()
    assert ros.spin_until(lambda: len(markers) > before and shown_zone_ids(markers) == [6]), \
        processes.logs()
    assert all(5 not in (shown_zone_ids([m]) or []) for m in markers[before:])


@pytest.mark.parametrize("stamped", [True, False], ids=["stamped", "unstamped"])
def test_a_restarted_policy_does_not_revive_a_cleared_keepout_mask(
        ros, processes, tiny_model, configurations_file, stamped: bool) -> None:
    """As for zones: a latched keep-out mask cleared by the service stays gone when the policy
    restarts and the latched history hands it the same mask again; one sent without a stamp
    came back (it is now known by when the middleware says it was published)."""
    markers = markers_of(ros)
    mask_topic = TOPICS["keepout_mask"]
    masks = ros.node.create_publisher(OccupancyGrid, mask_topic.resolved("/pusht"),
                                      qos_profile(mask_topic, "publisher"))
    clear = ros.node.create_client(Trigger, SERVICES["clear_zones"].resolved("/pusht"))

    def start() -> None:
        processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                        configuration="fast_project")

    def shown() -> int:
        return len(shown_zone_ids(markers) or [])

    mask = rasterize([SQUARE], 4.0, (0.0, 0.0), 128, 128)
    start()
    assert ros.spin_until(lambda: masks.get_subscription_count() == 1), processes.logs()
    stamp = ros.node.get_clock().now().to_msg() if stamped else Time()
    masks.publish(occupancy_grid(mask, 4.0, (0.0, 0.0), stamp))
    assert ros.spin_until(lambda: shown() == 1), processes.logs()
    assert clear.wait_for_service(timeout_sec=DISCOVERY_S)
    future = clear.call_async(Trigger.Request())
    assert ros.spin_until(future.done) and future.result().message == "cleared 1 zones"
    assert ros.spin_until(lambda: shown() == 0)
    assert processes.stop("policy_node") == 0
    before = len(markers)
    start()
    zones = zone_publisher(ros)
    assert ros.spin_until(lambda: masks.get_subscription_count() == 1
                          and zones.get_subscription_count() == 2), processes.logs()
    ros.spin_for(2.0)  # the latched mask is delivered on matching; it must not come back
    publish(ros, zones, 6, offset=100.0)  # markers now: zone 6 and nothing else
    assert ros.spin_until(lambda: len(markers) > before and shown_zone_ids(markers) == [6]), \
        processes.logs()
    assert all(shown_zone_ids([m]) == [6] for m in markers[before:]), processes.logs()
    ros.node.destroy_publisher(masks)  # its history would reach the next test's node
