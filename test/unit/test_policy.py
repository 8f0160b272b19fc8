"""The policy: weights I/O, seeded sampling, and the shipped weights in and out of the loop."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from constrained_diffusion_ros.evaluation.rollout import rollout
from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import load_policy, save_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler
from constrained_diffusion_ros.training.dataset import load_demonstrations


@pytest.fixture(scope="module")
def demos(dataset_path: Path):
    return load_demonstrations(dataset_path)


def test_save_then_load_gives_identical_outputs(tmp_path: Path,
                                                tiny_policy: DiffusionPolicy) -> None:
    policy = tiny_policy
    save_policy(policy, tmp_path)
    loaded = load_policy(tmp_path)
    sample, steps, cond = torch.randn(3, 16, 2), torch.tensor([0, 50, 99]), torch.randn(3, 40)
    assert torch.equal(policy.unet(sample, steps, cond), loaded.unet(sample, steps, cond))
    assert loaded.config == policy.config


def test_mismatched_or_corrupt_weights_are_refused(tmp_path: Path,
                                                   tiny_policy: DiffusionPolicy) -> None:
    save_policy(tiny_policy, tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    config["policy"]["down_dims"] = [32, 64, 128]
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="do not match"):
        load_policy(tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="cannot read weights"):
        load_policy(tmp_path)
    with pytest.raises(ValueError, match="not a policy directory"):
        load_policy(tmp_path / "missing")


def test_sampling_with_a_fixed_seed_is_reproducible(
        make_tiny_policy: Callable[..., DiffusionPolicy]) -> None:
    sampler = DenoisingSampler(make_tiny_policy(), "ddim", 5)
    obs = torch.rand(4, 2, 20) * 512

    def draw(seed: int) -> torch.Tensor:
        return sampler.sample(obs, torch.Generator().manual_seed(seed))

    assert torch.equal(draw(1), draw(1))
    assert not torch.equal(draw(1), draw(2))
    assert DenoisingSampler(make_tiny_policy(), "ddpm").num_inference_steps == 100


@pytest.fixture(scope="module")
def shipped() -> DiffusionPolicy:
    return load_policy(default_model_dir())


def test_shipped_weights_give_in_range_actions(shipped: DiffusionPolicy, demos) -> None:
    obs = torch.from_numpy(demos.observations[[0, 1, 500, 501]]).reshape(2, 2, 20)
    actions = DenoisingSampler(shipped).sample(obs, torch.Generator().manual_seed(0))
    assert actions.shape == (2, 16, 2)
    stats = shipped.config.normalizer["action"]
    low, high = torch.tensor(stats["min"]), torch.tensor(stats["max"])
    assert torch.all(actions >= low - 1e-3) and torch.all(actions <= high + 1e-3)


def test_shipped_policy_makes_progress_in_closed_loop(shipped: DiffusionPolicy) -> None:
    unconstrained = ConstraintConfig("none", sampler="ddim", denoising_steps=10)
    planner = ConstrainedPlanner(shipped, unconstrained, PUSHT_ROBOT)
    generator = torch.Generator().manual_seed(0)
    seeds = [100000, 100001, 100002, 100003]
    log = rollout(planner, seeds, n_steps=96, generator=generator)
    start = log.coverage[:, 0]
    assert log.coverage.max(axis=1).mean() > start.mean() + 0.3, log.coverage.max(axis=1)


def test_weights_with_nan_are_refused(tmp_path: Path, tiny_policy: DiffusionPolicy) -> None:
    """What a diverged training run saves loads no more: the node would publish NaN."""
    with torch.no_grad():
        next(tiny_policy.unet.parameters())[0] = float("nan")
    save_policy(tiny_policy, tmp_path)
    with pytest.raises(ValueError, match="NaN or inf"):
        load_policy(tmp_path)


@pytest.mark.parametrize(("change", "reason"), [
    ({"horizon": 15}, "multiple of 4"),
    ({"n_action_steps": 20}, "exceeds horizon"),
    ({"down_dims": [64, 128, 1_000_000]}, "down_dims"),
    ({"kernel_size": 4}, "odd"),
    ({"n_obs_steps": 0}, "positive integer"),
])
def test_a_config_that_would_fail_later_is_refused_before_any_network_is_built(
        tmp_path: Path, tiny_policy: DiffusionPolicy, change: dict, reason: str) -> None:
    save_policy(tiny_policy, tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    config["policy"].update(change)
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=reason):
        load_policy(tmp_path)
