"""What the planning core must know about the robot, in one small object.

The core (policy, sampling, zones, planning) never imports the simulator: the nodes and the
evaluation build a `RobotModel` from the PushT constants (`constrained_diffusion_ros.pusht`),
and a node for another robot builds one from its parameters.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from constrained_diffusion_ros.zones.area import Bounds

# A reported pusher may be this much farther from the last than the PD law can carry it
# (`RobotModel.reach`, an exact bound): gains, rates and positions of a real robot known to
# a tenth.
REACH_SLACK = 1.1


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

    @property
    def reaction_s(self) -> float:
        """s a moving zone has to come closer before this robot has got out of its way: the
        setpoint in force runs until the next control step, a step longer if the next one
        reaches the robot late (the shield's `late`), and the PD law then trails a setpoint
        that retreats at constant speed by kv / kp seconds of its travel."""
        return 2.0 / self.control_hz + self.kv / self.kp

    def outside(self, points: np.ndarray) -> np.ndarray:
        """Bool (...): the point (..., 2) lies outside the workspace (NaN: no point, False)."""
        x_min, y_min, x_max, y_max = self.workspace
        points = np.asarray(points)
        return ((points < (x_min, y_min)) | (points > (x_max, y_max))).any(axis=-1)

    def implausible(self, position: np.ndarray, previous: np.ndarray | None = None,
                    seconds: float = 0.0) -> str | None:
        """Why a reported pusher position cannot be this robot's (None: it can be).

        Outside the workspace by more than the pusher's radius, or farther from `previous`
        (reported `seconds` before) than the PD law can carry it (`reach`, with REACH_SLACK).
        A position refused here is a sensor fault or an attack, never a place to hold the
        pusher.
        """
        position = np.asarray(position, dtype=float)
        x_min, y_min, x_max, y_max = self.workspace
        grown = self.pusher_radius
        if not np.all(np.isfinite(position)) or np.any(position < (x_min - grown, y_min - grown)) \
                or np.any(position > (x_max + grown, y_max + grown)):
            return f"pusher reported at {np.round(position, 1).tolist()}, outside the workspace"
        if previous is None or seconds <= 0:
            return None
        reach = REACH_SLACK * self.reach(seconds)
        jump = float(np.linalg.norm(position - np.asarray(previous, dtype=float)))
        if jump > reach:
            return (f"pusher reported {jump:.0f} px from where it was {seconds:.2f} s before, "
                    f"farther than it can move ({reach:.0f} px)")
        return None

    def reach(self, seconds: float) -> float:
        """The farthest (px) the pusher can move in `seconds` (rounded up to control steps)
        under setpoints in the workspace, each held for a control step; inf if the PD law does
        not settle.

        Exact, from the PD law: per axis the position is linear in the setpoints (`transition`),
        so the move over the window is sum_b K_b s_b over every setpoint s_b so far, with
        sum_b K_b = 0 (one setpoint held for ever moves nothing). Taken about the workspace's
        centre, |move| <= R sum_b |K_b| with R the half-diagonal: attained by setpoints at
        opposite corners in the signs of K_b (one step: at rest in a corner, the other one
        commanded for two steps), and covering every start at rest in the workspace (a
        setpoint held there for ever). Its limit: setpoints outside the workspace (the
        simulator takes them up to a workspace beyond its edges) can carry the pusher farther;
        a node that commands such setpoints gets its pusher refused.
        """
        x_min, y_min, x_max, y_max = self.workspace
        steps = max(1, math.ceil(seconds * self.control_hz - 1e-6))
        return float(np.hypot(x_max - x_min, y_max - y_min)) / 2 * _move_gain(self, steps)

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


@functools.lru_cache(maxsize=256)
def _move_gain(robot: RobotModel, steps: int) -> float:
    """sum_b |K_b| of `RobotModel.reach` for a window of `steps` control steps (taken once per
    robot and window: the node asks at every observation)."""
    one = robot.transition(robot.substeps)[-1]
    settle, drive = one[:, :2], one[:, 2]  # one control step: state <- state, setpoint
    if np.max(np.abs(np.linalg.eigvals(settle))) >= 1.0:
        return math.inf
    total, power = 0.0, np.eye(2)
    for _ in range(steps):  # the window's setpoints, newest first
        total += abs(float((power @ drive)[0]))
        power = settle @ power
        if np.abs(power).max() < 1e-15:
            break
    before = (power - np.eye(2))[0]  # what the state at the window's start adds
    power = np.eye(2)
    while np.abs(power).max() >= 1e-15:  # the setpoints before the window, newest first
        total += abs(float(before @ power @ drive))
        power = settle @ power
    return total
