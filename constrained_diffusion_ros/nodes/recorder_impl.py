"""The recorder node itself (`recorder` is its command, and says what it does): apart, so
that `recorder --help` answers from the parameter table without importing rclpy or
rosbags."""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from constrained_diffusion_ros.recording import bags
from msg_schemas import NAMESPACE, TOPICS, Endpoint, qos_profile
from node_support.parameters import Param, declare
from node_support.spin import log_matches


def bag_qos(profile: QoSProfile) -> Qos:
    """An rclpy QoS profile as rosbags stores it in the bag (the enums share rmw's names)."""
    def bag_time(duration: Duration) -> QosTime:
        sec, nsec = divmod(duration.nanoseconds, 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(
        history=QosHistory[profile.history.name], depth=profile.depth,
        reliability=QosReliability[profile.reliability.name],
        durability=QosDurability[profile.durability.name],
        deadline=bag_time(profile.deadline), lifespan=bag_time(profile.lifespan),
        liveliness=QosLiveliness[profile.liveliness.name],
        liveliness_lease_duration=bag_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions)


class Recorder(Node):
    """Raw subscriptions to every contract topic, written as they arrive."""

    def __init__(self, parameters: Sequence[Param]) -> None:
        super().__init__("recorder", namespace=NAMESPACE)
        values = declare(self, parameters)
        self.output = Path(values["output"])
        metadata_file = values["metadata_file"]
        self.metadata_file = Path(metadata_file) if metadata_file else None
        self.trial_metadata = self.read_metadata(warn_missing=False)

        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        initial = {} if self.trial_metadata is None else {
            "trial_metadata": json.dumps(self.trial_metadata)}
        # WriterError if the directory exists (bags are never appended to)
        self.writer: Writer | None = bags.open_bag(self.output, initial)
        self.connections = {}  # topic -> rosbags Connection, added at its first message
        # Keyed by full name (namespace and remapping applied), as the bag stores them.
        self.subscriptions_by_topic = {}
        for endpoint in TOPICS.values():
            topic = self.resolve_topic_name(endpoint.name)
            self.subscriptions_by_topic[topic] = self.create_subscription(
                endpoint.message_class(), endpoint.name,
                partial(self.on_message, endpoint, topic), qos_profile(endpoint, "recorder"),
                raw=True)
        self.counts = dict.fromkeys(self.subscriptions_by_topic, 0)
        # What is being recorded, logged as it changes.
        self.publisher_timer = log_matches(self, list(self.subscriptions_by_topic.values()))
        self.flush_timer = self.create_timer(bags.FLUSH_PERIOD_S, self.flush)
        self.get_logger().info(f"recording {len(TOPICS)} topics to {self.output}")

    def read_metadata(self, warn_missing: bool = True) -> object | None:
        if self.metadata_file is None:
            return None
        try:
            return json.loads(self.metadata_file.read_text())
        except FileNotFoundError:
            if warn_missing:
                self.get_logger().warning(f"metadata_file {self.metadata_file} not found")
        except (OSError, ValueError) as error:
            self.get_logger().warning(f"metadata_file {self.metadata_file} unreadable: {error}")
        return None

    def on_message(self, endpoint: Endpoint, topic: str, data: bytes) -> None:
        if self.writer is None:
            return
        connection = self.connections.get(topic)
        if connection is None:
            connection = self.writer.add_connection(
                topic, endpoint.type, typestore=self.typestore,
                offered_qos_profiles=[bag_qos(qos_profile(endpoint, "publisher"))])
            self.connections[topic] = connection
        self.writer.write(connection, self.get_clock().now().nanoseconds, data)
        self.counts[topic] += 1

    def flush(self) -> None:
        if self.writer is not None:
            bags.flush(self.writer)

    def close(self) -> None:
        """Store the metadata and finish the bag; safe to call twice."""
        if self.writer is None:
            return
        trial = self.read_metadata()
        if trial is None:
            trial = self.trial_metadata
        if trial is not None:
            self.writer.set_custom_data("trial_metadata", json.dumps(trial))
        self.writer.set_custom_data("message_counts", json.dumps(self.counts))
        self.writer.close()
        self.writer = None
        counts = ", ".join(f"{name} {n}" for name, n in self.counts.items() if n)
        self.get_logger().info(f"bag {self.output} closed: {sum(self.counts.values())} "
                               f"messages ({counts or 'none'})")


def record(args: list[str] | None, parameters: Sequence[Param]) -> int:
    """Records until SIGINT or SIGTERM; 1 if the bag cannot be opened."""
    # Own signal handlers instead of rclpy's: rclpy's would shut the context down first, and the
    # bag is closed (and its summary logged) while ROS still runs.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    try:
        node = Recorder(parameters)
    except (WriterError, OSError, ValueError, ParameterException) as error:
        get_logger("recorder").error(f"cannot record: {error}")
        rclpy.try_shutdown()
        return 1
    try:
        while not stop.is_set() and rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.1)
        # Drain what DDS has already delivered, so nothing received before the signal is lost.
        node.publisher_timer.cancel()
        idle = 0
        while idle < 2:
            before = sum(node.counts.values())
            rclpy.spin_once(node, timeout_sec=0.05)
            idle = idle + 1 if sum(node.counts.values()) == before else 0
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
