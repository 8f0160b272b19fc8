"""PushT demonstrations from the reference's zarr layout, as padded training windows.

The whole low-dimensional dataset is a few megabytes, so it is held in memory as tensors and a
batch is one gather: no DataLoader, no worker processes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from constrained_diffusion_ros.policy.policy_config import regular_file

REQUIRED_ARRAYS = ("data/state", "data/action", "data/keypoint", "meta/episode_ends")


@dataclass
class Demonstrations:
    """Per-step arrays of every episode, concatenated, plus the episode boundaries."""

    observations: np.ndarray  # (steps, 20): 9 keypoints (x, y) then pusher (x, y)
    actions: np.ndarray  # (steps, 2)
    states: np.ndarray  # (steps, 5)
    episode_ends: np.ndarray  # (episodes,) exclusive ends

    @property
    def episode_starts(self) -> np.ndarray:
        return np.concatenate([[0], self.episode_ends[:-1]])


def load_demonstrations(path: str | Path) -> Demonstrations:
    """Reads a PushT zarr store; raises ValueError naming what is missing or malformed."""
    import zarr

    path = Path(path)
    if not path.exists():
        raise ValueError(f"dataset not found: {path}")
    if path.is_dir():
        check_store_entries(path)
    try:
        root = zarr.open(str(path), mode="r")
        arrays = {name: np.asarray(root[name][:]) for name in REQUIRED_ARRAYS}
    except KeyError as error:
        raise ValueError(
            f"{path} lacks array {error}; expected {', '.join(REQUIRED_ARRAYS)}") from None
    except Exception as error:  # zarr raises many types for a non-store path
        raise ValueError(f"{path} is not a readable zarr store: {error}") from error
    states, actions = arrays["data/state"], arrays["data/action"]
    keypoints, ends = arrays["data/keypoint"], arrays["meta/episode_ends"].astype(np.int64)
    steps = len(states)
    shapes_ok = (states.shape, actions.shape, keypoints.shape) == ((steps, 5), (steps, 2),
                                                                    (steps, 9, 2))
    if not shapes_ok:
        raise ValueError(
            f"unexpected shapes: state {states.shape}, action {actions.shape}, "
            f"keypoint {keypoints.shape}; expected (N, 5), (N, 2), (N, 9, 2)"
        )
    if len(ends) == 0 or ends[-1] != steps or np.any(np.diff(np.r_[0, ends]) <= 0):
        raise ValueError("meta/episode_ends must be increasing and end at the number of steps")
    observations = np.concatenate([keypoints.reshape(steps, 18), states[:, :2]], axis=1)
    return Demonstrations(observations.astype(np.float32), actions.astype(np.float32),
                          states.astype(np.float32), ends)


def check_store_entries(store: Path) -> None:
    """Refuses (ValueError, one line naming the entry) a store directory holding anything but
    regular files and directories, symlinks judged by their targets: zarr would open a FIFO
    inside it (say data/action/.zarray) and block forever waiting for a writer, and read a
    device without end. A few hundred entries: one stat each."""
    visited: set[tuple[int, int]] = set()
    pending = [store]
    while pending:
        directory = pending.pop()
        try:
            info = os.stat(directory)
            if (info.st_dev, info.st_ino) in visited:  # a symlink loop: seen already
                continue
            visited.add((info.st_dev, info.st_ino))
            with os.scandir(directory) as entries:
                found = list(entries)
        except OSError as error:
            raise ValueError(f"cannot read {directory}: {error.strerror or error}") from None
        for entry in found:
            if entry.is_dir():  # follows a symlink, as zarr does
                pending.append(Path(entry.path))
            else:
                regular_file(entry.path)  # a FIFO, a device, a dangling link: one line


class WindowSampler:
    """Windows of `horizon` steps, padded at episode edges by repeating the edge step.

    As in the reference's SequenceSampler, a window may start `n_obs_steps - 1` steps before an
    episode and end `n_action_steps - 1` steps after it, so every step is seen as the "current"
    one with a full observation history and a full action horizon.
    """

    def __init__(self, demos: Demonstrations, horizon: int, n_obs_steps: int,
                 n_action_steps: int) -> None:
        pad_before, pad_after = n_obs_steps - 1, n_action_steps - 1
        index_rows, starts, ends = [], demos.episode_starts, demos.episode_ends
        offsets = np.arange(horizon)
        for start, end in zip(starts, ends):
            first = np.arange(start - pad_before, end - horizon + pad_after + 1)
            index_rows.append(np.clip(first[:, None] + offsets[None, :], start, end - 1))
        self.indices = torch.from_numpy(np.concatenate(index_rows))
        self.observations = torch.from_numpy(demos.observations)
        self.actions = torch.from_numpy(demos.actions)
        self.n_obs_steps = n_obs_steps

    def __len__(self) -> int:
        return len(self.indices)

    def batch(self, window_ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(observation history (B, n_obs_steps, 20), action window (B, horizon, 2))."""
        rows = self.indices[window_ids]
        return self.observations[rows[:, : self.n_obs_steps]], self.actions[rows]
