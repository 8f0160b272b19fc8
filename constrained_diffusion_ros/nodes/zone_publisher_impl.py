"""The zone publisher node itself (`zone_publisher` is its command, and says what it does):
apart, so that `zone_publisher --help` answers from the parameter table without importing
rclpy, torch or shapely."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, PolygonInstanceStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node

from constrained_diffusion_ros.evaluation.scenarios import Scenario, load_scenarios
from constrained_diffusion_ros.evaluation.zone_paths import ZoneMover
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import rasterize, validate_polygon
from constrained_diffusion_ros.zones.grid import MaskCaps
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import occupancy_grid, step_of_stamp, zone_message
from node_support.parameters import Param, declare
from sim_bridge import CONTROL_HZ

# Cells a side of the keep-out mask at most (zone_publisher.MAX_KEEPOUT_CELLS, which --help
# shows, is the same number written out).
MAX_KEEPOUT_CELLS = math.isqrt(MaskCaps.cells)


def parse_polygon(text: str, label: str = "parameter polygon") -> np.ndarray:
    """'x1,y1;x2,y2;...' -> (V, 2) vertices, validated; ValueError names the fault."""
    try:
        vertices = [[float(c) for c in pair.split(",")] for pair in text.split(";")
                    if pair.strip()]
    except ValueError:
        raise ValueError(f"{label}: expected 'x1,y1;x2,y2;...', got {text!r}") from None
    if any(len(v) != 2 for v in vertices):
        raise ValueError(f"{label}: every vertex needs exactly x,y, got {text!r}")
    validate_polygon(vertices, label)
    return np.asarray(vertices, dtype=float)


class ZonePublisher(Node):
    """Publishes a scenario's zones, one ad-hoc polygon and/or one removal, and keeps them up."""

    def __init__(self, parameters: Sequence[Param]) -> None:
        super().__init__("zone_publisher", namespace=NAMESPACE)
        values = declare(self, parameters)

        def param(name: str):
            return values[name]

        self.scenario: Scenario | None = None
        if name := param("scenario"):
            scenarios = load_scenarios(param("scenarios_file") or None)
            if name not in scenarios:
                raise ValueError(f"unknown scenario {name!r}; known: {', '.join(scenarios)}")
            self.scenario = scenarios[name]
        first_id = int(param("first_id"))
        n_scenario = len(self.scenario.polygons) if self.scenario else 0
        self.scenario_ids = list(range(first_id, first_id + n_scenario))
        ids = list(self.scenario_ids)
        self.adhoc: tuple[int, np.ndarray] | None = None
        if text := param("polygon"):
            zone_id = int(param("zone_id"))
            self.adhoc = (zone_id if zone_id >= 0 else first_id + n_scenario, parse_polygon(text))
            ids.append(self.adhoc[0])
        remove_id = int(param("remove_id"))
        self.remove_id = remove_id if remove_id >= 0 else None
        if self.remove_id is not None:
            ids.append(self.remove_id)
        if not ids:
            raise ValueError("nothing to publish: set scenario, polygon or remove_id")
        if len(set(ids)) != len(ids):
            raise ValueError(f"zone ids collide: {ids} (set first_id, zone_id or remove_id)")

        topic = TOPICS["zones"]
        self.pub = self.create_publisher(PolygonInstanceStamped, topic.name,
                                         qos_profile(topic, "publisher"))
        self.grid_resolution = float(param("keepout_resolution"))
        x_min, y_min, x_max, y_max = PUSHT_ROBOT.workspace
        finest = max(x_max - x_min, y_max - y_min) / MAX_KEEPOUT_CELLS
        if 0 < self.grid_resolution < finest:
            raise ValueError(f"parameter keepout_resolution must be 0 (polygons) or at least "
                             f"{finest:g} px (a mask of at most {MAX_KEEPOUT_CELLS} cells a "
                             f"side), got {self.grid_resolution!r}")
        if self.grid_resolution > 0:
            if self.scenario is None:
                raise ValueError("keepout_resolution needs a scenario")
            mask = TOPICS["keepout_mask"]
            self.grid_pub = self.create_publisher(OccupancyGrid, mask.name,
                                                  qos_profile(mask, "publisher"))
        self.follow = bool(param("follow_sim_time")) and self.scenario is not None \
            and self.scenario.moving
        self.step = 0
        self.sim_time: Time | None = None  # stamp of the sim step last seen
        self.start = self.get_clock().now()
        homes = self.scenario is not None and self.scenario.homes
        self.mover = ZoneMover(self.scenario.motion, self.scenario.centroid, 1) if homes else None
        self.pusher: np.ndarray | None = None  # where the sim last said the pusher is
        if self.follow or homes:
            pusher = TOPICS["pusher"]
            self.create_subscription(PointStamped, pusher.name, self.on_pusher,
                                     qos_profile(pusher))
        rate_hz = float(param("rate_hz"))
        if rate_hz > 0:
            self.create_timer(1.0 / rate_hz, self.publish_zones)
        self.publish_zones()
        self.get_logger().info(f"publishing zone ids {ids}"
                               + (f" of scenario {self.scenario.name!r}" if self.scenario else ""))

    def publish_zones(self) -> None:
        if self.follow:
            stamp = self.sim_time or Time()
        else:
            now = self.get_clock().now()
            stamp = now.to_msg()
            if self.scenario is not None and self.scenario.moving:
                self.step = int((now - self.start).nanoseconds * CONTROL_HZ // 1_000_000_000)
        if self.scenario is not None and self.grid_resolution > 0:
            self.grid_pub.publish(self.keepout_mask(stamp))
        elif self.scenario is not None:
            for zone_id, vertices in zip(self.scenario_ids, self.polygons()):
                self.pub.publish(zone_message(zone_id, vertices, stamp))
        if self.adhoc is not None:
            self.pub.publish(zone_message(*self.adhoc, stamp))
        if self.remove_id is not None:
            self.pub.publish(zone_message(self.remove_id, None, stamp))

    def keepout_mask(self, stamp) -> OccupancyGrid:
        """The scenario's zones at the current step rasterized over the workspace."""
        x_min, y_min, x_max, y_max = PUSHT_ROBOT.workspace
        cells = (int(np.ceil((x_max - x_min) / self.grid_resolution)),
                 int(np.ceil((y_max - y_min) / self.grid_resolution)))
        values = rasterize(self.polygons(), self.grid_resolution,
                           (x_min, y_min), *cells)
        return occupancy_grid(values, self.grid_resolution, (x_min, y_min), stamp)

    def polygons(self) -> list[np.ndarray]:
        """The scenario's zones at the current step (a homing one: headed for the pusher as
        last reported; where its path puts it until a pusher is)."""
        if self.mover is None or self.pusher is None:
            return self.scenario.polygons_at(self.step)
        return self.scenario.polygons_at(self.step, self.mover.at(self.step, self.pusher[None])[0])

    def on_pusher(self, msg: PointStamped) -> None:
        """A new sim step (stamp = step / 10 s; a reset goes back to 0): move the zones there."""
        self.pusher = np.array([msg.point.x, msg.point.y])
        if not self.follow:
            return
        step = step_of_stamp(msg.header.stamp, CONTROL_HZ)
        if self.sim_time is not None and step == self.step:
            return  # the sim re-sent an observation it already published
        self.step, self.sim_time = step, msg.header.stamp
        self.publish_zones()
