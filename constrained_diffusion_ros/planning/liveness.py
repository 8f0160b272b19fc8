"""Standstills at a zone's edge: how a safety filter that stops instead of steering shows.

A pusher that stays put with a zone next to its disc is the filter's doing far more often than
the policy's; the evaluation counts them per episode (`standstills`), the policy node per step
as it runs (`StandstillMeter`), with one definition.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch

from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.plugins import ZoneCheckError

STANDSTILL_STEPS = 5  # a standstill: at least this many control steps in a row
STANDSTILL_PX = 0.5  # of motion per step at most
STANDSTILL_NEAR_PX = 5.0  # with a zone this close to the pusher's disc


def standstills(moved: np.ndarray, near: np.ndarray) -> np.ndarray:
    """(E, T) bool: steps in runs of at least STANDSTILL_STEPS where the pusher moved under
    STANDSTILL_PX (`moved`, px per step) with a zone near its disc (`near`)."""
    still = (moved < STANDSTILL_PX) & near
    marked = np.zeros_like(still)
    if still.shape[1] < STANDSTILL_STEPS:
        return marked
    # A step is in such a run when a whole window of STANDSTILL_STEPS still steps covers it.
    windows = np.lib.stride_tricks.sliding_window_view(still, STANDSTILL_STEPS, axis=1)
    full = windows.all(axis=-1)  # (E, T - n + 1): the window starting there is all still
    for offset in range(STANDSTILL_STEPS):
        marked[:, offset:offset + full.shape[1]] |= full
    return marked


class StandstillMeter:
    """The same count, one control step at a time: `steps` in standstills so far, `longest`
    run (steps)."""

    def __init__(self) -> None:
        self.steps = self.longest = self._run = 0

    def update(self, moved: float, clearance: float, radius: float) -> None:
        """One step: the pusher moved `moved` px, and its centre is `clearance` px from the
        nearest zone (a disc of `radius`)."""
        if moved < STANDSTILL_PX and clearance < radius + STANDSTILL_NEAR_PX:
            self._run += 1
            self.steps += STANDSTILL_STEPS if self._run == STANDSTILL_STEPS else \
                int(self._run > STANDSTILL_STEPS)
            self.longest = max(self.longest, self._run if self._run >= STANDSTILL_STEPS else 0)
        else:
            self._run = 0

    def reset_run(self) -> None:
        """A new episode: a run does not carry over."""
        self._run = 0


class StandstillCounts:
    """The policy node's two counts: standstills with a waypoint to execute (`filter`: the
    filter's doing) and while the last setpoint is held waiting for a plan (`waiting`:
    planning's). A run counts in one of them at a time."""

    def __init__(self) -> None:
        self.filter, self.waiting = StandstillMeter(), StandstillMeter()

    def observe(self, pusher: np.ndarray, moved: float | None, area: RestrictedArea | None,
                radius: float, waiting: bool) -> None:
        """One observed step: the pusher at `pusher` moved `moved` px (None: a new episode),
        with the zones `area` in force (None: none; a plug-in check that fails counts as
        none here: the chunk loop reports it)."""
        clearance = math.inf
        if area is not None:
            with contextlib.suppress(ZoneCheckError):
                clearance = float(area.signed_distance(torch.from_numpy(pusher[None]))[0])
        self.update(moved, clearance, radius, waiting)

    def status(self, control_hz: float) -> dict[str, object]:
        return {"standstill_steps": self.filter.steps,
                "standstill_longest_s": f"{self.filter.longest / control_hz:.1f}",
                "standstill_waiting_steps": self.waiting.steps}

    def update(self, moved: float | None, clearance: float, radius: float,
               waiting: bool) -> None:
        """One step (`moved` None: a new episode, where no run carries over)."""
        counting, other = (self.waiting, self.filter) if waiting else (self.filter, self.waiting)
        other.reset_run()
        if moved is None:
            counting.reset_run()
        else:
            counting.update(moved, clearance, radius)
