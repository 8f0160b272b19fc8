"""Shared fixtures: the real PushT demonstrations, read from a path (never copied), and tiny
random policies for tests that need a network but not a trained one.

Tests are grouped by layer, one folder each, and marked by it (markers in pytest.ini):
`pytest -m unit` runs the ROS-free suite alone, `-m ros` the DDS tests, `-m install` colcon."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ZARR = REPO.parent / "shared" / "datasets" / "pusht_cchi_v7_replay.zarr"
LAYERS = ("unit", "ros", "install")


@pytest.fixture(scope="session", autouse=True)
def own_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """What the package caches (exported ONNX graphs) goes to a folder of the session's, for
    the tests and the nodes they start alike: no test reads what another run left."""
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Each test is marked with its layer, the folder it lives in."""
    for item in items:
        layer = item.path.parent.name
        if layer not in LAYERS:
            raise pytest.UsageError(f"{item.nodeid}: tests live in one of test/{LAYERS}")
        item.add_marker(getattr(pytest.mark, layer))


@pytest.fixture(scope="session")
def dataset_path() -> Path:
    """Missing data is a failure, not a skip: CI has the dataset beside the checkout."""
    path = Path(os.environ.get("PUSHT_ZARR", str(DEFAULT_ZARR)))
    if not path.exists():
        pytest.fail(f"PushT dataset not found at {path}; set PUSHT_ZARR to the "
                    "pusht_cchi_v7_replay.zarr directory (expected at ../shared/datasets/).")
    return path


@pytest.fixture(scope="session")
def tiny_dims() -> tuple[int, ...]:
    """U-Net widths of the tiny test policies: the shipped network class, fast on CPU."""
    return (16, 32, 64)


@pytest.fixture
def make_tiny_policy(tiny_dims: tuple[int, ...]) -> Callable[..., DiffusionPolicy]:
    """Builds untrained policies with identity-like normalisers ([0, 512] -> [-1, 1]).

    The same seed gives the same weights; building reseeds torch's global generator.
    """
    import torch

    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
    from constrained_diffusion_ros.policy.policy_config import PolicyConfig

    def build(seed: int = 0) -> DiffusionPolicy:
        torch.manual_seed(seed)
        stats = {"obs": {"min": [0.0] * 20, "max": [512.0] * 20},
                 "action": {"min": [0.0, 0.0], "max": [512.0, 512.0]}}
        return DiffusionPolicy(PolicyConfig(down_dims=tiny_dims, normalizer=stats)).eval()

    return build


@pytest.fixture
def tiny_policy(make_tiny_policy: Callable[..., DiffusionPolicy]) -> DiffusionPolicy:
    """A tiny untrained policy, seed 0."""
    return make_tiny_policy()
