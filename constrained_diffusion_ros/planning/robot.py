"""What the planning core must know about the robot, in one small object.

The core (policy, sampling, zones, planning) never imports the simulator: the nodes and the
evaluation build a `RobotModel` from the PushT constants (`constrained_diffusion_ros.pusht`),
and a node for another robot builds one from its parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from constrained_diffusion_ros.zones.area import Bounds


@dataclass(frozen=True)
class RobotModel:
    """A disc pusher driven by a PD law toward the commanded setpoint, in workspace px."""

    pusher_radius: float  # px: zones grown by it keep the pusher's body out
    workspace: Bounds  # x_min, y_min, x_max, y_max (px): outside counts as restricted
    kp: float  # PD law: acceleration = kp (setpoint - position) - kv velocity
    kv: float
    control_hz: float  # setpoints per second
    physics_hz: float  # integration steps per second (the PD law is applied at this rate)
    pusher_in_observation: tuple[int, int]  # [start, stop) of the pusher's x, y in an observation

    def __post_init__(self) -> None:
        x_min, y_min, x_max, y_max = self.workspace
        if not (x_max > x_min and y_max > y_min):
            raise ValueError(f"robot workspace must be x_min, y_min, x_max, y_max with positive "
                             f"size, got {self.workspace}")
        if self.pusher_radius < 0 or self.kp <= 0 or self.kv < 0:
            raise ValueError("robot pusher_radius and kv must be >= 0 and kp > 0")
        if not 0 < self.control_hz <= self.physics_hz:
            raise ValueError(f"robot rates need 0 < control_hz <= physics_hz, got "
                             f"{self.control_hz} and {self.physics_hz}")
        start, stop = self.pusher_in_observation
        if stop - start != 2 or start < 0:
            raise ValueError(f"pusher_in_observation must span 2 entries, got "
                             f"{self.pusher_in_observation}")

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return round(self.physics_hz / self.control_hz)

    def outside(self, points: np.ndarray) -> np.ndarray:
        """Bool (...): the point (..., 2) lies outside the workspace (NaN: no point, False)."""
        x_min, y_min, x_max, y_max = self.workspace
        points = np.asarray(points)
        return ((points < (x_min, y_min)) | (points > (x_max, y_max))).any(axis=-1)

    def implausible(self, position: np.ndarray, previous: np.ndarray | None = None,
                    seconds: float = 0.0) -> str | None:
        """Why a reported pusher position cannot be this robot's (None: it can be).

        Outside the workspace by more than the pusher's radius, or farther from `previous`
        (reported `seconds` before) than the PD law can carry it: with setpoints in the
        workspace, |setpoint - position| <= D (its diagonal), so the speed never exceeds
        kp D / kv (where the acceleration would turn against it), with a quarter's slack. A
        position refused here is a sensor fault or an attack, never a place to hold the pusher.
        """
        position = np.asarray(position, dtype=float)
        x_min, y_min, x_max, y_max = self.workspace
        grown = self.pusher_radius
        if not np.all(np.isfinite(position)) or np.any(position < (x_min - grown, y_min - grown)) \
                or np.any(position > (x_max + grown, y_max + grown)):
            return f"pusher reported at {np.round(position, 1).tolist()}, outside the workspace"
        if previous is None or seconds <= 0 or self.kv <= 0:
            return None
        diagonal = float(np.hypot(x_max - x_min, y_max - y_min))
        reach = 1.25 * self.kp * diagonal / self.kv * seconds + grown
        jump = float(np.linalg.norm(position - np.asarray(previous, dtype=float)))
        if jump > reach:
            return (f"pusher reported {jump:.0f} px from where it was {seconds:.2f} s before, "
                    f"farther than it can move ({reach:.0f} px)")
        return None

    def pusher(self, observations: np.ndarray) -> np.ndarray:
        """(..., 2) pusher positions in (..., obs_dim) observations (numpy or torch)."""
        start, stop = self.pusher_in_observation
        return observations[..., start:stop]

    def transition(self, n_substeps: int) -> np.ndarray:
        """(n_substeps, 2, 3): entry k maps one axis's (position, velocity, setpoint) to its
        (position, velocity) after k + 1 physics steps with the setpoint held.

        The pusher is kinematic: contacts never move it, so its PD law alone decides its path
        and a controller can predict it exactly (semi-implicit Euler, velocity first).
        """
        dt = 1.0 / self.physics_hz
        one = np.array([
            [1.0 - dt * dt * self.kp, dt * (1.0 - dt * self.kv), dt * dt * self.kp],
            [-dt * self.kp, 1.0 - dt * self.kv, dt * self.kp],
            [0.0, 0.0, 1.0],
        ])
        powers = [one]
        for _ in range(n_substeps - 1):
            powers.append(one @ powers[-1])
        return np.stack(powers)[:, :2]
