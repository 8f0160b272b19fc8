"""The action queue of real-time chunking: waypoints indexed by control step, free of threads,
with the chunk loop's rules on it: the replan rule, the rule for a chunk used up, the committed
prefix; and the observation history.

A chunk planned from the observation of step t puts its executed waypoint j (chunk index
`first_executed + j`) at step t + j, whenever it arrives: installed at a later step, the
waypoints whose time has passed are skipped (as LeRobot's asynchronous action queue merges
chunks). While a plan is being made, the waypoints that will execute before it arrives are
already decided; the next chunk is denoised with them held fixed (`committed_prefix`), so the
handover does not jump. The chunk loop (chunk_loop.py) keeps one queue for all its episodes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from constrained_diffusion_ros.sampling.hooks import CommittedPrefix, prefix_weights


class ActionQueue:
    """The chunk in force per episode (B rows), as waypoints indexed by control step.

    A row holds the executed part of its chunk and the rest of the horizon after it, so a plan
    that arrives late still finds waypoints to execute; it is due for a new one once
    `n_action_steps` of them have executed after the ones skipped at install (the horizon the
    policy was trained to execute, whatever the delay).
    """

    def __init__(self, batch: int, n_action_steps: int) -> None:
        self.n_action_steps = n_action_steps
        self.waypoints = np.full((batch, 0, 2), np.nan)
        self.first_step = np.zeros(batch, dtype=np.int64)
        self.end = np.zeros(batch, dtype=np.int64)  # index after the last one to execute
        self.planned = np.zeros(batch, dtype=bool)
        self.installs = np.zeros(batch, dtype=np.int64)  # chunks installed per row: its id
        self.skipped = 0  # waypoints skipped at install because their time had passed

    def install(self, rows: np.ndarray, waypoints: np.ndarray, first_step: np.ndarray | int,
                now: int) -> np.ndarray:
        """Rows `rows` take `waypoints` (R, N, 2), waypoint j for step `first_step + j`; returns
        how many of them had already passed at step `now` (skipped)."""
        rows = np.asarray(rows)
        if waypoints.shape[1] != self.waypoints.shape[1]:
            grown = np.full((len(self.first_step), waypoints.shape[1], 2), np.nan)
            keep = min(waypoints.shape[1], self.waypoints.shape[1])
            grown[:, :keep] = self.waypoints[:, :keep]
            self.waypoints = grown
        self.waypoints[rows] = waypoints
        self.first_step[rows] = first_step
        self.planned[rows] = True
        self.installs[rows] += 1
        skipped = np.clip(now - self.first_step[rows], 0, waypoints.shape[1])
        self.end[rows] = np.minimum(skipped + self.n_action_steps, waypoints.shape[1])
        self.skipped += int(skipped.sum())
        return skipped

    def clear(self, rows: np.ndarray | None = None) -> None:
        """Forget the chunks of `rows` (all by default): nothing to execute until a plan."""
        self.planned[slice(None) if rows is None else rows] = False

    def offset(self, step: int) -> np.ndarray:
        """(B,) index of step `step` in each row's chunk."""
        return step - self.first_step

    def at(self, step: int) -> np.ndarray:
        """(B, 2) the waypoints of step `step`; NaN where a row has none (no chunk, or its
        chunk is used up)."""
        out = np.full((len(self.first_step), 2), np.nan)
        index = self.offset(step)
        ok = self.planned & (index >= 0) & (index < self.waypoints.shape[1])
        out[ok] = self.waypoints[np.nonzero(ok)[0], index[ok]]
        return out

    def at_or(self, step: int, held: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, 2) the waypoints of step `step`, with `held` (B, 2) where a row has none: the
        robot holds its last setpoint until a plan arrives (the one rule for a chunk used up);
        and (B,) which rows had none."""
        waypoints = self.at(step)
        waiting = np.isnan(waypoints).any(axis=-1)
        if waiting.any():
            waypoints[waiting] = np.asarray(held, dtype=float)[waiting]
        return waypoints, waiting

    def remaining(self, step: int) -> np.ndarray:
        """(B,) waypoints still to execute from step `step` on; 0 without a chunk."""
        left = self.end - self.offset(step)
        return np.where(self.planned, np.clip(left, 0, self.n_action_steps), 0)

    def upcoming(self, rows: np.ndarray, step: int, count: int) -> np.ndarray:
        """(R, count, 2) the waypoints of steps step .. step + count - 1; NaN where none."""
        index = self.offset(step)[rows, None] + np.arange(count)[None]
        ok = self.planned[rows, None] & (index >= 0) & (index < self.waypoints.shape[1])
        out = np.full((len(rows), count, 2), np.nan)
        r, c = np.nonzero(ok)
        out[r, c] = self.waypoints[np.asarray(rows)[r], index[r, c]]
        return out

    def rest_refused(self, rows: np.ndarray, step: int,
                     refused: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(R,) whether a waypoint of the rows' chunks still to execute from step `step` on is
        one that `refused` ((R, N, 2) -> (R, N) bool) refuses. With the planner's `violates`
        (where its plans keep waypoints out of now) it is the chunk loop's replan rule: replan
        when zones came onto the rest of the chunk."""
        rows = np.asarray(rows)
        remaining = self.remaining(step)[rows]
        count = int(remaining.max(initial=0))
        if count == 0:
            return np.zeros(len(rows), dtype=bool)
        inside = np.asarray(refused(self.upcoming(rows, step, count)))
        return (inside & (np.arange(count)[None] < remaining[:, None])).any(axis=1)


