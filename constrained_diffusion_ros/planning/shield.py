"""A last check on each executed setpoint: will the pusher's body stay out of the zones on its
way there?

Commanded setpoints outside the inflated zones are not enough: the pusher follows a PD law,
carries its velocity into the next setpoint and cuts corners, so its disc can dip into a zone
between setpoints. The pusher is kinematic, so its path is known exactly from its position,
velocity and setpoint (`RobotModel.transition`). The shield accepts a setpoint only if
holding it from now on keeps the pusher centre outside the area inflated by its radius (over a
horizon, and at the setpoint itself, where the pusher comes to rest); else it takes the safe
candidate nearest to it (`slide`, the default): the minimal change, as a control-barrier-function
filter makes it, so where the straight step is blocked the motion along the zone's boundary is
kept and the pusher slides around a small zone instead of parking in front of it. The
candidates are the steps along the blocked line, points around the wanted setpoint, that
setpoint moved just out of the grown zone, and braking points (where the pusher is, and back
along its velocity). Where even the nearest safe one brings the pusher
no nearer (a zone squarely across its way, where the minimal change is to stay), it follows
the zone's boundary: the safe point around it heading most nearly where it is sent. A
real-time node's setpoint may reach the robot after its tick, so the one in force runs a step
longer: a candidate must be safe taking over now or one step later (`late`), after a step of
any setpoint that may be in force then (a node that answers one observation again, as plans
or zones arrive, cannot know which of its answers the robot's tick met); where none is, safe
late after those some candidate can be safe after, else after the newest, else on time only.
With `slide=False` it takes the largest safe step along the line instead, as the filter before
did (it stops the pusher where the line grazes a zone).
The last accepted setpoint was itself checked from the previous state and is a candidate, so a
safe choice exists as long as the zones do not change under the pusher (a shield in the sense
of safe reinforcement learning).

A zone that moves (`zones.motion.MovingZones`) is checked as it may be when the pusher gets to
each point of a path: grown by its assumed speed times its age and the time to that point, up
to the robot's reaction time (ISO/TS 15066's separation). The candidates then also hold
retreats, points around the pusher at one and two such reaches, so that the pusher gives way
early instead of waiting at the zone's edge; where none is safe (a wall behind it, zones all
round) it is `cornered`, takes the candidate kept farthest from what the zones may reach, and
says so (docs/moving_zones.md).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.geometry import BUFFER_SAG
from constrained_diffusion_ros.zones.motion import MovingZones

# Fractions of the way from the last accepted setpoint to the planned one, tried largest first.
FRACTIONS = (0.75, 0.5, 0.25, 0.0)  # after the whole way (1.0) was refused
# Control steps between two observations over which the velocity is still estimated; after a
# longer gap the pusher has come to rest at its setpoint for all a shield can tell.
MAX_GAP_STEPS = 10
SENT_KEPT = 8  # setpoints remembered per observation (a real-time node may send several)
# Sliding: points around the wanted setpoint, at these fractions of the blocked step's length
# in each of DIRECTIONS directions, besides the steps along the line and the way out.
RING_FRACTIONS = (0.125, 0.25, 0.5, 0.75, 1.0)
DIRECTIONS = 16
# Where the nearest safe setpoint brings the pusher less than STALL_PX nearer a wanted one at
# least 4 STALL_PX away (a zone squarely in its way), it follows the zone's boundary instead:
# the safe point around the setpoint in force, at most FOLLOW_PX away, that heads most nearly
# toward the wanted setpoint, ties going the way it already moves.
STALL_PX = 1.0
FOLLOW_PX = 40.0
# Braking: the pusher's position, now and after a step late, and points back along its velocity
# by these times (s), where it comes to rest soonest: a zone dropped in its way can leave no
# setpoint nearer the wanted one safe.
BRAKE_S = (0.0, 0.1, 0.2)
CHUNK = 16  # candidates checked at once, best first, until one is safe
SPARSE = 6  # a quick refusal first looks at every SPARSE-th substep of a path
FEW = 2  # candidates that passed it, checked whole at once, in order
# Retreats from a moving zone: points around the pusher at these multiples of the zone's reach
# (speed x (age + reaction)), in DIRECTIONS directions, plus RETREAT_PX.
RETREAT_REACHES = (1.0, 2.0)
RETREAT_PX = 10.0
TIE_PX = 1.0  # cornered: paths whose closest points are this near count as equally close


class Path(NamedTuple):
    """Points of a path checked against the zones: (H, 3) coefficients of (start position,
    start velocity, setpoint) per axis, and (H,) their times (s) from the start (inf: at
    rest, however long it takes)."""

    coefficients: Tensor
    seconds: Tensor


class PusherShield:
    """Filters (B, 2) setpoints for a batch of pushers; `area` is already inflated by the
    pusher radius, so a pusher centre outside it means a disc outside the zones."""

    def __init__(self, robot: RobotModel, horizon_s: float = 0.6, margin: float = 0.5,
                 escape: float = 20.0, slide: bool = True, late: bool = True) -> None:
        horizon = max(robot.substeps, round(horizon_s * robot.physics_hz))
        coefficients = robot.transition(max(horizon, MAX_GAP_STEPS * robot.substeps))
        # One control step holding the setpoint in force: where the pusher is if the chosen
        # setpoint arrives after the robot's next tick (`late`).
        self.one_step = torch.from_numpy(coefficients[robot.substeps - 1]) if late else None
        # Position after each substep, then at rest (the setpoint itself): the horizon may end
        # before a pusher far away gets there, and a setpoint is held until the next one.
        at_rest = np.array([[0.0, 0.0, 1.0]])
        path = torch.from_numpy(np.concatenate([coefficients[:horizon, 0], at_rest]))
        seconds = torch.cat([torch.arange(1, horizon + 1, dtype=torch.float64)
                             / robot.physics_hz, torch.tensor([math.inf])])
        self.path = Path(path, seconds)
        self.sparse_path = Path(torch.cat([path[SPARSE - 1:-1:SPARSE], path[-1:]]),
                                torch.cat([seconds[SPARSE - 1:-1:SPARSE], seconds[-1:]]))
        self.tick_s = 1.0 / robot.control_hz  # a late path starts a control step later
        # (2, 3) n control steps, n = 1 .. MAX_GAP_STEPS: entry n - 1
        self.control_steps = coefficients[robot.substeps - 1::robot.substeps][:MAX_GAP_STEPS]
        self.fractions = torch.tensor(FRACTIONS, dtype=torch.float64)
        self.cornered_steps = 0  # calls that left a row cornered (kept over resets: a count)
        self.reach = (path[:, 2].abs().max(), path[:, 1].abs().max())
        self.margin, self.escape, self.slide = margin, escape, slide
        x_min, y_min, x_max, y_max = robot.workspace  # where a retreat may send the pusher
        self.low = torch.tensor([x_min, y_min], dtype=torch.float64)
        self.high = torch.tensor([x_max, y_max], dtype=torch.float64)
        # The inflated area's arcs are chords, up to radius * BUFFER_SAG inside the true disc's
        # reach: the check asks that much more, so the margin holds against the true zone.
        self.clearance = margin + robot.pusher_radius * BUFFER_SAG
        angles = torch.arange(DIRECTIONS, dtype=torch.float64) * (2 * torch.pi / DIRECTIONS)
        unit = torch.stack([angles.cos(), angles.sin()], dim=-1)
        self.ring = (torch.tensor(RING_FRACTIONS, dtype=torch.float64)[:, None, None]
                     * unit[None]).reshape(-1, 2)  # (R * D, 2) offsets per px of step length
        self.reset()

    def reset(self) -> None:
        # step, position, the setpoints sent since that observation (latest last), velocity
        # estimated at that step
        self.last: tuple[int, np.ndarray, list[np.ndarray], np.ndarray] | None = None
        self.in_force: np.ndarray | None = None  # the setpoint in force at that observation
        self.corrected = 0  # setpoints changed since the reset
        # Rows of the last call that a moving zone left no safe setpoint (no free space to
        # retreat into): the one kept farthest from the zones was taken instead.
        self.cornered = np.zeros(0, dtype=bool)

    def estimate(self, position: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(velocity (B, 2), setpoints that may be in force (K, B, 2), newest last) at the
        observation of control step `step`.

        The velocity comes from the last two observed positions and the setpoint held between
        them, over the actual number of control steps between them (the PD law is linear: per
        axis one equation, one unknown, the earlier velocity). A second call for the same
        observation (a real-time controller ticking again before the next observation) reuses
        that estimate and holds the setpoint sent last. Which setpoint a robot executed is not
        always the last one sent: a real-time node that sends again (a zone arrived) may do so
        after the robot's tick, and a late setpoint leaves the one in force before running.
        Over one step each of those is tried, and the one whose implied earlier velocity
        agrees with the velocity estimated then is taken (a wrong one is off by about 10 px/s
        per px of setpoint). In force from a new observation on is the setpoint sent last for
        the one before; on a second call for the same observation, whichever of those sent
        since reached the robot before its tick: the one in force then, or any sent for this
        observation. Without a usable earlier observation (a new episode: the simulator resets
        with the pusher at rest) the pusher is taken at rest, holding its position."""
        if self.last is None or len(self.last[1]) != len(position):
            return np.zeros_like(position), position[None]
        last_step, last_position, sent, last_velocity = self.last
        gap = step - last_step
        if gap == 0:
            return last_velocity, distinct([self.in_force, *sent])
        if not 0 < gap <= len(self.control_steps):
            return np.zeros_like(position), position[None]
        (p_p, p_v, p_u), (v_p, v_v, v_u) = self.control_steps[gap - 1]
        # (K, B, 2) candidates; over one step also the setpoint in force before, which the
        # robot kept if everything sent for that observation arrived after its tick.
        kept = [self.in_force] if self.in_force is not None and \
            self.in_force.shape == position.shape else []
        executed = np.stack([*kept, *sent] if gap == 1 else sent[-1:])
        before = (position - p_p * last_position - p_u * executed) / p_v
        best = np.linalg.norm(before - last_velocity, axis=-1).argmin(axis=0)  # (B,)
        rows = np.arange(len(position))
        before, executed = before[best, rows], executed[best, rows]
        return v_p * last_position + v_v * before + v_u * executed, sent[-1][None]

    def __call__(self, area: RestrictedArea | None, position: np.ndarray, setpoint: np.ndarray,
                 step: int) -> np.ndarray:
        """The setpoints to execute from the observation of control step `step` (steps may
        repeat or skip, as a real-time clock meets the observations); with no area they pass
        unchanged, but the history is kept."""
        position, setpoint = np.asarray(position, float), np.asarray(setpoint, float)
        velocity, held = self.estimate(position, step)
        self.cornered = np.zeros(len(position), dtype=bool)
        if area is None:
            self._remember(step, position, setpoint, velocity, held[-1])
            return setpoint
        p, v = torch.from_numpy(position), torch.from_numpy(velocity)
        # (B, K, 2) the setpoints that may be in force, newest last
        start, goal = torch.from_numpy(held).transpose(0, 1), torch.from_numpy(setpoint)
        # (a moving zone: as far as it may come)
        near = torch.nonzero(area.signed_distance_after(p.float(), math.inf)
                             < self._reach(p, v, start, goal) + self.clearance).flatten()
        chosen = goal.clone()
        if len(near):
            chosen[near], cornered = self._choose(area.select_rows(near), p[near], v[near],
                                                  start[near], goal[near])
            self.cornered[near.numpy()] = cornered.numpy()
            self.cornered_steps += int(cornered.sum())
        result = chosen.numpy()
        self.corrected += int((chosen != goal).any(dim=-1).sum())
        self._remember(step, position, result, velocity, held[-1])
        return result

    def _reach(self, p: Tensor, v: Tensor, held: Tensor, goal: Tensor) -> Tensor:
        """(B,) how far from p the paths toward `goal` can go: only pushers that could reach
        the area need their paths checked. A path leaves its start p by at most
        c_max |u - p| + b_max |v| (p_k - p = c_k (u - p) + b_k v); a late one starts where a
        step of a setpoint in `held` (B, K, 2) took it, so its bound adds that step."""
        reach = self.reach[0] * (goal - p).norm(dim=-1) + self.reach[1] * v.norm(dim=-1)
        if self.one_step is None:
            return reach
        late_p, late_v = self._step_late(p, v, held)
        late = ((late_p - p[:, None]).norm(dim=-1)
                + self.reach[0] * (goal[:, None] - late_p).norm(dim=-1)
                + self.reach[1] * late_v.norm(dim=-1)).amax(dim=1)
        return torch.maximum(reach, late)

    def _step_late(self, p: Tensor, v: Tensor, held: Tensor) -> tuple[Tensor, Tensor]:
        """(N, K, 2) positions and velocities of pushers at p moving at v (N, 2) after one
        control step holding each setpoint of `held` (N, K, 2): where a late setpoint takes
        over."""
        (p_p, p_v, p_u), (v_p, v_v, v_u) = self.one_step
        return (p_p * p[:, None] + p_v * v[:, None] + p_u * held,
                v_p * p[:, None] + v_v * v[:, None] + v_u * held)

    def _remember(self, step: int, position: np.ndarray, setpoint: np.ndarray,
                  velocity: np.ndarray, held: np.ndarray) -> None:
        """The observation and the setpoint sent for it, after those already sent for it."""
        if self.last is not None and self.last[0] == step and \
                self.last[2][-1].shape == setpoint.shape:
            self.last = (step, position, [*self.last[2][-(SENT_KEPT - 1):], setpoint], velocity)
        else:  # a new observation
            self.last, self.in_force = (step, position, [setpoint], velocity), held

    def _safe(self, area: RestrictedArea, p: Tensor, v: Tensor, candidates: Tensor,
              held: Tensor | None = None, path: Path | None = None) -> Tensor:
        """(N, F) whether holding candidate (N, F, 2) keeps a pusher at p moving at v clear of
        the area: after every physics substep of the horizon, and at the candidate itself
        (or at the points of `path`, a subset of them: a quick test that can only refuse).
        With `held` (N, K, 2) (or (N, 2)), the setpoints that may be in force, and `late`,
        also if the candidate takes over one control step later (it reached the robot after
        its tick), after a step of each of them. A moving zone is checked as it may be when
        the pusher gets to each point (`RestrictedArea.signed_distance_after`)."""
        return self._margin(area, p, v, candidates, held, path) >= 0

    def _margin(self, area: RestrictedArea, p: Tensor, v: Tensor, candidates: Tensor,
                held: Tensor | None = None, path: Path | None = None) -> Tensor:
        """(N, F) the least clearance beyond the required one along each candidate's paths
        (`_safe`): negative where it is not safe."""
        return self._margins(area, p, v, candidates, held, path)[0]

    def _margins(self, area: RestrictedArea, p: Tensor, v: Tensor, candidates: Tensor,
                 held: Tensor | None = None, path: Path | None = None,
                 after_s: tuple[float, ...] = (0.0,), per_start: bool = False) -> Tensor:
        """(A, N, F) `_margin` over the points of the paths `after_s[a]` or more from now, for
        each of `after_s` (the distances taken once); `per_start`: (A, N, F, 1 + K), the path
        taking over now, then after a step of each of `held` (N, K, 2), apart."""
        coefficients, seconds = self.path if path is None else path
        a, b, c = coefficients.unbind(-1)
        starts = [0.0]
        if held is not None and self.one_step is not None:
            late_p, late_v = self._step_late(p, v, held[:, None] if held.dim() == 2 else held)
            p, v = (torch.cat([p[:, None], late_p], dim=1),
                    torch.cat([v[:, None], late_v], dim=1))  # (N, 1 + K starts, 2)
            starts += [self.tick_s] * late_p.shape[1]
        else:
            p, v = p[:, None], v[:, None]
        paths = (a[:, None] * p[:, None, :, None] + b[:, None] * v[:, None, :, None]
                 + c[:, None] * candidates[:, :, None, None])  # (N, F, starts, H, 2)
        count, n_candidates = paths.shape[:2]
        paths = paths.reshape(count, -1, 2).float()
        # (1, F * starts * H): when the pusher is at each point, from now
        when = (torch.tensor(starts, dtype=torch.float64)[:, None] + seconds[None])
        when = when.expand(n_candidates, *when.shape).reshape(1, -1)
        clearance = area.near(paths, self.clearance).signed_distance_after(paths, when)
        shape = (count, n_candidates, len(starts), -1) if per_start else (count, n_candidates, -1)
        return torch.stack([
            torch.where(when >= after, clearance, torch.inf).reshape(shape).amin(dim=-1)
            for after in after_s]) - self.clearance

    def _choose(self, area: RestrictedArea, p: Tensor, v: Tensor, held: Tensor,
                goal: Tensor) -> tuple[Tensor, Tensor]:
        """A safe setpoint near `goal` for pushers at p moving at v, one of `held` (N, K, 2)
        in force, the newest last; and (N,) the rows a moving zone left none safe
        (cornered)."""
        chosen = goal.clone()
        cornered = torch.zeros(len(goal), dtype=torch.bool)
        blocked = torch.nonzero(~self._safe(area, p, v, goal[:, None], held)[:, 0]).flatten()
        if len(blocked) == 0:
            return chosen, cornered
        area, p, v = area.select_rows(blocked), p[blocked], v[blocked]
        held, goal = held[blocked], goal[blocked]
        start = held[:, -1]
        rows = torch.arange(len(blocked))
        candidates = start[:, None] + self.fractions[None, :, None] * (goal - start)[:, None]
        if self.slide:  # the safe candidate nearest to the wanted setpoint: the minimal change
            step = (goal - start).norm(dim=-1).clamp_min(1.0)
            around = goal[:, None] + step[:, None, None] * self.ring[None]
            out = area.project_out(goal.float(), 2 * self.margin).double()[:, None]
            ring = slice(candidates.shape[1] + 1, candidates.shape[1] + 1 + around.shape[1])
            candidates = torch.cat([candidates, out, around, self._brakes(p, v, start),
                                    *self._retreats(area, p, goal)], dim=1)
            distance = (candidates - goal[:, None]).norm(dim=-1)
            order = distance.argsort(dim=1, stable=True)
            pick = self._first_safe(area, p, v, held, candidates, order)
            if (pick < 0).any() and self.one_step is not None:
                again = torch.nonzero(pick < 0).flatten()
                pick[again] = self._late_fallback(area.select_rows(again), p[again], v[again],
                                                  held[again], candidates[again], order[again])
            stuck = pick < 0
            fallback = candidates[rows, pick.clamp_min(0)]
            wanted = (goal - start).norm(dim=-1)
            stalled = ~stuck & (wanted - distance[rows, pick.clamp_min(0)] < STALL_PX) \
                & (wanted >= 4 * STALL_PX)
            if stalled.any():
                follow = self._follow(area, p, v, held, goal, stalled)
                fallback[stalled] = torch.where(follow.isnan(), fallback[stalled], follow)
        else:  # the largest safe step along the line
            ring = slice(0, 0)
            safe = self._safe(area, p, v, candidates, held)
            stuck = ~safe.any(dim=1)
            fallback = candidates[rows, safe.float().argmax(dim=1)]
        # No safe candidate (it started inside, or a zone moved onto it): head for the nearest
        # point `escape` px clear, so a zone still coming does not catch it at once. Cornered
        # by a moving zone (no free space to retreat into): the way out whose whole path keeps
        # farthest from what the zones may reach (`_farthest`).
        if stuck.any():  # the area may be batch-aware (row b, zones b): query every row
            escape = area.project_out(p.float(), self.escape).double()
            fallback = torch.where(stuck[:, None], escape, fallback)
            if isinstance(area, MovingZones):
                # Cornered by a moving zone: one that can reach the pusher's paths (a pusher
                # stuck at a zone that stands still, moving ones far off, takes the escape).
                reach = area.reach() + self._reach(p, v, held, goal) + self.clearance
                trapped = torch.nonzero(stuck & (area.reach() > 0) & (
                    area.moving_distance(p.float()).double() < reach)).flatten()
                if len(trapped):
                    # Ways out rather than points around the wanted setpoint (the ring left
                    # out): fewer paths to check, on the executor's time while a hand closes in.
                    ways_out = torch.cat([candidates[:, :ring.start], candidates[:, ring.stop:],
                                          escape[:, None]], dim=1)[trapped]
                    ways_out = torch.maximum(torch.minimum(ways_out, self.high), self.low)
                    farthest = self._farthest(area.select_rows(trapped), p[trapped],
                                              v[trapped], ways_out)
                    fallback[trapped] = ways_out[torch.arange(len(trapped)), farthest]
                    cornered[blocked[trapped]] = True
        chosen[blocked] = fallback
        return chosen, cornered

    def _farthest(self, area: RestrictedArea, p: Tensor, v: Tensor, candidates: Tensor
                  ) -> Tensor:
        """(N,) for cornered pushers, the candidate (N, F, 2) whose path keeps farthest from
        what the zones may reach all along it: its closest point decides, so no path runs
        past a zone to a retreat beyond it (the pusher covers a hundred px and more within a
        control step). Where that ties (within TIE_PX: a zone already so close that every
        path's first points decide), the one kept farthest after the first control step. A
        path into a zone that stands still (or a wall) is taken only where every one is: what a
        hand may reach is an assumption, a still zone is not, and a pusher kept far from a
        hand's reach by running into one breaks the guarantee the still zone has."""
        whole, later = self._margins(area, p, v, candidates, after_s=(0.0, self.tick_s))
        if isinstance(area, MovingZones):
            clear = self._margin(area.still, p, v, candidates) >= 0
            whole = torch.where(clear | ~clear.any(dim=1, keepdim=True), whole, -torch.inf)
        tied = whole >= whole.amax(dim=1, keepdim=True) - TIE_PX
        return torch.where(tied, later, -torch.inf).argmax(dim=1)

    def _retreats(self, area: RestrictedArea, p: Tensor, goal: Tensor) -> list[Tensor]:
        """[(N, R, 2)] points to retreat to from moving zones, around the pusher at multiples
        of how far they may come (`MovingZones.reach`); none for zones that stand still. A
        row whose zones stand still gets copies of its goal (refused already)."""
        if not isinstance(area, MovingZones):
            return []
        reach = area.reach().expand(len(p)).double()  # (N,)
        radii = reach[:, None] * torch.tensor(RETREAT_REACHES, dtype=torch.float64) + RETREAT_PX
        unit = self.ring[-DIRECTIONS:]  # the ring's outer circle: unit directions
        points = p[:, None, None] + radii[:, :, None, None] * unit[None, None]
        points = torch.maximum(torch.minimum(points.reshape(len(p), -1, 2), self.high), self.low)
        return [torch.where((reach > 0)[:, None, None], points, goal[:, None])]

    def _brakes(self, p: Tensor, v: Tensor, start: Tensor) -> Tensor:
        """(N, 2 len(BRAKE_S), 2) braking setpoints, from the state now and from the state a
        step late holding `start`."""
        brake = torch.tensor(BRAKE_S, dtype=torch.float64)[None, :, None]
        states = [(p, v)]
        if self.one_step is not None:
            late_p, late_v = self._step_late(p, v, start[:, None])
            states.append((late_p[:, 0], late_v[:, 0]))
        return torch.cat([position[:, None] - brake * velocity[:, None]
                          for position, velocity in states], dim=1)

    def _first_safe(self, area: RestrictedArea, p: Tensor, v: Tensor, held: Tensor | None,
                    candidates: Tensor, order: Tensor) -> Tensor:
        """(N,) per row, the index of the first safe candidate (N, F, 2) in `order` (N, F), or
        -1 (`held` (N, K, 2): the setpoints that may be in force, for the late check; None: on
        time only). Checked
        CHUNK candidates at a time, best first, rows that found one dropping out: the same
        answer as checking all, at a fraction of the cost where a good one is safe."""
        found = torch.full((len(order),), -1, dtype=torch.long)
        pending = torch.arange(len(order))
        for low in range(0, order.shape[1], CHUNK):
            if len(pending) == 0:
                break
            index = order[pending, low:low + CHUNK]  # (P, C)
            subset, some = area.select_rows(pending), (p[pending], v[pending])
            chunk = candidates[pending[:, None], index]  # (P, C, 2)
            # Every SPARSE-th point first: a candidate refused there is refused; the rest,
            # moved to the front in their order, get the whole check.
            in_force = None if held is None else held[pending]
            passed = self._safe(subset, *some, chunk, in_force, self.sparse_path)
            survivors = passed.sum(dim=1).max()
            if survivors == 0:
                continue
            front = torch.argsort((~passed).to(torch.uint8), dim=1, stable=True)[:, :survivors]
            # The survivors, in order, a few at a time: the first of them is mostly safe.
            open_rows = torch.arange(len(pending))
            for at in range(0, int(survivors), FEW):
                lines = open_rows[:, None]
                tried = front[open_rows, at:at + FEW]  # (O, FEW) positions in the chunk
                safe = self._safe(subset.select_rows(open_rows), some[0][open_rows],
                                  some[1][open_rows], chunk[lines, tried],
                                  None if in_force is None else in_force[open_rows]) \
                    & passed[lines, tried]
                hit = safe.any(dim=1)
                first = tried[torch.arange(len(open_rows)), safe.float().argmax(dim=1)]
                found[pending[open_rows[hit]]] = index[open_rows[hit], first[hit]]
                open_rows = open_rows[~hit]
                if len(open_rows) == 0:
                    break
            pending = pending[found[pending] < 0]
        return found

    def _late_fallback(self, area: RestrictedArea, p: Tensor, v: Tensor, held: Tensor,
                       candidates: Tensor, order: Tensor) -> Tensor:
        """(N,) `_first_safe` for rows where no candidate is safe a step late after every one
        of `held` (N, K, 2) (one sent just before a zone came, into it): a setpoint after which
        no candidate is safe is one no choice now can help, and is left out; the choice is
        then safe late after all the others, else after the newest of them (the robot takes
        the newest that reached it), else on time only, rather than an unchecked escape. Lost
        is judged on the quick check, which can only refuse: a setpoint it keeps that no
        candidate is safe after only costs the step to the newest."""
        rows, count = len(held), held.shape[1]
        quick = self._margins(area, p, v, candidates, held, self.sparse_path,
                              per_start=True)[0] >= 0  # (N, F, 1 + K)
        lost = ~(quick[..., 1:] & quick[..., :1]).any(dim=1)  # (N, K)
        newest_kept = torch.where(lost, -1, torch.arange(count)).amax(dim=1).clamp_min(0)
        newest = held[torch.arange(rows), newest_kept][:, None]
        # A lost one is replaced by the newest kept (a duplicate changes no check).
        kept = torch.where(lost[..., None], newest, held)
        pick = torch.full((rows,), -1, dtype=torch.long)
        for in_force in ([kept] if lost.any() else []) + [newest, None]:
            again = torch.nonzero(pick < 0).flatten()
            if len(again) == 0:
                break
            pick[again] = self._first_safe(area.select_rows(again), p[again], v[again],
                                           None if in_force is None else in_force[again],
                                           candidates[again], order[again])
        return pick

    def _follow(self, area: RestrictedArea, p: Tensor, v: Tensor, held: Tensor, goal: Tensor,
                rows: Tensor) -> Tensor:
        """(S, 2) for the stalled `rows` (bool): the safe point around the newest of `held`
        (N, K, 2), at most
        FOLLOW_PX away, whose direction is nearest the wanted one, the way the pusher moves
        breaking ties, the farthest of those; NaN where none is safe."""
        selected = torch.nonzero(rows).flatten()
        area, p, v, held, goal = area.select_rows(selected), p[rows], v[rows], held[rows], \
            goal[rows]
        start = held[:, -1]
        step = (goal - start).norm(dim=-1).clamp_max(FOLLOW_PX)
        candidates = start[:, None] + step[:, None, None] * self.ring[None]
        wanted = torch.nn.functional.normalize(goal - start, dim=-1)
        moving = torch.nn.functional.normalize(v, dim=-1)  # zero at rest
        unit = torch.nn.functional.normalize(self.ring, dim=-1)
        score = (unit @ wanted.T + 0.25 * unit @ moving.T).T + 1e-3 * self.ring.norm(dim=-1)
        best = self._first_safe(area, p, v, held, candidates,
                                score.argsort(dim=1, descending=True, stable=True))
        chosen = candidates[torch.arange(len(best)), best.clamp_min(0)]
        return torch.where((best >= 0)[:, None], chosen, torch.nan)


def distinct(setpoints: list[np.ndarray]) -> np.ndarray:
    """(K, B, 2) the (B, 2) arrays of `setpoints` without repeats, in order of their last
    appearance (the newest last)."""
    kept: list[np.ndarray] = []
    for setpoint in reversed(setpoints):
        if setpoint is not None and not any(np.array_equal(setpoint, k) for k in kept):
            kept.append(setpoint)
    return np.stack(kept[::-1])
