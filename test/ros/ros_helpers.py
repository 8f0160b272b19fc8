"""Shared helpers for tests that run nodes as processes over real DDS.

Node processes come from the package's own launcher (`NodeProcesses`), in a random ROS domain
per test module, so parallel runs on one machine, and other modules of the same run, do not
hear each other. Waits poll match counts, messages or logs, never blind sleeps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from geometry_msgs.msg import Point32, PointStamped, PolygonStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from constrained_diffusion_ros.evaluation.launcher import NodeProcesses, random_domain_id
from msg_schemas import FRAME_ID, NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import stamp_nanoseconds, stamp_of_step, step_of_stamp
from node_support import spin
from sim_bridge import CONTROL_HZ

REPO = Path(__file__).resolve().parents[2]
SEED = 100000  # the scene the node tests run
DISCOVERY_S = 20.0  # discovery takes a few seconds here; generous for a loaded machine

__all__ = [
    "DISCOVERY_S",
    "REPO",
    "SEED",
    "NodeProcesses",
    "Ros",
    "observation_messages",
    "random_domain_id",
    "shown_zone_ids",
    "stamp_ns",
    "stamp_step",
    "step_ns",
    "step_stamp",
]


def shown_zone_ids(markers: list) -> list[int] | None:
    """Zone ids (marker ids) in the latest of the policy's zone markers; None before any."""
    if not markers:
        return None
    return sorted(m.id for m in markers[-1].markers if m.action == m.ADD)


def stamp_ns(stamp) -> int:
    return stamp_nanoseconds(stamp)


def stamp_step(stamp) -> int:
    """Control step of a simulated-time stamp."""
    return step_of_stamp(stamp, CONTROL_HZ)


class Ros:
    """The in-process test node, on its own context in the test's domain."""

    def __init__(self, domain_id: int, name: str = "test_node") -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, namespace=NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate: Callable[[], bool], timeout: float = DISCOVERY_S) -> bool:
        return spin.spin_until(self.executor, predicate, timeout, period_s=0.02)

    def spin_for(self, seconds: float) -> None:
        """Keep receiving for a while: only to check that nothing *more* arrives."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def publisher(self, topic: str, msg_type, name: str | None = None):
        """A publisher with the contract's QoS for `topic` (a TOPICS key), on `name` if given
        (a remapped copy of the topic), else on the contract's name."""
        endpoint = TOPICS[topic]
        return self.node.create_publisher(msg_type, name or endpoint.name,
                                          qos_profile(endpoint, "publisher"))

    def inbox(self, topic: str, msg_type, callback: Callable | None = None) -> list:
        """Every message on a contract topic, in arrival order (after `callback`, if given)."""
        received: list = []

        def keep(msg) -> None:
            received.append(msg)
            if callback is not None:
                callback(msg)

        self.node.create_subscription(msg_type, TOPICS[topic].name, keep,
                                      qos_profile(TOPICS[topic]))
        return received

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def step_stamp(step: int):
    """The simulated-time stamp of a control step."""
    return stamp_of_step(step, CONTROL_HZ)


def step_ns(step: int) -> int:
    return stamp_nanoseconds(step_stamp(step))


def observation_messages(step: int, pusher: tuple[float, float]
                         ) -> tuple[PolygonStamped, PointStamped]:
    """The two halves of one observation of control step `step`, as the simulator stamps them:
    a fixed T (keypoints up the middle) and the pusher at `pusher`."""
    keypoints = PolygonStamped()
    keypoints.header.stamp, keypoints.header.frame_id = step_stamp(step), FRAME_ID
    keypoints.polygon.points = [Point32(x=256.0, y=256.0 + i, z=0.0) for i in range(9)]
    message = PointStamped()
    message.header = keypoints.header
    message.point.x, message.point.y = pusher
    return keypoints, message
