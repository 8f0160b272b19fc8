"""Training: dataset windows as the reference cuts them, clear errors, a tiny run that learns."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from constrained_diffusion_ros.policy.weights import load_policy
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


def test_store_entries_must_be_files_or_directories_links_judged_by_target(
        tmp_path: Path) -> None:
    """Each entry is checked before zarr opens any (a FIFO blocked it: see test_cli): a linked
    directory is followed, a dangling link is refused by name."""
    import zarr

    store = tmp_path / "tiny.zarr"
    root = zarr.open_group(str(store), mode="w", zarr_format=2)
    for name, shape in (("state", (40, 5)), ("action", (40, 2)), ("keypoint", (40, 9, 2))):
        root.create_array(f"data/{name}", data=np.ones(shape, np.float32))
    root.create_array("meta/episode_ends", data=np.array([20, 40]))
    (store / "data" / "action").rename(tmp_path / "action")
    (store / "data" / "action").symlink_to(tmp_path / "action")
    assert load_demonstrations(store).actions.shape == (40, 2)
    (store / "data" / "notes").symlink_to(tmp_path / "nowhere")  # zarr itself never reads it
    with pytest.raises(ValueError, match=r"cannot read .*data/notes: No such file"):
        load_demonstrations(store)


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
    weights = (out / "model.safetensors").read_bytes()
    assert train.main([*common, "--steps", "30"]) == 2  # a model there: neither flag given
    assert (out / "model.safetensors").read_bytes() == weights
    (out / "checkpoint" / "state.json").write_text("{damaged")
    assert train.main([*common, "--steps", "90", "--resume"]) == 2  # one line, no traceback


def test_a_non_finite_loss_stops_training_with_a_clear_error(
        dataset_path: Path, tmp_path: Path, tiny_dims: tuple[int, ...], monkeypatch,
        capsys) -> None:
    """NaN in the data (here: a loss made NaN) ends the run at once: exit 2, one line, no
    weights saved (they would load as NaN and drive the pusher with NaN setpoints)."""
    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

    monkeypatch.setattr(DiffusionPolicy, "compute_loss",
                        lambda self, *args: self.unet.parameters().__next__().sum() * np.nan)
    out = tmp_path / "nan"
    assert train.main(["--dataset", str(dataset_path), "--output", str(out), "--batch-size",
                       "8", "--down-dims", *map(str, tiny_dims), "--steps", "5",
                       "--quiet"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("train_policy: error: non-finite loss") and "\n" not in error
    assert not (out / "model.safetensors").exists()
