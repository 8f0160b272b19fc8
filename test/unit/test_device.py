"""The network's device: CPU by default, a GPU only when asked for and present, and the same
noise (so the same chunks) whatever the device."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from constrained_diffusion_ros.evaluation import benchmark
from constrained_diffusion_ros.policy.device import resolve_device
from constrained_diffusion_ros.policy.weights import load_policy, save_policy


def test_cpu_is_always_there_and_an_absent_or_unknown_device_is_one_clear_error() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="not available"):
        resolve_device("cuda:99")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="not available"):
            resolve_device("cuda")
    with pytest.raises(ValueError, match="unknown device"):
        resolve_device("abacus")
    with pytest.raises(ValueError, match="not supported"):
        resolve_device("meta")


def test_a_policy_loads_on_the_cpu_and_benchmark_policy_runs_there(
        make_tiny_policy, tmp_path: Path) -> None:
    model = save_policy(make_tiny_policy(0), tmp_path / "model")
    assert load_policy(model, "cpu").device == torch.device("cpu")
    figures = tmp_path / "figures.json"
    assert benchmark.main(["--model", str(model), "--device", "cpu", "--episodes", "2",
                           "--steps", "8", "--sampler", "ddim", "--denoising-steps", "2",
                           "--threads", "1", "--json", str(figures)]) == 0
    written = json.loads(figures.read_text())
    assert written["device"] == "cpu" and written["episodes"] == 2
