"""Fixtures of the ROS-free tests: the recorded demonstrations as arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def dataset(dataset_path: Path) -> dict[str, np.ndarray]:
    import zarr

    root = zarr.open(str(dataset_path), mode="r")
    return {
        "state": np.asarray(root["data/state"][:], dtype=np.float64),
        "action": np.asarray(root["data/action"][:], dtype=np.float64),
        "keypoint": np.asarray(root["data/keypoint"][:], dtype=np.float64),
        "episode_ends": np.asarray(root["meta/episode_ends"][:]),
    }
