"""How zones move: a velocity per zone id from its successive stamped updates, the speed a
guarantee assumes of each, and the area a shield checks against (`MovingZones`).

A moving zone is the same id republished with a new stamp (a hand a camera tracks). Its
velocity is the displacement of its centroid between two updates over the time between their
stamps, smoothed over the updates before; after a gap longer than `max_gap_s` it is measured
afresh.

What a guarantee assumes of a zone (`assumed_speed`, the zone's own bound):
- a zone no update has shown moving stands still (published once, or republished in place:
  the static guarantee);
- one seen moving may move in any direction, from then on, at up to `headroom` times the
  fastest it has been measured between two updates (at least `floor`), never more than
  `speed_bound`; with `headroom` 0, at `speed_bound` whatever it was measured at, as ISO 13855
  assumes an approach speed rather than trusting a person to keep to one.
A zone measured faster than the bound, or faster than it was assumed to move before that
update, broke the assumption: `over_bound` names the first, `exceeded` counts the second, so
it is said, not trusted.

An update that puts a zone farther than JUMP x the bound could have taken it, and JUMP_PX
besides, is not motion but a re-placement (an id reused, a tracker that lost and found its
object): the zone counts as placed anew there (`jumps`), standing still as a new zone does.
Its updates go on being taken as placements until `max_gap_s` passes without a jump: an id
that jumps is not trusted to move, so that ids scattered at random (a flood), some of whose
updates look like motion by chance, are not taken for a swarm of hands each grown by the
bound. Nothing could have kept a separation across a jump; the static guarantee holds for
each placement.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
import torch
from numpy.typing import ArrayLike
from torch import Tensor

from constrained_diffusion_ros.zones.area import AreaUnion, Bounds, RestrictedArea, Translated

# px/s: the speed assumed of a zone whose own is not measured, and the bound a measured one is
# held to. 300 px/s covers the hands the package is checked against (50 to 300 px/s: at 100 px/s
# a zone covers 10 px per control step, about a slow hand on a PushT table).
DEFAULT_SPEED_BOUND = 300.0
MIN_UPDATES = 3  # updates (two displacements) before a zone's own speed is trusted
MAX_GAP_S = 1.0  # a longer pause between updates starts the estimate afresh
SMOOTHING = 0.5  # weight of the newest displacement in the velocity
MOVED_PX = 0.5  # a centroid displaced more between two updates: the zone moves
JUMP = 3.0  # displaced faster than JUMP x the bound between two updates: re-placed, not moved
# px a displacement may exceed that by and still be motion: stamps that come close together (a
# tracker's jitter, a publisher behind on a busy machine) do not make a hand's step a jump
JUMP_PX = 30.0
# A moving zone's own bound: HEADROOM x the fastest it was measured at, at least FLOOR px/s:
# a hand that sets off again after a pause, or speeds up by half, is still covered.
HEADROOM = 1.5
FLOOR = 50.0
COVER_PX = 1.0  # how far a moving zone's outline (`cover`) may lie beyond its convex hull


def cover(polygon: shapely.Geometry, tolerance: float = COVER_PX) -> shapely.Geometry:
    """A convex outline of few vertices that covers `polygon`, within 2 x `tolerance` px of
    its convex hull: what a moving zone is checked as. It is grown by how far it may come
    anyway (tens of px), so a px is nothing to the guarantee (a concave one, a hand's outline,
    is taken as its hull: more than it covers, never less), and a few edges instead of up to
    the cap's 64 keep the checks of many moving zones within a control period. The hull is
    grown by `tolerance` and simplified by as much: a chord of a convex outline lies within
    `tolerance` of the vertices it drops, so the hull stays inside."""
    grown = shapely.convex_hull(polygon).buffer(tolerance, join_style="mitre")
    return shapely.simplify(grown, tolerance)


def assumed_speeds(moved: np.ndarray, fastest: np.ndarray, bound: float,
                   headroom: float = HEADROOM, floor: float = FLOOR) -> np.ndarray:
    """px/s a guarantee assumes of zones (one per entry): 0 for those never seen moving, else
    headroom x their fastest measured speed (at least `floor`, at most `bound`; the bound
    itself with headroom 0)."""
    own = np.minimum(bound, np.maximum(floor, headroom * np.asarray(fastest, dtype=float)))
    return np.where(np.asarray(moved), bound if headroom == 0 else own, 0.0)


@dataclass
class Track:
    """What is known of one zone's motion."""

    stamp: float  # s, of the latest update
    centroid: np.ndarray  # (2,) px
    velocity: np.ndarray  # (2,) px/s; zero until two updates
    updates: int  # updates since the estimate (re)started
    moved: bool = False  # an update has shown it displaced (it may move again at any time)
    fastest: float = 0.0  # px/s, the fastest displacement between two updates so far
    jumped_at: float = -np.inf  # s, the stamp of its latest jump


