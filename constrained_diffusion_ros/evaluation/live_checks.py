"""What a live trial checks, for the benchmarks that measure it and the acceptance test that
asserts it: where to drop a zone on the pusher's path so that the pusher can still stop
outside it (an overlap after that is the filter's fault), and whether a setpoint respects a
zone (outside it grown by the pusher's radius, as the body-safe guarantee promises)."""

from __future__ import annotations

import numpy as np
import shapely

from constrained_diffusion_ros.pusht import PUSHT_ROBOT

# The pusher's PD law over one control step: per physics substep, its (position, velocity) as
# weights of (position, velocity, setpoint) at the step's start, per axis.
ONE_STEP = PUSHT_ROBOT.transition(PUSHT_ROBOT.substeps)
# Both the distance a step covers and the velocity it ends with scale with setpoint - position.
VELOCITY_PER_PX_MOVED = ONE_STEP[-1, 1, 2] / ONE_STEP[-1, 0, 2]
CARRY = float(np.abs(ONE_STEP[:, 0, 1]).max())  # px carried on per px/s of velocity
TOLERANCE = 0.5  # px: a setpoint this close to the grown zone's boundary respects it
CLEAR_PX = 2.0  # px the disc must be able to stay clear of a zone dropped in its path


def square(centre: np.ndarray, side: float) -> np.ndarray:
    """(4, 2) the corners of a square of `side` px around `centre`."""
    half = side / 2
    return centre + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])


def zone_in_path(plan: np.ndarray, held: np.ndarray, pusher: np.ndarray, moved: np.ndarray,
                 side: float) -> np.ndarray | None:
    """A square on the waypoints about to execute, as close to the held setpoint as can be
    with the pusher still able to stop outside it even if the node's answer comes one control
    step late: its disc clear by CLEAR_PX of the path it takes in one more step toward the
    held setpoint (its PD law, from its position and the velocity its last step `moved`
    implies) plus what it then carries on by its velocity before a new setpoint can stop it.
    None: no such place on the plan."""
    ahead = np.argmin(np.linalg.norm(plan - held, axis=1))
    for index in range(ahead, len(plan)):
        centre = np.clip(plan[index], side / 2 + 2, PUSHT_ROBOT.workspace[2] - 2 - side / 2)
        if stops_outside(shapely.Polygon(square(centre, side)), pusher, moved, held):
            return square(centre, side)
    return None


def stops_outside(shape: shapely.Polygon, pusher: np.ndarray, moved: np.ndarray,
                  held: np.ndarray) -> bool:
    """Whether the pusher's disc stays CLEAR_PX clear of `shape` over one more step toward
    `held` and what it then carries on by its velocity (see `zone_in_path`)."""
    state = np.stack([pusher, VELOCITY_PER_PX_MOVED * moved, held])  # (p, v, u) per axis
    path = ONE_STEP[:, 0] @ state  # (substeps, 2)
    carried_on = CARRY * np.linalg.norm(ONE_STEP[-1, 1] @ state)
    swept = shapely.LineString(np.vstack([pusher, path]))
    return shape.distance(swept) > PUSHT_ROBOT.pusher_radius + CLEAR_PX + carried_on


def respects(shape: shapely.Polygon, point: np.ndarray) -> bool:
    """Whether a setpoint at `point` keeps the pusher's disc out of `shape` (TOLERANCE px)."""
    where = shapely.Point(*point)
    return shape.distance(where) >= PUSHT_ROBOT.pusher_radius - TOLERANCE \
        and not shape.contains(where)


def disc_depth(shape: shapely.Polygon, pusher: np.ndarray) -> float:
    """px the pusher's disc at `pusher` reaches into `shape` (negative: clear by as much)."""
    return PUSHT_ROBOT.pusher_radius - shape.distance(shapely.Point(*pusher))
