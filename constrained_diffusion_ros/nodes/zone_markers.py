"""The zones in force, shown: `ZoneMarkers` publishes them as markers for viewers (RViz,
Foxglove) when they change, at most once per control tick in realtime so that a flood of zone
messages costs the executor no marker per message."""

from __future__ import annotations

from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.zones.live import LiveZones
from msg_schemas import TOPICS, qos_profile
from msg_schemas.conversions import zone_markers

MARKER_NAMESPACE = "zones"  # marker namespace <node namespace>/zones, id = zone id


class ZoneMarkers:
    """Markers of `zones` on the node's zone-marker topic. `changed` after every change:
    published at once, or with `period_s` (realtime) at the next timer tick."""

    def __init__(self, node: Node, zones: LiveZones, period_s: float | None) -> None:
        self.node, self.zones = node, zones
        self.publisher = node.create_publisher(MarkerArray, TOPICS["zone_markers"].name,
                                               qos_profile(TOPICS["zone_markers"], "publisher"))
        self._due = False
        self._paced = period_s is not None
        if self._paced:
            node.create_timer(period_s, self._on_timer)
        if zones.fixed is not None:
            self.publish()  # viewers see the plug-in check from the start

    def changed(self) -> None:
        if self._paced:
            self._due = True
        else:
            self.publish()

    def _on_timer(self) -> None:
        if self._due:
            self._due = False
            self.publish()

    def publish(self) -> None:
        stamp = self.node.get_clock().now().to_msg()
        namespace = "/".join((self.node.get_namespace().rstrip("/"), MARKER_NAMESPACE))
        outlines = self.zones.outlines()
        for k, polygon in enumerate(getattr(self.zones.fixed, "polygons", None) or []):
            outlines[f"plugin/{k}"] = polygon  # a plug-in check that can show itself
        self.publisher.publish(zone_markers(outlines, stamp, namespace))
