"""Every topic and service: name, message type, QoS, frame and units.

Names are relative, as ROS expects: each node resolves them in its namespace, `pusht` unless
started with another (`--ros-args -r __ns:=/robot1`), and remaps them by their plain name
(`-r zones:=/obstacles`). The nodes, the recorder, the trial launcher and the README's diagram
all read names from here; no topic string is written anywhere else. Plain data (no rclpy
import), so the contract can be read, tested and documented without ROS; `qos_profile` builds
the rclpy QoS when needed.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

FRAME_ID = "workspace"  # PushT workspace: 512 x 512 px, origin top-left, y down (as the image)
NAMESPACE = "pusht"  # every node's namespace unless `__ns` says otherwise
OPTIONAL_NODES = ("view_node",)  # a stack runs with or without them: nobody waits for them


@dataclass(frozen=True)
class Endpoint:
    name: str
    type: str  # ROS interface type, e.g. "geometry_msgs/msg/PointStamped"
    qos: str  # "sensor", "latched" (late joiners get the zones in force), "map" or "clock"
    publisher: str
    subscribers: tuple[str, ...]
    units: str
    description: str

    @property
    def key(self) -> str:
        """How code refers to it: `TOPICS["setpoint"].name` is "setpoint"."""
        return self.name.rsplit("/", 1)[-1]

    def resolved(self, namespace: str = NAMESPACE) -> str:
        """The full name in `namespace`: "/pusht/setpoint" by default (an absolute name, as
        /diagnostics, stays as it is)."""
        if self.name.startswith("/"):
            return self.name
        prefix = namespace.strip("/")
        return f"/{prefix}/{self.name}" if prefix else f"/{self.name}"

    def message_class(self) -> type:
        """The generated Python class of `type` ("geometry_msgs/msg/PointStamped" ->
        geometry_msgs.msg.PointStamped); imported when asked, so the contract needs no ROS."""
        package, kind, name = self.type.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)


TOPICS: dict[str, Endpoint] = {e.key: e for e in (
    Endpoint("pusher", "geometry_msgs/msg/PointStamped", "sensor", "sim_node",
             ("policy_node", "recorder", "view_node"),
             "px, frame workspace; stamp = simulated time",
             "Pusher position after each control step"),
    Endpoint("keypoints", "geometry_msgs/msg/PolygonStamped", "sensor", "sim_node",
             ("policy_node", "recorder"), "px, frame workspace; same stamp as pusher",
             "The 9 T-block keypoints (dataset order) after each control step"),
    Endpoint("block_pose", "geometry_msgs/msg/PoseStamped", "sensor", "sim_node",
             ("recorder", "view_node"), "px and rad about z, frame workspace", "T block pose"),
    Endpoint("score", "std_msgs/msg/Float64", "sensor", "sim_node", ("recorder", "view_node"),
             "score in [0, 1] = clip(coverage / 0.95)", "Goal coverage score after each step"),
    Endpoint("setpoint", "geometry_msgs/msg/PointStamped", "sensor", "policy_node",
             ("sim_node", "recorder", "view_node"),
             "px, frame workspace; stamp = the observation's",
             "Commanded pusher target, one per control step"),
    Endpoint("plan", "nav_msgs/msg/Path", "sensor", "policy_node", ("recorder", "view_node"),
             "px, frame workspace", "The chunk in force, from its first executed waypoint (15)"),
    Endpoint("zones", "geometry_msgs/msg/PolygonInstanceStamped", "latched",
             "zone_publisher", ("policy_node", "recorder"), "px, frame workspace",
             "Restricted zones keyed by id: add or replace; an empty polygon removes the id (also "
             "published by view_node: zones drawn in the Foxglove app)"),
    Endpoint("keepout_mask", "nav_msgs/msg/OccupancyGrid", "map", "zone_publisher",
             ("policy_node", "recorder"), "cells of `resolution` px from `origin`, frame workspace",
             "A keep-out mask (nav2 keep-out filter convention: cells >= keepout_threshold are "
             "restricted, -1 free); replaces the previous mask"),
    Endpoint("zone_markers", "visualization_msgs/msg/MarkerArray", "latched",
             "policy_node", ("recorder", "view_node"), "px, frame workspace",
             "Zones in force for viewers: one line strip per zone, marker id = zone id, marker "
             "namespace <node namespace>/zones"),
    Endpoint("/clock", "rosgraph_msgs/msg/Clock", "clock", "sim_node",
             ("policy_node", "zone_publisher", "recorder"), "simulated time = control step / 10",
             "Simulated time with each observation: nodes started with use_sim_time run on it "
             "(absolute, as ROS expects)"),
    Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", "sensor", "policy_node",
             ("recorder", "view_node"), "key/value strings",
             "Health (OK / WARN / ERROR) and counters: plans, planning time, zones in force by "
             "id; absolute, as every ROS diagnostics publisher"),
)}

SERVICES: dict[str, Endpoint] = {e.key: e for e in (
    Endpoint("clear_zones", "std_srvs/srv/Trigger", "services", "policy_node", (), "",
             "Remove every zone in force (zones stamped before the call stay gone, across "
             "restarts too)"),
    Endpoint("reset", "std_srvs/srv/Trigger", "services", "sim_node", (), "",
             "Reset the scene to the sim node's `seed` parameter (set it first)"),
    Endpoint("policy_node/change_state", "lifecycle_msgs/srv/ChangeState", "services",
             "policy_node", (), "",
             "Lifecycle transitions (configure, activate, deactivate, cleanup, shutdown), as "
             "nav2's lifecycle manager asks them; get_state beside it"),
)}


def qos_profile(endpoint: Endpoint, role: str = "subscriber"):
    """The rclpy QoS profile of a topic for a role: "publisher", "subscriber" or "recorder".

    All reliable. Publishers keep their recent history (transient local) so that a recorder
    whose match arrives late still gets the first messages of a trial; live subscribers of
    sensor topics ask for no history (volatile), so a simulator never acts on stale setpoints;
    latched topics (zones) give every late joiner the zones in force. The clock keeps no
    history at all (a late joiner must not see time run backwards), for every role; a map (a
keep-out mask) keeps its latest message only, as nav2's map server.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if role not in ("publisher", "subscriber", "recorder"):
        raise ValueError(f"unknown QoS role {role!r}")
    latched = endpoint.qos in ("latched", "map")
    keeps_history = endpoint.qos != "clock" and (latched or role != "subscriber")
    # Latched (zones): deep enough that a burst of updates waits for the callback instead of
    # being overwritten, and a late joiner gets every id's last message.
    depths = {"map": 1, "latched": 10_000}
    depth = depths.get(endpoint.qos, 1000 if keeps_history else 10)
    if role == "recorder":  # a recorder queues whatever comes, in bursts too
        depth = max(depth, 1000)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if keeps_history else DurabilityPolicy.VOLATILE)