class ZoneMotion:
    """Velocities of zones by id, from `observe(id, centroid, stamp)`; `forget` a zone that
    is gone. Not thread-safe: its owner (`LiveZones`) holds its lock around it."""

    def __init__(self, speed_bound: float = DEFAULT_SPEED_BOUND, min_updates: int = MIN_UPDATES,
                 max_gap_s: float = MAX_GAP_S, headroom: float = HEADROOM) -> None:
        if not speed_bound >= 0:
            raise ValueError(f"the zone speed bound must be >= 0 px/s, got {speed_bound}")
        if not headroom >= 0:
            raise ValueError(f"the zone speed headroom must be >= 0, got {headroom}")
        self.speed_bound, self.min_updates, self.max_gap_s = speed_bound, min_updates, max_gap_s
        self.headroom = headroom
        self.tracks: dict[object, Track] = {}
        self.exceeded = 0  # updates that showed a zone faster than it was assumed to move
        self.jumps = 0  # updates that re-placed a zone (beyond JUMP x the bound)

    def observe(self, zone_id: object, centroid: ArrayLike, stamp: float) -> None:
        """A zone's update: its centroid (px) at `stamp` (s). An update no later than the last
        (a replay, or out of order) says nothing of motion and is ignored."""
        centroid = np.asarray(centroid, dtype=float)
        track = self.tracks.get(zone_id)
        if track is not None and stamp <= track.stamp:
            return
        if track is None:
            self.tracks[zone_id] = Track(stamp, centroid, np.zeros(2), 1)
            return
        displacement = float(np.linalg.norm(centroid - track.centroid))
        raw = displacement / (stamp - track.stamp)
        jumped = displacement > JUMP_PX + JUMP * self.speed_bound * (stamp - track.stamp)
        if jumped or stamp - track.jumped_at < self.max_gap_s:  # placed anew
            self.jumps += jumped
            self.tracks[zone_id] = Track(stamp, centroid, np.zeros(2), 1,
                                         jumped_at=stamp if jumped else track.jumped_at)
            return
        if track.moved and raw > self._assumed(track):
            self.exceeded += 1
        moved = track.moved or displacement > MOVED_PX
        fastest = max(track.fastest, raw) if moved else 0.0
        if stamp - track.stamp > self.max_gap_s:
            self.tracks[zone_id] = Track(stamp, centroid, np.zeros(2), 1, moved, fastest)
            return
        velocity = (centroid - track.centroid) / (stamp - track.stamp)
        if track.updates > 1:
            velocity = SMOOTHING * velocity + (1 - SMOOTHING) * track.velocity
        self.tracks[zone_id] = Track(stamp, centroid, velocity, track.updates + 1, moved,
                                     fastest)

    def forget(self, zone_id: object) -> None:
        self.tracks.pop(zone_id, None)

    def clear(self) -> None:
        self.tracks.clear()

    def measured(self, zone_id: object) -> bool:
        """Whether the zone's own speed is known (enough updates behind it)."""
        track = self.tracks.get(zone_id)
        return track is not None and track.updates >= self.min_updates

    def velocity(self, zone_id: object) -> np.ndarray:
        """(2,) px/s: the measured velocity, zero where none is measured."""
        return self.tracks[zone_id].velocity.copy() if self.measured(zone_id) else np.zeros(2)

    def speed(self, zone_id: object) -> float:
        """px/s: the zone's measured speed, 0 where none is measured yet."""
        return float(np.linalg.norm(self.velocity(zone_id)))

    def moving(self, zone_id: object) -> bool:
        """Whether an update has shown the zone displaced: it is taken to move from then on."""
        track = self.tracks.get(zone_id)
        return track is not None and track.moved

    def assumed_speed(self, zone_id: object) -> float:
        """px/s a guarantee assumes of the zone (its own bound: the module's rule); 0 for one
        never seen moving."""
        track = self.tracks.get(zone_id)
        return 0.0 if track is None else self._assumed(track)

    def _assumed(self, track: Track) -> float:
        return float(assumed_speeds(track.moved, track.fastest, self.speed_bound,
                                    self.headroom))

    def over_bound(self) -> list[object]:
        """Ids of the zones measured faster than the bound."""
        return [zone_id for zone_id in self.tracks
                if self.measured(zone_id) and self.speed(zone_id) > self.speed_bound]


