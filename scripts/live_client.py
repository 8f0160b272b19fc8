"""The live benchmarks' own ROS client (`Client`): observes the topics of a stack of nodes
(`launcher.Stack`, the harness `trial` runs on too), drops zones and resets the sim; and
`start_scene`, a reset that waits for the new scene's first plan. bench_realtime,
moving_trials, bench_hostile and bench_startup drive the nodes through it."""

from __future__ import annotations

import sys
import threading
import time
from typing import NamedTuple

import numpy as np
import shapely

from constrained_diffusion_ros.evaluation.launcher import Stack
from msg_schemas import NAMESPACE, SERVICES, TOPICS, qos_profile
from msg_schemas.conversions import path_of, point_of, step_of_stamp, zone_message
from sim_bridge import CONTROL_HZ


class Setpoint(NamedTuple):
    """A setpoint as the client got it; times in s."""

    received: float  # time.monotonic() when the client's callback ran
    point: np.ndarray  # (2,)
    sent: float  # the policy's clock (wall time) when it published it: its source timestamp
    delivered: float  # the same clock, when the client's middleware received it
    called: float  # the same clock, when the client's callback ran


class Client:
    """On the stack's client node: observes the topics, drops zones, resets the sim.

    Setpoints are taken on a thread of their own (a second node with its own executor), as a
    robot driver would take them: they do not wait behind this client's bookkeeping of plans,
    markers and diagnostics on the main thread.
    """

    def __init__(self, stack: Stack) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped, PolygonInstanceStamped
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter_client import AsyncParameterClient
        from std_srvs.srv import Trigger
        from visualization_msgs.msg import MarkerArray

        self.stack, self.context = stack, stack.context
        self.node, self.executor = stack.node, stack.executor
        self.setpoints: list[Setpoint] = []  # appended by the listener thread only
        self.pushers: list[tuple[float, int, np.ndarray]] = []
        self.plan: np.ndarray | None = None
        self.plan_time = 0.0
        self.plan_times: list[float] = []  # time.monotonic() of every plan received
        # When the client got the last markers (monotonic s), when the policy sent them (its
        # clock, s), and the union of the zones they show.
        self.markers: tuple[float, float, shapely.Geometry] | None = None
        self.status: dict[str, str] = {}

        def subscribe(key: str, msg_type, callback) -> None:
            self.node.create_subscription(msg_type, TOPICS[key].name, callback,
                                          qos_profile(TOPICS[key]))

        # The listener thread waits at most this long for the interpreter lock (default 5 ms).
        sys.setswitchinterval(0.0002)
        self.listener = rclpy.create_node("bench_realtime_setpoints", namespace=NAMESPACE,
                                          context=self.context)
        self.listener.create_subscription(PointStamped, TOPICS["setpoint"].name,
                                          self._on_setpoint, qos_profile(TOPICS["setpoint"]))
        self.listener_executor = SingleThreadedExecutor(context=self.context)
        self.listener_executor.add_node(self.listener)
        self.listener_thread = threading.Thread(target=self.listener_executor.spin,
                                                name="setpoints", daemon=True)
        self.listener_thread.start()
        subscribe("pusher", PointStamped, lambda m: self.pushers.append(
            (time.monotonic(), step_of_stamp(m.header.stamp, CONTROL_HZ), point_of(m))))
        subscribe("plan", PathMsg, self._on_plan)
        subscribe("zone_markers", MarkerArray, self._on_markers)
        subscribe("diagnostics", DiagnosticArray,
                  lambda m: self.status.update({kv.key: kv.value for kv in m.status[0].values}))
        self.zones = self.node.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                                qos_profile(TOPICS["zones"], "publisher"))
        self.reset = self.node.create_client(Trigger, SERVICES["reset"].name)
        self.clear = self.node.create_client(Trigger, SERVICES["clear_zones"].name)
        self.sim_parameters = AsyncParameterClient(self.node, "sim_node")
        self.Trigger = Trigger

    def discovered(self) -> bool:
        node = self.node
        return (self.reset.service_is_ready() and self.sim_parameters.services_are_ready()
                and all(s.get_publisher_count() >= 1
                        for s in (*node.subscriptions, *self.listener.subscriptions))
                and self.zones.get_subscription_count() >= 1
                and node.count_subscribers(TOPICS["pusher"].name) >= 2)

    def _on_setpoint(self, msg, info: dict) -> None:
        self.setpoints.append(Setpoint(time.monotonic(), point_of(msg),
                                       info["source_timestamp"] * 1e-9,
                                       info["received_timestamp"] * 1e-9, time.time()))

    def _on_plan(self, msg) -> None:
        self.plan, self.plan_time = path_of(msg), time.monotonic()
        self.plan_times.append(self.plan_time)

    def _on_markers(self, msg, info: dict) -> None:
        polygons = [shapely.Polygon([(p.x, p.y) for p in m.points[:-1]])
                    for m in msg.markers if m.action == m.ADD]
        self.markers = (time.monotonic(), info["source_timestamp"] * 1e-9,
                        shapely.union_all(polygons))

    def spin_until(self, condition, timeout: float, what: str) -> None:
        self.stack.wait_for(condition, what, timeout, period_s=0.005)

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        self.spin_until(lambda: time.monotonic() >= deadline, seconds + 1, "time")

    def call(self, client, request, what: str):
        return self.stack.call(client, request, what)

    def reset_to(self, seed: int) -> None:
        from rclpy.parameter import Parameter

        future = self.sim_parameters.set_parameters([Parameter("seed", value=seed)])
        self.spin_until(future.done, 30.0, "the sim's seed")
        self.call(self.reset, self.Trigger.Request(), "sim reset")

    def publish_zone(self, zone_id: int, vertices) -> None:
        self.zones.publish(zone_message(zone_id, vertices, self.node.get_clock().now().to_msg()))

    def close(self) -> None:
        """The setpoint listener stopped; the stack closes the rest."""
        self.listener_executor.shutdown()
        self.listener_thread.join(timeout=5.0)
        self.listener.destroy_node()



def start_scene(client: Client, seed: int) -> float:
    """Reset the sim to `seed` and wait for a plan of the new scene (not one the node was still
    planning for the last); when the wait for the plan began (time.monotonic())."""
    last, seen = (client.pushers[-1][1] if client.pushers else 0), len(client.pushers)
    client.reset_to(seed)
    # Until the node sees the new scene it may still install (and publish) a plan of the last
    # one: wait for the new scene's first observation, then for a plan after it. (A sim still
    # at step 0 gives nothing to tell the new scene by.)
    if last > 0:
        client.spin_until(lambda: any(step < last for _, step, _ in client.pushers[seen:]),
                          60.0, "the new scene")
    begin = time.monotonic()
    client.spin_until(lambda: client.plan is not None and client.plan_time > begin
                      and client.setpoints and client.setpoints[-1].received > begin,
                      60.0, "a plan after the reset")
    return begin