class ObservationHistory:
    """The last `n_steps` observations per episode, the policy's input. At the start the
    first one stands for the steps before it; a control step with no observation (a real-time
    node may miss one) repeats the one before it, and after a gap as long as the history the
    newest stands for them all, as at the start."""

    def __init__(self, first: np.ndarray, n_steps: int) -> None:
        self.frames = np.repeat(np.asarray(first, dtype=np.float32)[:, None], n_steps, axis=1)

    def push(self, observation: np.ndarray, steps: int = 1) -> None:
        """(B, obs_dim) the observation `steps` control steps after the newest; 0: the newest
        step's again (it replaces it)."""
        observation = np.asarray(observation, dtype=np.float32)[:, None]
        if steps == 0:
            self.frames = np.concatenate([self.frames[:, :-1], observation], axis=1)
            return
        n_steps = self.frames.shape[1]
        if steps >= n_steps:
            self.frames = np.repeat(observation, n_steps, axis=1)
            return
        missed = np.repeat(self.frames[:, -1:], steps - 1, axis=1)
        self.frames = np.concatenate([self.frames, missed, observation], axis=1)[:, -n_steps:]

    def tensor(self, rows: np.ndarray | None = None) -> torch.Tensor:
        frames = self.frames if rows is None else self.frames[rows]
        return torch.from_numpy(frames.astype(np.float32))

    @property
    def latest(self) -> np.ndarray:
        """(B, obs_dim) the observations of the newest step."""
        return self.frames[:, -1]


def committed_prefix(queue: ActionQueue, rows: np.ndarray, step: int, delay: int, soft: int,
                     first_executed: int, free: np.ndarray | None = None
                     ) -> CommittedPrefix | None:
    """The prefix hook for a chunk planned at step `step` that arrives `delay` steps later.

    Chunk index i lies at step `step - first_executed + i`: indices up to `first_executed +
    delay` are the waypoints already executed or committed (held exactly); the `soft` after
    them are drawn toward the chunk in force. Rows with no chunk in force, and `free` ones
    (R,) bool (their chunk was planned for other zones), are left free. Returns None when
    nothing is known (the first plan of an episode).
    """
    count = first_executed + delay + soft
    known = queue.upcoming(rows, step - first_executed, count)
    weights = np.broadcast_to(prefix_weights(first_executed + delay, soft).numpy(),
                              known.shape[:2]).copy()
    missing = np.isnan(known).any(axis=-1)
    if free is not None:
        missing[np.asarray(free, dtype=bool)] = True
    weights[missing] = 0.0
    if not weights.any():
        return None
    known[missing] = 0.0
    return CommittedPrefix(torch.from_numpy(known), torch.from_numpy(weights))
