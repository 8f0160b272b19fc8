"""The PushT task's facts, apart from its physics: workspace and walls, the pusher and its PD
gains and rates, the T's geometry and keypoints, the goal, coverage and score, seeded scenes.

Everything here is plain numpy and shapely, so the renderer, the evaluation and the robot model
of the planning core can learn the scene without building a physics engine. Numbers follow the
reference environment of Chi et al., Diffusion Policy (RSS 2023).
"""

from __future__ import annotations

from functools import cache
from numbers import Integral

import numpy as np

WORKSPACE_SIZE = 512.0
AGENT_RADIUS = 15.0
AGENT_START = (256.0, 400.0)
GOAL_POSE = np.array([256.0, 256.0, np.pi / 4])
SUCCESS_THRESHOLD = 0.95
CONTROL_HZ = 10
SIM_HZ = 100
SUBSTEPS = SIM_HZ // CONTROL_HZ
K_P = 100.0  # the pusher's PD law: acceleration = K_P (target - position) - K_V velocity
K_V = 20.0

# Commanded targets and positions must lie in this box (the workspace padded by its own size
# on each side): permissive enough for any real command, but finite and physically sane.
COORD_LIMITS = (-WORKSPACE_SIZE, 2.0 * WORKSPACE_SIZE)

WALL_RADIUS = 2.0
WALLS = (
    ((5.0, 506.0), (5.0, 5.0)),
    ((5.0, 5.0), (506.0, 5.0)),
    ((506.0, 5.0), (506.0, 506.0)),
    ((5.0, 506.0), (506.0, 506.0)),
)

# The T block in body coordinates (scale 30, length 4): crossbar and stem.
TEE_BAR = np.array([(-60.0, 30.0), (60.0, 30.0), (60.0, 0.0), (-60.0, 0.0)])
TEE_STEM = np.array([(-15.0, 30.0), (-15.0, 120.0), (15.0, 120.0), (15.0, 30.0)])
# Outline of the union of the two rectangles, as one valid polygon for area computations.
TEE_OUTLINE = np.array(
    [
        (-60.0, 0.0),
        (60.0, 0.0),
        (60.0, 30.0),
        (15.0, 30.0),
        (15.0, 120.0),
        (-15.0, 120.0),
        (-15.0, 30.0),
        (-60.0, 30.0),
    ]
)

# The policy's observation: the 9 keypoints (x, y) flattened, then the pusher (x, y).
PUSHER_IN_OBSERVATION = (18, 20)

# Keypoints of the T in body coordinates, in the dataset's order (fitted to data/keypoint).
KEYPOINTS_LOCAL = np.array(
    [
        [9.269787, 90.040974],
        [-60.983472, -1.186730],
        [60.912755, -1.393363],
        [-0.270504, 25.543625],
        [-14.064927, 122.815854],
        [39.002738, 32.857404],
        [-39.966414, 32.729655],
        [-16.824344, 62.863179],
        [23.541461, -1.700288],
    ]
)


def observation(keypoints: np.ndarray, pusher: np.ndarray) -> np.ndarray:
    """(..., 9, 2) keypoints and (..., 2) pusher -> (..., 20) observations (dataset layout)."""
    keypoints, pusher = np.asarray(keypoints), np.asarray(pusher)
    return np.concatenate([keypoints.reshape(*keypoints.shape[:-2], -1), pusher], axis=-1)


def check_seed(seed: object) -> int:
    """Seeds feed numpy's legacy RandomState, which takes integers in [0, 2**32)."""
    # ValueError, not TypeError: callers handle every bad input through one exception type.
    if isinstance(seed, bool) or not isinstance(seed, Integral):
        raise ValueError(
            f"seed must be a non-negative int, got {seed!r} ({type(seed).__name__})"
        )
    if not 0 <= int(seed) < 2**32:
        raise ValueError(f"seed must be in [0, 2**32), got {seed}")
    return int(seed)


def seeded_state(seed: int) -> np.ndarray:
    """Initial state for a seed, drawn exactly as the reference environment draws it."""
    rs = np.random.RandomState(check_seed(seed))
    return np.array(
        [
            rs.randint(50, 450),
            rs.randint(50, 450),
            rs.randint(100, 400),
            rs.randint(100, 400),
            rs.randn() * 2 * np.pi - np.pi,
        ],
        dtype=np.float64,
    )


# --------------------------------------------------------------------------- geometry


def _rotation(angles: np.ndarray) -> np.ndarray:
    """(N,) angles -> (N, 2, 2) rotation matrices."""
    c, s = np.cos(angles), np.sin(angles)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _poses(block_poses: object) -> np.ndarray:
    arr = np.asarray(block_poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"block_poses must have shape (N, 3), got {arr.shape}")
    return arr


def _transform(local: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Body points (K, 2) placed at poses (N, 3) -> world points (N, K, 2)."""
    rot = _rotation(poses[:, 2])
    return np.einsum("nij,kj->nki", rot, local) + poses[:, None, :2]


def block_keypoints(block_poses: object) -> np.ndarray:
    """The 9 dataset keypoints of the T for each block pose: (N, 3) -> (N, 9, 2)."""
    return _transform(KEYPOINTS_LOCAL, _poses(block_poses))


def tee_polygons(pose: object) -> list[np.ndarray]:
    """The T's two rectangles in world coordinates for one pose (x, y, angle)."""
    p = _poses(np.reshape(np.asarray(pose, dtype=np.float64), (1, 3)))
    return [_transform(TEE_BAR, p)[0], _transform(TEE_STEM, p)[0]]


def _tee_geoms(poses: np.ndarray) -> np.ndarray:
    import shapely  # here: the commands that only read the scene's numbers start without it

    return shapely.polygons(_transform(TEE_OUTLINE, poses))


@cache
def _goal() -> tuple[object, float]:
    """The goal T's geometry and area, built at the first coverage asked for."""
    import shapely

    geom = _tee_geoms(GOAL_POSE[None])[0]
    return geom, float(shapely.area(geom))


def coverage(block_poses: object) -> np.ndarray:
    """Fraction of the goal T covered by the block T for each pose: (N, 3) -> (N,)."""
    import shapely

    goal, goal_area = _goal()
    blocks = _tee_geoms(_poses(block_poses))
    return shapely.area(shapely.intersection(blocks, goal)) / goal_area


def score_from_coverage(cov: np.ndarray) -> np.ndarray:
    """Reward as in the reference: coverage scaled so that reaching the threshold scores 1."""
    return np.clip(np.asarray(cov) / SUCCESS_THRESHOLD, 0.0, 1.0)
