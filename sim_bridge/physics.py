"""ROS-free PushT physics (pymunk) that reproduces the Diffusion Policy PushT environment.

The physics mirrors the reference environment closely enough that replaying the recorded
demonstrations reproduces their states; the quirks kept for that reason are commented. The
scene's facts (geometry, goal, score) live in `sim_bridge.scene`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from numbers import Integral

import numpy as np
import pymunk

from sim_bridge.scene import (
    AGENT_RADIUS,
    AGENT_START,
    COORD_LIMITS,
    K_P,
    K_V,
    SIM_HZ,
    SUBSTEPS,
    SUCCESS_THRESHOLD,
    TEE_BAR,
    TEE_STEM,
    WALL_RADIUS,
    WALLS,
    WORKSPACE_SIZE,
    block_keypoints,
    coverage,
    observation,
    score_from_coverage,
    seeded_state,
)

DT = 1.0 / SIM_HZ
TEE_MASS = 1.0

# Shape friction 0: the reference's `body.friction = 1` has no effect in pymunk, and replaying the
# dataset matches with 0 (median block error 3e-5 px) but not with 1 (median 27 px).
SHAPE_FRICTION = 0.0


# --------------------------------------------------------------------------- validation


def _to_float(value: object, name: str) -> np.ndarray:
    """Numbers only: numpy would also turn True or "1" into 1.0."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers: {exc}") from None
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be an array of numbers, got {raw.dtype} values")
    return raw.astype(np.float64)


