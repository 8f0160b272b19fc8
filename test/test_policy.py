"""The learned part: dataset windows, training, weights I/O, sampling and closed-loop progress."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from constrained_diffusion_ros.evaluation.rollout import rollout
from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import load_policy, save_policy
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler
from constrained_diffusion_ros.training import train
from constrained_diffusion_ros.training.dataset import WindowSampler, load_demonstrations


@pytest.fixture(scope="module")
def demos(dataset_path: Path):
    return load_demonstrations(dataset_path)


def test_windows_pad_episode_edges_like_the_reference(demos) -> None:
    sampler = WindowSampler(demos, horizon=16, n_obs_steps=2, n_action_steps=8)
    lengths = np.diff(np.r_[0, demos.episode_ends])
    assert len(sampler) == int((lengths - 16 + 1 + 1 + 7).sum())
    obs, actions = sampler.batch(torch.tensor([0]))
    assert obs.shape == (1, 2, 20) and actions.shape == (1, 16, 2)
    # The first window starts one step before the episode: its first step repeats step 0.
    first = torch.from_numpy(demos.observations[0])
    assert torch.equal(obs[0, 0], first) and torch.equal(obs[0, 1], first)
    assert torch.equal(actions[0, 1], torch.from_numpy(demos.actions[0]))
    # The last window of episode 0 runs 7 steps past its end, repeating the last action.
    last_window = int(lengths[0] - 16 + 1 + 1 + 7) - 1
    _, actions = sampler.batch(torch.tensor([last_window]))
    end = int(demos.episode_ends[0]) - 1
    assert torch.equal(actions[0, -8:], torch.from_numpy(demos.actions[end]).expand(8, 2))


def test_missing_or_malformed_dataset_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not found"):
        load_demonstrations(tmp_path / "nope.zarr")
    (tmp_path / "empty.zarr").mkdir()
    with pytest.raises(ValueError):
        load_demonstrations(tmp_path / "empty.zarr")


def test_tiny_training_lowers_the_loss_and_resumes(dataset_path: Path, tmp_path: Path,
                                                    tiny_dims: tuple[int, ...]) -> None:
    out = tmp_path / "tiny"
    common = ["--dataset", str(dataset_path), "--output", str(out), "--batch-size", "64",
              "--down-dims", *map(str, tiny_dims), "--warmup", "5", "--lr", "1e-3", "--quiet"]
    assert train.main([*common, "--steps", "30", "--checkpoint-every", "15"]) == 0
    assert train.main([*common, "--steps", "60", "--checkpoint-every", "15", "--resume"]) == 0
    losses = json.loads((out / "losses.json").read_text())
    assert len(losses) == 60  # the resumed run continued the first one's record
    assert np.mean(losses[-10:]) < 0.6 * np.mean(losses[:10]), (losses[:10], losses[-10:])
    for name in ("model.safetensors", "config.json", "loss_curve.png"):
        assert (out / name).is_file()
    policy = load_policy(out)
    assert policy.config.down_dims == tiny_dims
    assert json.loads((out / "config.json").read_text())["training"]["steps"] == 60


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
    sampler = DenoisingSampler(shipped, "ddim", 10)
    generator = torch.Generator().manual_seed(0)
    seeds = [100000, 100001, 100002, 100003]
    log = rollout(lambda obs, _step, _rows: sampler.sample(obs, generator), seeds, n_steps=96)
    start = log.coverage[:, 0]
    assert log.coverage.max(axis=1).mean() > start.mean() + 0.3, log.coverage.max(axis=1)
