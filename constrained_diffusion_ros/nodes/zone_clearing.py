"""Zones leaving without a message: `ZoneClearing` serves the node's clear service, remembers
what was cleared across restarts, and drops zones past their lifetime."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from rclpy.node import Node
from std_srvs.srv import Trigger

from constrained_diffusion_ros.zones.live import LiveZones
from msg_schemas import SERVICES

EXPIRY_PERIOD_S = 0.2  # zones past their lifetime are dropped this often


class ZoneClearing:
    """The clear service and expiry of `zones`; `on_change()` after either changed them.

    Clears are remembered in $ROS_HOME/constrained_diffusion_ros/<node>.cleared as the (id,
    stamp) of each zone cleared, so that a latched publisher's replay of them stays gone after
    the node restarts (exact messages: any clock, any publisher)."""

    def __init__(self, node: Node, zones: LiveZones, on_change: Callable[[], None]) -> None:
        self.node, self.zones, self.on_change = node, zones, on_change
        ros_home = Path(os.environ.get("ROS_HOME") or Path.home() / ".ros")
        self.clear_file = ros_home / "constrained_diffusion_ros" / (
            node.get_fully_qualified_name().strip("/").replace("/", "__") + ".cleared")
        zones.cleared = self._remembered()
        node.create_service(Trigger, SERVICES["clear_zones"].name, self._on_clear)
        node.create_timer(EXPIRY_PERIOD_S, self._expire)

    def _expire(self) -> None:
        now = self.node.get_clock().now().nanoseconds * 1e-9  # zone stamps' clock
        if self.zones.expire(now):
            self.on_change()

    def _on_clear(self, _request, response):
        count = len(self.zones)
        self.zones.clear()
        self.on_change()
        response.success, response.message = True, f"cleared {count} zones"
        try:  # remembered across restarts: latched publishers replay what was cleared
            self.clear_file.parent.mkdir(parents=True, exist_ok=True)
            self.clear_file.write_text(json.dumps(list(self.zones.cleared)))
        except OSError as error:
            self.node.get_logger().warning(
                f"cannot remember the clear in {self.clear_file} ({error.strerror}): a restart "
                f"would revive the cleared zones that latched publishers replay")
        return response

    def _remembered(self) -> dict[tuple, None]:
        """The (id, stamp) of zones cleared by this node name in earlier runs."""
        try:
            pairs = json.loads(self.clear_file.read_text())
            return {(zone_id, float(stamp)): None for zone_id, stamp in pairs}
        except (OSError, ValueError, TypeError):
            return {}
