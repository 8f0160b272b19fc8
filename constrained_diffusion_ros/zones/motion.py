"""How zones move: a velocity per zone id from its successive stamped updates, and the speed a
guarantee must assume where none is measured.

A moving zone is the same id republished with a new stamp (a hand a camera tracks). Its
velocity is the displacement of its centroid between two updates over the time between their
stamps, smoothed over the updates before; after a gap longer than `max_gap_s` it is measured
afresh. A zone with fewer than `min_updates` updates behind its estimate is assumed to move at
`speed_bound`, as ISO 13855 assumes an approach speed where none is measured. A tracked zone
faster than the bound breaks the assumption a separation built on the bound rests on:
`over_bound` names it, so it is said, not trusted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

# px/s: the speed assumed of a zone whose own is not measured, and the bound a measured one is
# held to. 300 px/s covers the hands the package is checked against (50 to 300 px/s: at 100 px/s
# a zone covers 10 px per control step, about a slow hand on a PushT table).
DEFAULT_SPEED_BOUND = 300.0
MIN_UPDATES = 3  # updates (two displacements) before a zone's own speed is trusted
MAX_GAP_S = 1.0  # a longer pause between updates starts the estimate afresh
SMOOTHING = 0.5  # weight of the newest displacement in the velocity


@dataclass
class Track:
    """What is known of one zone's motion."""

    stamp: float  # s, of the latest update
    centroid: np.ndarray  # (2,) px
    velocity: np.ndarray  # (2,) px/s; zero until two updates
    updates: int  # updates since the estimate (re)started


class ZoneMotion:
    """Velocities of zones by id, from `observe(id, centroid, stamp)`; `forget` a zone that
    is gone. Not thread-safe: its owner (`LiveZones`) holds its lock around it."""

    def __init__(self, speed_bound: float = DEFAULT_SPEED_BOUND, min_updates: int = MIN_UPDATES,
                 max_gap_s: float = MAX_GAP_S) -> None:
        if not speed_bound >= 0:
            raise ValueError(f"the zone speed bound must be >= 0 px/s, got {speed_bound}")
        self.speed_bound, self.min_updates, self.max_gap_s = speed_bound, min_updates, max_gap_s
        self.tracks: dict[object, Track] = {}

    def observe(self, zone_id: object, centroid: ArrayLike, stamp: float) -> None:
        """A zone's update: its centroid (px) at `stamp` (s). An update no later than the last
        (a replay, or out of order) says nothing of motion and is ignored."""
        centroid = np.asarray(centroid, dtype=float)
        track = self.tracks.get(zone_id)
        if track is not None and stamp <= track.stamp:
            return
        if track is None or stamp - track.stamp > self.max_gap_s:
            self.tracks[zone_id] = Track(stamp, centroid, np.zeros(2), 1)
            return
        velocity = (centroid - track.centroid) / (stamp - track.stamp)
        if track.updates > 1:
            velocity = SMOOTHING * velocity + (1 - SMOOTHING) * track.velocity
        self.tracks[zone_id] = Track(stamp, centroid, velocity, track.updates + 1)

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
        """px/s to assume of the zone: its measured speed, else the bound."""
        if self.measured(zone_id):
            return float(np.linalg.norm(self.tracks[zone_id].velocity))
        return self.speed_bound

    def over_bound(self) -> list[object]:
        """Ids of the zones measured faster than the bound."""
        return [zone_id for zone_id in self.tracks
                if self.measured(zone_id) and self.speed(zone_id) > self.speed_bound]
