"""The network's runtimes: ONNX Runtime gives torch's forwards, and a runtime that cannot run
the network falls back to torch with one log line."""

from __future__ import annotations

import logging
import pickle

import pytest
import torch

from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy import inference
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import ZoneSet, rectangle


@pytest.fixture(scope="module")
def shipped() -> DiffusionPolicy:
    return load_policy(default_model_dir())


def test_every_forward_of_a_body_safe_plan_agrees_with_torch(
        shipped: DiffusionPolicy, monkeypatch: pytest.MonkeyPatch) -> None:
    """A DDIM 10 plan with the body-safe hooks, at batch 1 and 4: at each denoising step the
    ONNX Runtime forward (its FiLM's step part computed once for the schedule, its
    condition's part once per plan) equals torch's own forward on the same input to
    TOLERANCE."""
    assert inference.use_runtime(shipped, "onnxruntime") == "onnxruntime"
    fast_denoiser, worst, calls = shipped.denoiser, [0.0], [0]

    def compared(timesteps: torch.Tensor, cond: torch.Tensor):
        network = fast_denoiser(timesteps, cond)

        def checked(sample: torch.Tensor, index: int) -> torch.Tensor:
            out = network(sample, index)
            expected = shipped.unet(sample, timesteps[index], cond)
            worst[0] = max(worst[0], float((out - expected).abs().max()))
            calls[0] += 1
            return out
        return checked

    config = ConstraintConfig(name="safe", sampler="ddim", denoising_steps=10, resample=True,
                              push=10, project=True, inflate=True, path_repair=True,
                              shield=True)
    planner = ConstrainedPlanner(shipped, config, PUSHT_ROBOT)
    zones = ZoneSet.from_polygons([rectangle(200, 200, 260, 260)])
    monkeypatch.setattr(shipped, "denoiser", compared)
    try:
        for batch in (1, 4):
            observations = torch.rand(batch, 2, shipped.config.obs_dim) * 400 + 50
            chunks = planner.plan(observations, zones, None, torch.Generator().manual_seed(3))
            assert chunks.shape == (batch, shipped.config.horizon, 2)
            assert torch.isfinite(chunks).all()
    finally:
        inference.use_runtime(shipped, "torch")
    assert calls[0] >= 20  # every forward of both plans went through the check
    assert worst[0] <= inference.TOLERANCE


def test_the_film_outputs_split_into_the_steps_part_and_the_conditions(
        shipped: DiffusionPolicy) -> None:
    """Each block's FiLM output, Linear(Mish([step embedding, condition])), equals the sum of
    the step's part and the condition's, for every step and row."""
    unet, steps = shipped.unet, torch.tensor([99, 50, 3])
    cond = torch.rand(2, shipped.config.global_cond_dim) * 2 - 1
    with torch.no_grad():
        split = unet.step_films(steps)[:, None] + unet.condition_films(cond)[None]
        embedded = unet.step_encoder(steps)
        whole = torch.cat([embedded[:, None].expand(3, 2, -1), cond[None].expand(3, 2, -1)], -1)
        expected = torch.cat([block.film(whole) for block in unet.blocks()], dim=-1)
    assert split.shape == expected.shape == (3, 2, expected.shape[-1])
    assert float((split - expected).abs().max()) <= 1e-5


def test_the_graph_travels_with_the_policy_and_opens_again(shipped: DiffusionPolicy) -> None:
    """A planning process gets the policy pickled: the session is opened there again."""
    try:
        assert inference.use_runtime(shipped, "onnxruntime") == "onnxruntime"
        copy = pickle.loads(pickle.dumps(shipped))
        assert isinstance(copy.fast, inference.OnnxDenoiser)
        assert inference.disagreement(copy, copy.fast, seed=5) <= inference.TOLERANCE
    finally:
        inference.use_runtime(shipped, "torch")


def test_the_graph_is_cached_between_starts_and_a_bad_cache_is_exported_afresh(
        shipped: DiffusionPolicy, monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    exports, export = [], inference.export_onnx
    monkeypatch.setattr(inference, "export_onnx", lambda p: (exports.append(1), export(p))[1])
    try:
        assert inference.use_runtime(shipped, "onnxruntime") == "onnxruntime"
        (cached,) = inference.cache_dir().glob("*.onnx")
        assert inference.use_runtime(shipped, "onnxruntime") == "onnxruntime"
        assert len(exports) == 1  # the second start read the cache
        cached.write_bytes(b"not a graph")
        assert inference.use_runtime(shipped, "onnxruntime") == "onnxruntime"
        assert len(exports) == 2 and cached.read_bytes() != b"not a graph"  # and cached again
    finally:
        inference.use_runtime(shipped, "torch")


@pytest.mark.parametrize("fault", ["cannot export", "disagrees"])
def test_a_runtime_that_cannot_run_the_network_falls_back_to_torch_saying_so(
        shipped: DiffusionPolicy, fault: str, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture, tmp_path) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # nothing cached: it must export
    if fault == "cannot export":
        def broken(_policy):
            raise RuntimeError("Unsupported: ONNX export of operator mish\nmore detail")
        monkeypatch.setattr(inference, "export_onnx", broken)
    else:
        monkeypatch.setattr(inference, "disagreement", lambda *_args, **_kw: 0.5)
    with caplog.at_level(logging.WARNING, logger=inference.__name__):
        assert inference.use_runtime(shipped, "onnxruntime") == "torch"
    assert shipped.fast is None
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "using torch" in lines[0] and "\n" not in lines[0]


def test_an_unknown_runtime_is_refused(shipped: DiffusionPolicy) -> None:
    with pytest.raises(ValueError, match="runtime must be one of"):
        inference.use_runtime(shipped, "tensorrt")
