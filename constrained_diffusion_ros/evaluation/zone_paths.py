"""How a scenario's zones move: along waypoints at a speed, pausing at each, and, like a hand
reaching for the pusher, homing on it for a while before withdrawing.

A path is an offset (px) from where the zones are drawn, at control step `step`. Homing
depends on each episode's pusher, so `ZoneMover` keeps one offset per episode and is told the
pushers step by step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from constrained_diffusion_ros.pusht import PUSHT_ROBOT

MOTION_KEYS = {"path", "speed", "speeds", "pauses", "home_s", "offset", "steps"}


@dataclass(frozen=True)
class ZonePath:
    """Offsets (px) of a scenario's zones over time: from `waypoints[0]` along the waypoints
    at `speed` px/s, `pauses[i]` s at waypoint i (the first: before setting off); then, for
    `home_s` s, straight for the pusher at `speed` (the zones' centroid heads for it), and back
    to the last waypoint at `speed`, where they stay."""

    waypoints: np.ndarray  # (W, 2)
    speed: float
    pauses: tuple[float, ...]
    home_s: float = 0.0

    def __post_init__(self) -> None:
        if self.waypoints.ndim != 2 or self.waypoints.shape[1] != 2 or not len(self.waypoints):
            raise ValueError("path must be a list of [dx, dy] offsets")
        if not np.all(np.isfinite(self.waypoints)):
            raise ValueError("path offsets must be finite")
        if not (np.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"speed must be a positive number of px/s, got {self.speed}")
        if len(self.pauses) != len(self.waypoints) or \
                not all(np.isfinite(p) and p >= 0 for p in self.pauses):
            raise ValueError("pauses must give one time >= 0 (s) per waypoint")
        if not (np.isfinite(self.home_s) and self.home_s >= 0):
            raise ValueError(f"home_s must be >= 0 s, got {self.home_s}")

    @classmethod
    def from_spec(cls, spec: object, speed: float | None = None) -> ZonePath:
        """A scenario's `motion` entry (`speed` overrides its own, for its `speeds` variants);
        the linear form {offset, steps} moves by `offset` over `steps` control steps."""
        if not isinstance(spec, dict) or set(spec) - MOTION_KEYS:
            raise ValueError(f"motion is a mapping of {sorted(MOTION_KEYS)}")
        if "offset" in spec:
            offset = np.asarray(spec["offset"], dtype=float)
            steps = int(spec.get("steps", 1))
            if offset.shape != (2,) or steps < 1:
                raise ValueError("motion offset is [dx, dy] and steps a count >= 1")
            length = float(np.linalg.norm(offset))
            return cls(np.array([[0.0, 0.0], offset]),
                       speed or max(length, 1e-9) * PUSHT_ROBOT.control_hz / steps, (0.0, 0.0))
        waypoints = np.asarray(spec.get("path", [[0.0, 0.0]]), dtype=float)
        pauses = tuple(float(p) for p in spec.get("pauses", [0.0] * len(waypoints)))
        return cls(waypoints, float(speed if speed is not None else spec.get("speed", 0.0)),
                   pauses, float(spec.get("home_s", 0.0)))

    @property
    def homes(self) -> bool:
        return self.home_s > 0

    def _knots(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) times and (K, 2) offsets where the path starts or stops moving."""
        times, points, now = [], [], 0.0
        for i, (point, pause) in enumerate(zip(self.waypoints, self.pauses)):
            if i:
                now += float(np.linalg.norm(point - self.waypoints[i - 1])) / self.speed
            times.append(now)
            points.append(point)
            now += pause
            times.append(now)
            points.append(point)
        return np.asarray(times), np.asarray(points)

    @property
    def path_s(self) -> float:
        """s until the path's last waypoint (and its pause) is done."""
        return float(self._knots()[0][-1])

    def offset_at(self, seconds: float) -> np.ndarray:
        """(2,) the offset along the path at `seconds` (homing aside)."""
        times, points = self._knots()
        return np.array([np.interp(seconds, times, points[:, 0]),
                         np.interp(seconds, times, points[:, 1])])


class ZoneMover:
    """The offsets of one scenario's zones for a batch of episodes, step by step: call `at`
    with steps in order (a repeated step answers the same)."""

    def __init__(self, path: ZonePath, centroid: np.ndarray, episodes: int) -> None:
        self.path, self.centroid = path, np.asarray(centroid, dtype=float)
        self.step = -1
        self.offsets = np.tile(path.offset_at(0.0), (episodes, 1))

    def at(self, step: int, pusher: np.ndarray | None = None) -> np.ndarray:
        """(E, 2) offsets at control step `step`; homing needs `pusher` (E, 2) then."""
        if step == self.step:
            return self.offsets
        dt = 1.0 / PUSHT_ROBOT.control_hz
        seconds, path = step * dt, self.path
        if not path.homes or seconds <= path.path_s or step < self.step:
            self.offsets = np.tile(path.offset_at(seconds), (len(self.offsets), 1))
        else:
            homing = seconds <= path.path_s + path.home_s
            if homing and pusher is None:
                raise ValueError("a homing zone needs the pushers' positions")
            target = (np.asarray(pusher, dtype=float) - self.centroid if homing
                      else np.tile(path.waypoints[-1], (len(self.offsets), 1)))
            gap = target - self.offsets
            distance = np.linalg.norm(gap, axis=-1, keepdims=True)
            travel = path.speed * dt * max(1, step - self.step)
            self.offsets = self.offsets + gap * np.minimum(1.0, travel / np.maximum(distance,
                                                                                    1e-9))
        self.step = step
        return self.offsets
