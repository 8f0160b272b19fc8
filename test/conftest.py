"""Shared fixtures: the real PushT demonstrations, read from a path (never copied)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ZARR = REPO.parent / "shared" / "datasets" / "pusht_cchi_v7_replay.zarr"


@pytest.fixture(scope="session")
def dataset_path() -> Path:
    """Missing data is a failure, not a skip: CI has the dataset beside the checkout."""
    path = Path(os.environ.get("PUSHT_ZARR", str(DEFAULT_ZARR)))
    if not path.exists():
        pytest.fail(f"PushT dataset not found at {path}; set PUSHT_ZARR to the "
                    "pusht_cchi_v7_replay.zarr directory (expected at ../shared/datasets/).")
    return path
