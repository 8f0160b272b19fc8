"""The view node itself (`view_node` is its command, and says what it does): apart, so that
`view_node --help` answers from the parameter table without importing rclpy, torch or
foxglove."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence

import foxglove
import torch
from diagnostic_msgs.msg import DiagnosticArray
from foxglove.channels import FrameTransformChannel, SceneUpdateChannel
from geometry_msgs.msg import PolygonInstanceStamped
from rclpy.node import Node

from constrained_diffusion_ros.nodes.policy_status import StatusReporter
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.view.layout import view_channels
from constrained_diffusion_ros.view.scene import (
    PARTS,
    SceneState,
    scene_update,
    take_policy_status,
    view_transform,
)
from constrained_diffusion_ros.view.zone_requests import (
    ZONE_REQUEST_SCHEMA,
    ZONE_REQUEST_SCHEMA_NAME,
    ZoneRequests,
)
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import zone_message
from msg_schemas.text import one_line
from node_support.parameters import Param, declare
from node_support.spin import UnusableArgument

STATUS_PERIOD_S = 1.0


class _Listener(foxglove.ServerListener):
    def __init__(self, requests: ZoneRequests) -> None:
        self.requests = requests

    def on_client_advertise(self, client, channel) -> None:
        self.requests.advertised(client.id, channel.id, channel.topic)

    def on_client_unadvertise(self, client, client_channel_id: int) -> None:
        self.requests.unadvertised(client.id, client_channel_id)

    def on_message_data(self, client, client_channel_id: int, data: bytes) -> None:
        self.requests.received(client.id, client_channel_id, data)


class ViewNode(Node):
    def __init__(self, parameters: Sequence[Param]) -> None:
        super().__init__("view_node", namespace=NAMESPACE)
        values = declare(self, parameters)
        torch.set_num_threads(1)  # zone checks only: the cores are the policy's
        prefix = self.get_namespace().rstrip("/")
        channels = view_channels(prefix)
        self.policy_name = f"{prefix}/{values['policy_node']}"
        self.inflating = {name for name, config in
                          load_configurations(values["configurations_file"]).items()
                          if config.inflate}
        self.state = SceneState(pusher_radius=PUSHT_ROBOT.pusher_radius)
        self.requests = ZoneRequests(channels["zone_requests"], values["max_vertices"],
                                     PUSHT_ROBOT.workspace)
        self.shown_view_refusal = ""
        self.frames, self._dirty = 0, True
        self.foxglove = foxglove.Context()
        self.scene_channel = SceneUpdateChannel(channels["scene"], context=self.foxglove)
        self.transform_channel = FrameTransformChannel(channels["transforms"],
                                                       context=self.foxglove)
        self.status_channel = foxglove.Channel(channels["status"], context=self.foxglove,
                                               message_encoding="json")
        # The request channel is the client's; advertised here only so the layout's Publish
        # panel finds its schema.
        self.request_channel = foxglove.Channel(
            self.requests.topic, context=self.foxglove, message_encoding="json",
            schema=foxglove.Schema(name=ZONE_REQUEST_SCHEMA_NAME, encoding="jsonschema",
                                   data=json.dumps(ZONE_REQUEST_SCHEMA).encode()))
        try:
            self.server = foxglove.start_server(
                name=f"constrained_diffusion_ros {prefix or '/'}", host=values["host"],
                port=values["port"], context=self.foxglove,
                capabilities=[foxglove.Capability.ClientPublish], supported_encodings=["json"],
                server_listener=_Listener(self.requests),
                message_backlog_size=values["backlog"])
        except RuntimeError as error:
            raise UnusableArgument(f"cannot serve the view on {values['host']}:{values['port']}"
                                   f": {one_line(str(error)).split(': ')[-1]}") from None
        self.zone_pub = self.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                              qos_profile(TOPICS["zones"], "publisher"))
        self._subscribe()
        self.status = StatusReporter(self)
        self.create_timer(1.0 / values["rate_hz"], self._on_frame)
        self.create_timer(STATUS_PERIOD_S, self._on_status)
        self.get_logger().info(f"view on ws://{values['host']}:{self.server.port} "
                               f"(Foxglove: Open connection; layout config/foxglove_layout.json)")

    def destroy_node(self) -> None:
        self.server.stop()
        super().destroy_node()

    def _subscribe(self) -> None:
        """Each topic keeps its part of the scene state: the latest message, converted."""
        for part, (topic, convert) in PARTS.items():
            endpoint = TOPICS[topic]
            self.create_subscription(endpoint.message_class(), endpoint.name,
                                     self._keeper(part, convert), qos_profile(endpoint))
        self.create_subscription(DiagnosticArray, TOPICS["diagnostics"].name,
                                 self._on_diagnostics, qos_profile(TOPICS["diagnostics"]))

    def _keeper(self, part: str, convert):
        def on_message(msg) -> None:
            setattr(self.state, part, convert(msg))
            self._dirty = True
        return on_message

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.policy_name:
                before = self.state.policy_refusal
                take_policy_status(self.state, status.message,
                                   {kv.key: kv.value for kv in status.values},
                                   self.inflating)
                if self.state.policy_refusal != before:
                    self._show_refusal(self.state.policy_refusal)
                self._dirty = True

    def _show_refusal(self, reason: str) -> None:
        """In the scene and as a warning in the app, until another."""
        self.state.refusal = reason
        self._dirty = True
        self.server.publish_status(f"zone refused: {reason}", foxglove.StatusLevel.Warning)

    def _on_frame(self) -> None:
        """Zone requests out to ROS, then the scene, if anything changed."""
        stamp = self.get_clock().now()
        for zone_id, vertices in self.requests.take().items():
            self.zone_pub.publish(zone_message(zone_id, vertices if len(vertices) else None,
                                               stamp.to_msg()))
        if self.requests.reason != self.shown_view_refusal:
            self.shown_view_refusal = self.requests.reason
            self._show_refusal(self.requests.reason)
        if not self._dirty:
            return
        self._dirty = False
        now_ns = time.time_ns()
        self.transform_channel.log(view_transform(now_ns), log_time=now_ns)
        self.scene_channel.log(scene_update(self.state, now_ns), log_time=now_ns)
        state = self.state
        self.status_channel.log(json.dumps(
            {"score": state.score, "filter": state.filter_state or "free",
             "policy": state.policy_status, "zone_refused": state.refusal,
             "zones": sorted(state.zones)}), log_time=now_ns)
        self.frames += 1

    def _on_status(self) -> None:
        self.status.publish({**self.requests.counts, "zone_refusal": self.requests.reason,
                             "frames": self.frames, "port": self.server.port})
