"""The last word on a live setpoint before it leaves: whatever the planner or a fault produced,
the robot gets a finite setpoint inside the workspace, and none that moves it while the zones
leave it no free space."""

from __future__ import annotations

import numpy as np
import torch

from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.live import LiveZones
from constrained_diffusion_ros.zones.plugins import ZoneCheckError


class SoundSetpoints:
    """Passes sound setpoints and stands in for the rest: while there is no free space, the
    pusher's own (plausible) position; else the last setpoint passed, if it is still outside
    every zone; else the pusher's position. `unsound` counts the stand-ins."""

    def __init__(self, robot: RobotModel, zones: LiveZones) -> None:
        self.robot, self.zones = robot, zones
        self.no_free_space = False  # the zones (grown by the pusher) cover the workspace
        self.unsound = 0
        self.last_sound: np.ndarray | None = None

    def zones_changed(self) -> None:
        self.no_free_space = leaves_no_room(self.zones.snapshot().geometry,
                                            self.robot.workspace, self.robot.pusher_radius)

    def __call__(self, setpoint: np.ndarray, pusher: np.ndarray | None) -> np.ndarray:
        """`setpoint` (2,) if sound, else its stand-in (`pusher`: the last plausible
        position)."""
        if not self.no_free_space and np.all(np.isfinite(setpoint)) \
                and not self.robot.outside(setpoint):
            self.last_sound = setpoint
            return setpoint
        self.unsound += 1
        last = self.last_sound
        if not self.no_free_space and last is not None and self._clear(last):
            return last
        x_min, y_min, x_max, y_max = self.robot.workspace
        return np.clip(pusher, (x_min, y_min), (x_max, y_max))

    def inside_zone(self, point: np.ndarray) -> bool:
        """Whether `point` lies in a zone; False where a plug-in check cannot tell (the chunk
        loop reports its fault, and has stopped the pusher)."""
        try:
            return self._inside(point)
        except ZoneCheckError:
            return False

    def _clear(self, point: np.ndarray) -> bool:
        """Whether `point` is known to lie outside every zone."""
        try:
            return not self._inside(point)
        except ZoneCheckError:
            return False

    def _inside(self, point: np.ndarray) -> bool:
        area = self.zones.area_at(0)
        return area is not None and bool(area.contains(torch.tensor(point[None]))[0])
