"""The live, id-keyed zone set a ROS node updates from messages while inference reads it."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import shapely
import torch
from numpy.typing import ArrayLike

from constrained_diffusion_ros.zones.area import AreaUnion, Bounds, RestrictedArea
from constrained_diffusion_ros.zones.geometry import ZoneSet, validate_polygon
from constrained_diffusion_ros.zones.motion import (
    DEFAULT_SPEED_BOUND,
    HEADROOM,
    MovingZones,
    ZoneMotion,
    cover,
)

ZoneId = str | int


@dataclass(frozen=True)
class _Zone:
    polygon: shapely.Geometry  # a polygon, or several where a clip split it
    vertices: np.ndarray  # (V, 2) the outline in force, for viewers
    expires_at: float  # math.inf: never
    capped: bool = True  # counts toward max_zones (a message's zone; not a mask's piece)
    stamp: float | None = None  # the message's stamp (None: unstamped)
    # time.monotonic() at which the zone was where it is: its receipt less how old it was then
    seen_at: float = 0.0


# The largest caps at which a batch of zone messages costs under one control period and a DDIM
# plan about half a chunk's execution on a two-core machine; raise them on faster machines after
# running scripts/bench_zones.py there (docs/results.md, "What zones cost, and the caps").
DEFAULT_MAX_ZONES = 32
DEFAULT_MAX_VERTICES = 64
CLEARED_KEPT = 4096  # (id, stamp) pairs of cleared zones remembered at most
# s: a stamp older than this on arrival is taken as this old (a publisher's clock far behind
# would otherwise grow a moving zone over the whole workspace)
MAX_AGE_ON_ARRIVAL_S = 1.0
# s: the robot's reaction a moving zone is grown by where the node names none (the PushT
# robot's: two control steps and the PD law's lag, `RobotModel.reaction_s`)
DEFAULT_REACTION_S = 0.4
# moving zones the plans forecast at most (`LiveZones.forecast`): two hands and room to spare
MAX_FORECAST = 4


@dataclass
class BatchOutcome:
    """What `LiveZones.apply` did with a batch of zone messages."""

    received: int = 0  # messages in the batch
    applied: int = 0  # ids whose latest message was taken (added, replaced or removed)
    stale: int = 0  # ids whose latest message had outlived its lifetime already (a replay)
    superseded: int = 0  # messages replaced by a later one for the same id in the batch
    refused: list[tuple[ZoneId, str]] = field(default_factory=list)  # (id, why)
    changed: bool = False  # the zones in force changed
    # every change was a moving zone's update that stayed within what it was assumed able to
    # reach (`LiveZones.within_reach`): setpoints checked against the zones before still hold
    within_reach: bool = False


# (id, vertices) or (id, vertices, stamp): a message as it came
Update = tuple[ZoneId, ArrayLike] | tuple[ZoneId, ArrayLike, float | None]


def coalesce(updates: Iterable[Update]) -> dict[ZoneId, tuple[ArrayLike, float | None]]:
    """The last (vertices, stamp) per id, in the order the ids last appeared: a batch of
    messages taken at once reduces to one update per id, and none is lost."""
    latest: dict[ZoneId, tuple[ArrayLike, float | None]] = {}
    for zone_id, vertices, *stamp in updates:
        latest.pop(zone_id, None)
        latest[zone_id] = (vertices, stamp[0] if stamp else None)
    return latest


class LiveZones:
    """Zones keyed by id, added, replaced, removed and expired from callbacks on any thread.

    Readers take `snapshot()`, an immutable `ZoneSet` of the union, rebuilt lazily after a
    change, so a flood of messages costs one rebuild per read, not one per message; the
    inference loop can hold one for a whole chunk while callbacks keep updating. `version`
    increments on every change, letting readers tell cheaply whether their snapshot is stale.
    At most `max_zones` zones of at most `max_vertices` vertices are in force; more is refused
    with a reason, the zones in force kept.
    """

    def __init__(self, max_zones: int = DEFAULT_MAX_ZONES,
                 max_vertices: int = DEFAULT_MAX_VERTICES,
                 fixed: RestrictedArea | None = None, workspace: Bounds | None = None,
                 speed_bound: float = DEFAULT_SPEED_BOUND, speed_headroom: float = HEADROOM,
                 reaction_s: float = DEFAULT_REACTION_S) -> None:
        self.max_zones, self.max_vertices = max_zones, max_vertices
        # each id's velocity and the speed assumed of it, from its stamped updates
        self.motion = ZoneMotion(speed_bound, headroom=speed_headroom)
        self.reaction_s = reaction_s  # what a moving zone's reach is sized by (MovingZones)
        # (snapshot, the ids forecast, its zones that stand still with the fixed area, those
        # that move, those of them not forecast, and each forecast one)
        self._moving: tuple | None = None
        self.workspace = workspace  # zones are clipped to it, so what is accepted is enforced
        self.fixed = fixed  # always in force besides the zones (a plug-in check)
        self._union: tuple[ZoneSet, RestrictedArea] | None = None
        self.cleared: dict[tuple[ZoneId, float], None] = {}  # cleared (id, stamp), in order
        self._lock = threading.Lock()
        self._zones: dict[ZoneId, _Zone] = {}
        self._version = 0
        self._snapshot: ZoneSet | None = None
        self._beyond_reach = False  # a change since `apply` began was not `within_reach`

    def upsert(
        self, zone_id: ZoneId, vertices: ArrayLike, now: float, lifetime: float | None = None,
        stamp: float | None = None, capped: bool = True,
    ) -> bool:
        """Add or replace a zone; empty vertices remove it (the ROS convention). Returns False
        for a zone whose lifetime had passed before it came (a stale replay: nothing changes).

        `lifetime` in the same clock as `now`; None or 0 (as in ROS markers) means forever. Its
        age counts from `stamp` (when the zone was published, as nav2's collision monitor
        does), from `now` if there is none; a stamp from the future counts as now. A message
        with the id and stamp of a zone that was cleared is a stale replay too.
        Invalid vertices raise ValueError before anything changes, so the zones in force stay.
        The caps bound what messages may ask for; `capped=False` is for zones the node derives
        itself (a keep-out mask's pieces), which it does not refuse for their number or size.
        """
        if len(vertices) == 0:
            self.remove(zone_id)
            return True
        if lifetime is not None and not lifetime >= 0:
            raise ValueError(f"zone {zone_id!r}: lifetime must be >= 0 or None, got {lifetime}")
        expires_at = min(now, now if stamp is None else stamp) + lifetime if lifetime \
            else math.inf
        if expires_at <= now or (stamp is not None and (zone_id, stamp) in self.cleared):
            return False  # expired, or a replay of a message that was cleared
        if capped and len(vertices) > self.max_vertices:
            raise ValueError(f"zone {zone_id!r}: {len(vertices)} vertices, more than the "
                             f"{self.max_vertices} allowed")
        polygon = validate_polygon(vertices, f"zone {zone_id!r}", self.workspace)
        # What viewers see: the outline in force (as received unless clipped; a zone that the
        # clip split shows its first part).
        vertices = np.asarray(shapely.get_parts(polygon)[0].exterior.coords)[:-1]
        with self._lock:
            previous = self._zones.get(zone_id)
            in_force = sum(zone.capped for zone in self._zones.values())
            if capped and (previous is None or not previous.capped) and \
                    in_force >= self.max_zones:
                raise ValueError(f"zone {zone_id!r}: {self.max_zones} zones in force already "
                                 f"(the cap); remove one first")
            age = 0.0 if stamp is None else min(max(now - stamp, 0.0), MAX_AGE_ON_ARRIVAL_S)
            zone = _Zone(polygon, vertices, expires_at, capped, stamp, time.monotonic() - age)
            within = previous is not None and self.within_reach(zone_id, previous, zone)
            self._zones[zone_id] = zone
            self.motion.observe(zone_id, shapely.get_coordinates(polygon.centroid)[0],
                                now if stamp is None else stamp)
            if previous is None or not previous.polygon.equals_exact(polygon, 0.0):
                # (a re-published, identical zone only refreshes its lifetime)
                self._changed(within_reach=within)
        return True

    def within_reach(self, zone_id: ZoneId, previous: _Zone, zone: _Zone) -> bool:
        """Whether `zone`, an update of `previous`, lies wholly within what `previous` was
        assumed able to reach by the time it was seen (its assumed speed times the time
        between the two, `MovingZones`). A setpoint the shield accepted against `previous`
        then still holds until the next observation is answered: the update needs no answer
        of its own (a hand tracked at 20 Hz would otherwise cost a shield call per update).
        Never for a zone not yet seen moving, one that changed faster than assumed, or a
        change in shape beyond that reach."""
        speed = self.motion.assumed_speed(zone_id)
        if speed <= 0:
            return False
        reach = speed * max(0.0, zone.seen_at - previous.seen_at)
        return bool(previous.polygon.buffer(reach).covers(zone.polygon))

    def apply(self, updates: Iterable[Update], now: float,
              lifetime: float | None = None, capped: bool = True) -> BatchOutcome:
        """A batch of messages (id, vertices[, stamp]) as they came: coalesced to the last per
        id, each applied as `upsert` would; a refused one leaves that id as it was."""
        updates = list(updates)
        latest = coalesce(updates)
        outcome = BatchOutcome(received=len(updates), superseded=len(updates) - len(latest))
        before, self._beyond_reach = self._version, False
        for zone_id, (vertices, stamp) in latest.items():
            try:
                fresh = self.upsert(zone_id, vertices, now, lifetime, stamp, capped)
            except ValueError as error:
                outcome.refused.append((zone_id, str(error)))
            else:
                outcome.applied += fresh
                outcome.stale += not fresh
        outcome.changed = self._version != before
        outcome.within_reach = outcome.changed and not self._beyond_reach
        return outcome

    def remove(self, zone_id: ZoneId) -> bool:
        """Drop a zone; returns whether it existed."""
        with self._lock:
            self.motion.forget(zone_id)
            if self._zones.pop(zone_id, None) is None:
                return False
            self._changed()
            return True

    def clear(self) -> None:
        """Drop every zone; a stamped one stays gone when its message is replayed (a latched
        publisher's history): its (id, stamp) joins `cleared`."""
        with self._lock:
            self.cleared.update(((i, z.stamp), None) for i, z in self._zones.items()
                                if z.stamp is not None)
            while len(self.cleared) > CLEARED_KEPT:
                self.cleared.pop(next(iter(self.cleared)))
            self.motion.clear()
            if self._zones:
                self._zones.clear()
                self._changed()

    def expire(self, now: float) -> list[ZoneId]:
        """Drop zones whose lifetime has passed at `now`; returns their ids."""
        with self._lock:
            gone = [i for i, zone in self._zones.items() if zone.expires_at <= now]
            for zone_id in gone:
                del self._zones[zone_id]
                self.motion.forget(zone_id)
            if gone:
                self._changed()
            return gone

    def snapshot(self) -> ZoneSet:
        """Union of the zones in force, cached until the next change."""
        with self._lock:
            if self._snapshot is None:
                self._snapshot = ZoneSet(zone.polygon for zone in self._zones.values())
            return self._snapshot

    @property
    def version(self) -> int:
        return self._version

    # The executor's zone source: the same zones for every step and episode, until they change.

    def area_at(self, step: int) -> RestrictedArea | None:
        """The zones in force and the fixed area, or None when there is neither; as
        `MovingZones` where zones move (`ZoneMotion.assumed_speed`), aged from when they were
        where they are, sized by `reaction_s`. `step` is not used: live zones are those in
        force now, whatever the step (it is there for the executor's `ZoneSource`, whose
        scripted zones change at given steps)."""
        snapshot = self.snapshot()
        if self.fixed is None:
            area = None if snapshot.is_empty else snapshot
        elif snapshot.is_empty:
            area = self.fixed
        else:
            if self._union is None or self._union[0] is not snapshot:  # one per snapshot
                self._union = (snapshot, AreaUnion([self.fixed, snapshot]))
            area = self._union[1]
        moving = self._moving_zones(snapshot)
        if area is None or moving is None:
            return area
        return MovingZones(area, reaction_s=self.reaction_s, **moving)

    def _moving_zones(self, snapshot: ZoneSet) -> dict | None:
        """For `snapshot`, the keywords of `MovingZones` but the area: the zones that stand
        still (with the fixed area) and those that move, the fastest speed assumed of them,
        how long since the one seen longest ago was where it is, and the moving zones the
        plans forecast (`forecast`) with their velocities, the others as they are; None: none
        moves."""
        with self._lock:
            moving = [(i, z) for i, z in self._zones.items() if self.motion.moving(i)]
            if not moving:
                return None
            ahead = self.forecast([i for i, _ in moving])
            if self._moving is None or self._moving[:2] != (snapshot, ahead):
                ids = {i for i, _ in moving}
                still = ZoneSet(z.polygon for i, z in self._zones.items() if i not in ids)
                if self.fixed is not None:
                    still = AreaUnion([self.fixed, still])
                # each moving zone as a few edges that cover it (`cover`)
                covers = {i: cover(z.polygon) for i, z in moving}
                self._moving = (snapshot, ahead, still, ZoneSet(covers.values()),
                                ZoneSet(c for i, c in covers.items() if i not in ahead),
                                [ZoneSet([covers[i]]) for i in ahead])
            _, _, still, zones, steady, parts = self._moving
            return {"still": still, "moving": zones,
                    "speed": max(self.motion.assumed_speed(i) for i, _ in moving),
                    "age_s": max(0.0, time.monotonic() - min(z.seen_at for _, z in moving)),
                    "drift": [(part, torch.from_numpy(self.motion.velocity(i)))
                              for i, part in zip(ahead, parts, strict=True)],
                    "steady": steady}

    def forecast(self, moving: list[ZoneId]) -> tuple[ZoneId, ...]:
        """Of the `moving` ids, those the plans carry on at their measured velocity: at most
        MAX_FORECAST, the fastest, measured moving within the speed bound. A velocity beyond
        the bound is not believed (a tracker's noise, or a hand faster than assumed: the
        shield grows it by the bound all the same) and one of 0 changes nothing; the plans
        take those where they are. Each
        forecast costs the plans a pass over the chunk, so their number is bounded whatever
        comes in (a flood of moving ids)."""
        speeds = {i: self.motion.speed(i) for i in moving}
        believed = [i for i in moving if 0 < speeds[i] <= self.motion.speed_bound]
        return tuple(sorted(believed, key=lambda i: -speeds[i])[:MAX_FORECAST])

    def version_at(self, step: int) -> int:
        return self._version

    def outlines(self) -> dict[ZoneId, np.ndarray]:
        """Each zone in force by id, (V, 2) its outline: what viewers show."""
        with self._lock:
            return {zone_id: zone.vertices for zone_id, zone in self._zones.items()}

    def nearest(self, point: ArrayLike) -> tuple[ZoneId, float, float, float] | None:
        """(id, distance in px, measured speed and speed assumed of it in px/s) of the zone
        nearest `point` (distance 0 inside it), or None without zones: how close a moving zone
        is, for the status."""
        where = shapely.Point(*np.asarray(point, dtype=float))
        with self._lock:
            if not self._zones:
                return None
            zone_id, zone = min(self._zones.items(),
                                key=lambda item: item[1].polygon.distance(where))
            return (zone_id, float(zone.polygon.distance(where)), self.motion.speed(zone_id),
                    self.motion.assumed_speed(zone_id))

    @property
    def ids(self) -> list[ZoneId]:
        """Ids in force, in insertion order."""
        with self._lock:
            return list(self._zones)

    def __len__(self) -> int:
        return len(self._zones)

    def _changed(self, within_reach: bool = False) -> None:
        """Record a change (`within_reach`: see `within_reach`); caller holds the lock."""
        self._version += 1
        self._snapshot = None
        self._beyond_reach |= not within_reach