class MovingZones(RestrictedArea):
    """Zones where they were last seen, some of which move: what a shield checks a path
    against (`signed_distance_after`); every other query answers for the zones as they are.

    `area` is every zone (batch-aware or one for every row), `still` the part of it that
    stands still and `moving` the part that moves (`still` and `moving` make `area`; they are
    given apart so that no distance is taken twice). A moving zone may cover, `t` s from now,
    any point within `speed * (age_s + min(t, reaction_s))` of where it was seen: `speed`
    (px/s, one or (B,) per row) the speed assumed of it, `age_s` (s, one or (B,)) since it was
    where it was seen,
    `reaction_s` the time the robot needs to react (the setpoint in force until the next one
    takes over, and the PD law's lag behind a setpoint that retreats). Past `reaction_s` the
    zone is taken no farther: a path is checked against what the zone can reach before the
    robot has reacted, its separation speed x (age + reaction), as ISO/TS 15066 sizes a
    protective separation distance; the shield checks again at every tick.

    `drift` gives moving zones one by one with their measured velocities (px/s, (2,) or
    (B, 2) per row), for the plans: `ahead` forecasts where they will be. `steady` holds the
    moving zones not in `drift` (no velocity believed of them): the plans take them where
    they are; the shield grows them like the others.

    Inflated (by a pusher's radius), the moving part is not buffered but grown by `radius` in
    its signed distance, as its motion grows it: exact outside it, and a few edges per zone
    instead of the round joins of a buffer (a flood of ids taken for moving made every shield
    call that found nothing safe check thousands of those edges, for most of a second).
    """

    def __init__(self, area: RestrictedArea, still: RestrictedArea, moving: RestrictedArea,
                 speed: Tensor | float, age_s: Tensor | float, reaction_s: float,
                 drift: Sequence[tuple[RestrictedArea, Tensor]] = (),
                 steady: RestrictedArea | None = None, radius: float = 0.0) -> None:
        self.area, self.still, self.moving, self.steady = area, still, moving, steady
        self.radius = float(radius)  # px the moving part is grown by besides its motion
        self.drift = [(part, torch.as_tensor(v, dtype=torch.float64)) for part, v in drift]
        self.reaction_s = float(reaction_s)
        self.speed = torch.as_tensor(speed, dtype=torch.float64)
        self.age_s = torch.as_tensor(age_s, dtype=torch.float64)

    def reach(self, seconds: Tensor | float = float("inf")) -> Tensor:
        """px (one, or (B,) per row): how far past where they were seen the moving zones may
        be `seconds` from now."""
        seconds = torch.as_tensor(seconds, dtype=torch.float64).clamp_max(self.reaction_s)
        return self.speed * (self.age_s + seconds)

    def ahead(self, seconds: Tensor) -> RestrictedArea:
        """The zones as they will be when each waypoint of a chunk runs, `seconds` (H,) from
        the observation: each moving zone carried on at its measured velocity (`Forecast`);
        the zones as they are where none is measured."""
        if not self.drift:
            return self.area
        age = float(self.age_s.max()) if self.age_s.numel() else 0.0
        still = self.still if self.steady is None else AreaUnion([self.still, self.steady])
        return Forecast(still, self.drift, torch.as_tensor(seconds, dtype=torch.float64) + age)

    def signed_distance(self, points: Tensor) -> Tensor:
        return self.area.signed_distance(points)

    def signed_distance_after(self, points: Tensor, seconds: Tensor | float) -> Tensor:
        now = self.still.signed_distance(points)
        seconds = torch.as_tensor(seconds, dtype=torch.float64).clamp_max(self.reaction_s)
        speed, age = self.speed, self.age_s
        if speed.dim() == 1:  # per row: (B,) against (B, ...)
            shape = (len(speed), *([1] * (now.dim() - 1)))
            speed = speed.reshape(shape)
            age = age.reshape(shape) if age.dim() == 1 else age
        grown = (speed * (age + seconds) + self.radius).to(now.dtype)
        return torch.minimum(now, self.moving.signed_distance(points) - grown)

    def moving_distance(self, points: Tensor) -> Tensor:
        """Signed distance to the moving part where it was seen (grown by `radius`)."""
        return self.moving.signed_distance(points) - self.radius

    def contains(self, points: Tensor) -> Tensor:
        return self.area.contains(points)

    def outward_direction(self, points: Tensor) -> Tensor:
        return self.area.outward_direction(points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        return self.area.project_out(points, margin)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self.area.segment_clear_fraction(starts, ends)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        def pick(value: Tensor) -> Tensor:
            return value[rows] if value.dim() == 1 else value
        return MovingZones(self.area.select_rows(rows), self.still.select_rows(rows),
                           self.moving.select_rows(rows), pick(self.speed), pick(self.age_s),
                           self.reaction_s, _drift_rows(self.drift, rows),
                           self._steady(lambda area: area.select_rows(rows)), self.radius)

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        farthest = float(self.reach().max()) if self.speed.numel() else 0.0
        return MovingZones(self.area.near(points, reach), self.still.near(points, reach),
                           self.moving.near(points, reach + farthest + self.radius), self.speed,
                           self.age_s, self.reaction_s, self.drift, self.steady, self.radius)

    def _inflated(self, radius: float) -> RestrictedArea:
        return MovingZones(self.area.inflate(radius), self.still.inflate(radius), self.moving,
                           self.speed, self.age_s, self.reaction_s,
                           [(part.inflate(radius), v) for part, v in self.drift],
                           self._steady(lambda area: area.inflate(radius)), self.radius + radius)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        return MovingZones(self.area.bounded(workspace), self.still.bounded(workspace),
                           self.moving, self.speed, self.age_s, self.reaction_s, self.drift,
                           self._steady(lambda area: area.bounded(workspace)), self.radius)

    def _steady(self, change: Callable[[RestrictedArea], RestrictedArea]
                ) -> RestrictedArea | None:
        return None if self.steady is None else change(self.steady)


def _drift_rows(drift: list[tuple[RestrictedArea, Tensor]], rows: Tensor
                ) -> list[tuple[RestrictedArea, Tensor]]:
    """The moving zones and velocities of rows `rows` (a velocity per row, or one for all)."""
    return [(part.select_rows(rows), v[rows] if v.dim() == 2 else v) for part, v in drift]


class Forecast(RestrictedArea):
    """Zones as they will be when each waypoint of a chunk runs: what the plans steer, project
    and repair against, so that a chunk goes around where a hand will be, not where it was.

    Queries are chunks (B, H, 2) (or (..., H, 2)): waypoint h is checked against the zones that
    stand still and each moving zone carried on at its velocity for `seconds[h]`. `columns`
    keeps the waypoints from one on (a path's segments), `at` gives one moment per row (for
    points of any shape). A prediction, not a bound: the shield keeps the guarantee.
    """

    def __init__(self, still: RestrictedArea, drift: Sequence[tuple[RestrictedArea, Tensor]],
                 seconds: Tensor) -> None:
        self.still, self.drift, self.seconds = still, list(drift), seconds

    def _offset(self, velocity: Tensor, points: Tensor) -> Tensor:
        """(..., H, 2) how far a zone moving at `velocity` ((2,) or (B, 2)) has come by each
        waypoint of `points` (..., H, 2)."""
        if points.dim() < 2 or points.shape[-2] != len(self.seconds):
            raise ValueError(f"a forecast answers for chunks of {len(self.seconds)} waypoints "
                             f"(..., {len(self.seconds)}, 2), got {tuple(points.shape)}")
        if velocity.dim() == 1:
            return (self.seconds[:, None] * velocity).to(points.dtype)  # (H, 2)
        shift = velocity[:, None, :] * self.seconds[None, :, None]  # per row: (B, H, 2)
        return shift.reshape(len(velocity), *([1] * (points.dim() - 3)),
                             *shift.shape[1:]).to(points.dtype)

    def signed_distance(self, points: Tensor) -> Tensor:
        points = torch.as_tensor(points)
        distance = self.still.signed_distance(points)
        for part, velocity in self.drift:
            moved = part.signed_distance(points - self._offset(velocity, points))
            distance = torch.minimum(distance, moved.to(distance.dtype))
        return distance

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        """Waypoint by waypoint, each out of the zones of its moment."""
        points = torch.as_tensor(points)
        self._offset(torch.zeros(2, dtype=torch.float64), points)  # the shape, checked
        return torch.stack([self._moment(float(t)).project_out(points[..., h, :], margin)
                            for h, t in enumerate(self.seconds)], dim=-2)

    def columns(self, start: int) -> Forecast:
        """The forecast for the waypoints from `start` on."""
        return Forecast(self.still, self.drift, self.seconds[start:])

    def at(self, column: Tensor) -> RestrictedArea:
        """Row r's zones at the moment of its waypoint `column[r]` (R,), for points (R, ..., 2)
        of any shape."""
        seconds = self.seconds[torch.as_tensor(column)]  # (R,)
        return AreaUnion([self.still] + [
            Translated(part, (v if v.dim() == 2 else v[None]) * seconds[:, None])
            for part, v in self.drift])

    def _moment(self, seconds: float) -> RestrictedArea:
        return AreaUnion([self.still] + [Translated(part, v * seconds) for part, v in self.drift])

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return Forecast(self.still.select_rows(rows), _drift_rows(self.drift, rows),
                        self.seconds)

    def _inflated(self, radius: float) -> RestrictedArea:
        return Forecast(self.still.inflate(radius),
                        [(part.inflate(radius), v) for part, v in self.drift], self.seconds)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        return Forecast(self.still.bounded(workspace), self.drift, self.seconds)