def _as_float_array(value: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    """Convert to a float64 array of an exact shape, rejecting NaN/inf."""
    arr = _to_float(value, name)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def _check_coords(coords: np.ndarray, name: str) -> None:
    lo, hi = COORD_LIMITS
    bad = (coords < lo) | (coords > hi)
    if np.any(bad):
        raise ValueError(
            f"{name} must lie within [{lo:g}, {hi:g}] (workspace is [0, {WORKSPACE_SIZE:g}]), "
            f"got {coords.tolist()}"
        )


def _check_states(states: object, n: int) -> np.ndarray:
    """Validate (n, 5) states: finite, pusher and block inside the walls."""
    arr = _as_float_array(states, (n, 5), "states")
    lo, hi = WALLS[0][1][0], WALLS[2][0][0]  # the walls' inner lines, 5 and 506
    positions = arr[:, :4]
    if np.any((positions < lo) | (positions > hi)):
        raise ValueError(f"state positions (agent x, y, block x, y) must lie inside the walls "
                         f"[{lo:g}, {hi:g}], got {positions.tolist()}")
    return arr


def _check_actions(actions: object, n: int) -> np.ndarray:
    arr = _as_float_array(actions, (n, 2), "actions" if n != 1 else "action")
    _check_coords(arr, "action")
    return arr


# --------------------------------------------------------------------------- simulator


class PushTSim:
    """One PushT scene in its own pymunk space."""

    def __init__(self) -> None:
        self._build()
        self._set_state_unchecked(np.array([*AGENT_START, 256.0, 300.0, 0.0], dtype=np.float64))

    def _build(self) -> None:
        """Create a fresh space, so the future depends only on the state that is set."""
        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        space.damping = 0.0
        for a, b in WALLS:
            space.add(pymunk.Segment(space.static_body, a, b, WALL_RADIUS))

        agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        agent.position = AGENT_START
        agent_shape = pymunk.Circle(agent, AGENT_RADIUS)
        agent_shape.friction = SHAPE_FRICTION
        space.add(agent, agent_shape)

        # The reference computes both inertias from the crossbar: kept for fidelity.
        inertia = 2.0 * pymunk.moment_for_poly(TEE_MASS, [tuple(v) for v in TEE_BAR])
        block = pymunk.Body(TEE_MASS, inertia)
        bar = pymunk.Poly(block, [tuple(v) for v in TEE_BAR])
        stem = pymunk.Poly(block, [tuple(v) for v in TEE_STEM])
        for shape in (bar, stem):
            shape.friction = SHAPE_FRICTION
        block.center_of_gravity = (bar.center_of_gravity + stem.center_of_gravity) / 2
        space.add(block, bar, stem)

        self._space, self._agent, self._block = space, agent, block

    # ---- state

    def _set_state_unchecked(self, state: np.ndarray) -> None:
        self._build()
        ax, ay, bx, by, angle = (float(v) for v in state)
        self._agent.position = (ax, ay)
        # Angle first: pymunk rotates about the centre of gravity, which is not the T's origin.
        self._block.angle = angle
        self._block.position = (bx, by)
        # The reference runs one physics step so the new state takes effect.
        self._space.step(DT)

    def set_state(self, state: object) -> None:
        """Teleport to [agent x, agent y, block x, block y, block angle], velocities zero."""
        arr = _as_float_array(state, (5,), "state")
        self._set_state_unchecked(_check_states(arr[None], 1)[0])

    def reset(self, seed: int) -> np.ndarray:
        """Start the seeded scene of the reference environment."""
        self._set_state_unchecked(seeded_state(seed))
        return self.state

    @property
    def state(self) -> np.ndarray:
        """[agent x, agent y, block x, block y, block angle mod 2pi], as the dataset records it."""
        a, b = self._agent.position, self._block.position
        return np.array([a.x, a.y, b.x, b.y, self._block.angle % (2 * math.pi)])

    @property
    def block_pose(self) -> np.ndarray:
        b = self._block.position
        return np.array([b.x, b.y, self._block.angle])

    @property
    def agent_velocity(self) -> np.ndarray:
        v = self._agent.velocity
        return np.array([v.x, v.y])

    # ---- dynamics

    def _step_unchecked(self, tx: float, ty: float) -> None:
        agent, space = self._agent, self._space
        for _ in range(SUBSTEPS):
            p, v = agent.position, agent.velocity
            # Same operation order as the reference PD controller, for bitwise replay.
            acc_x = K_P * (tx - p.x) + K_V * (0.0 - v.x)
            acc_y = K_P * (ty - p.y) + K_V * (0.0 - v.y)
            agent.velocity = (v.x + acc_x * DT, v.y + acc_y * DT)
            space.step(DT)

    def step(self, action: object) -> np.ndarray:
        """Drive the pusher towards the target (x, y) for one 10 Hz control step."""
        arr = _as_float_array(action, (2,), "action")
        _check_coords(arr, "action")
        self._step_unchecked(float(arr[0]), float(arr[1]))
        return self.state

    # ---- observations and reward

    def keypoints(self) -> np.ndarray:
        return block_keypoints(self.block_pose[None])[0]

    def observation(self) -> np.ndarray:
        """(20,): the 9 keypoints flattened, then the pusher position (dataset obs layout)."""
        p = self._agent.position
        return observation(self.keypoints(), np.array([p.x, p.y]))

    def coverage(self) -> float:
        return float(coverage(self.block_pose[None])[0])

    def score(self) -> float:
        return float(score_from_coverage(self.coverage()))

    def success(self) -> bool:
        return self.coverage() > SUCCESS_THRESHOLD

    def render(self, size: int = 512, **kwargs: object) -> np.ndarray:
        """RGB image of the scene; keyword arguments go to `render.render_scene`."""
        from sim_bridge.render import render_scene

        return render_scene(self.state, size=size, **kwargs)


class PushTBatch:
    """N independent PushT scenes stepped together, with numpy arrays in and out."""

    def __init__(self, n: int) -> None:
        if isinstance(n, bool) or not isinstance(n, Integral) or n < 1:
            raise ValueError(f"batch size must be a positive int, got {n!r}")
        self._sims = [PushTSim() for _ in range(int(n))]

    def __len__(self) -> int:
        return len(self._sims)

    def reset(self, seeds: Sequence[int] | np.ndarray) -> np.ndarray:
        seeds = list(np.asarray(seeds).reshape(-1)) if isinstance(seeds, np.ndarray) else seeds
        if len(seeds) != len(self):
            raise ValueError(f"expected {len(self)} seeds, got {len(seeds)}")
        states = np.stack([seeded_state(s) for s in seeds])  # validates every seed first
        for sim, st in zip(self._sims, states):
            sim._set_state_unchecked(st)
        return self.states

    def set_states(self, states: object) -> None:
        arr = _check_states(states, len(self))
        for sim, st in zip(self._sims, arr):
            sim._set_state_unchecked(st)

    def step(self, actions: object) -> np.ndarray:
        arr = _check_actions(actions, len(self))
        for sim, (tx, ty) in zip(self._sims, arr.tolist()):
            sim._step_unchecked(tx, ty)
        return self.states

    @property
    def states(self) -> np.ndarray:
        return np.stack([sim.state for sim in self._sims])

    @property
    def block_poses(self) -> np.ndarray:
        return np.stack([sim.block_pose for sim in self._sims])

    @property
    def agent_velocities(self) -> np.ndarray:
        return np.stack([sim.agent_velocity for sim in self._sims])

    def keypoints(self) -> np.ndarray:
        return block_keypoints(self.block_poses)

    def observations(self) -> np.ndarray:
        return observation(self.keypoints(), self.states[:, :2])

    def coverage(self) -> np.ndarray:
        return coverage(self.block_poses)

    def score(self) -> np.ndarray:
        return score_from_coverage(self.coverage())

    def success(self) -> np.ndarray:
        return self.coverage() > SUCCESS_THRESHOLD

    def render(self, i: int, size: int = 512, **kwargs: object) -> np.ndarray:
        if not -len(self) <= i < len(self):
            raise ValueError(f"scene index {i} out of range for batch of {len(self)}")
        return self._sims[i].render(size=size, **kwargs)
