"""The denoising loop: hooks see workspace pixels once per update and their output is fed back."""

from __future__ import annotations

import numpy as np
import torch
from samples import CENTRE, make_step, observations

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.sampling.hooks import FinalProjection
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler, DenoisingStep

# -- Through the sampler -------------------------------------------------------------------------

def test_final_projection_through_the_sampler_keeps_every_waypoint_out(
        tiny_policy: DiffusionPolicy) -> None:
    sampler = DenoisingSampler(tiny_policy, "ddim", 5)
    obs = observations(8)
    free = sampler.sample(obs, torch.Generator().manual_seed(0))
    assert CENTRE.contains(free).any()
    out = sampler.sample(obs, torch.Generator().manual_seed(0), hooks=[FinalProjection(CENTRE)])
    assert out.shape == (8, 16, 2)
    assert not CENTRE.contains(out).any()


def test_hooks_see_workspace_pixels_once_per_denoising_step(tiny_policy: DiffusionPolicy) -> None:
    seen: list[tuple[int, int, tuple[int, ...], torch.Tensor]] = []
    generator = torch.Generator().manual_seed(0)

    def record(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        assert step.generator is generator and step.normalizer is tiny_policy.action_normalizer
        seen.append((step.index, step.total, tuple(sample.shape), sample.clone()))
        return sample

    out = DenoisingSampler(tiny_policy, "ddim", 5).sample(observations(3), generator, [record])
    assert [s[0] for s in seen] == [0, 1, 2, 3, 4]
    assert {s[1] for s in seen} == {5}
    assert {s[2] for s in seen} == {(3, 16, 2)}
    # The last sample the hook saw is the output, in pixels (normalised values would be ~256x off).
    torch.testing.assert_close(seen[-1][3], out, atol=1e-3, rtol=0)
    assert out.max() > 100


def test_a_hook_changes_what_the_next_denoising_step_starts_from(
        tiny_policy: DiffusionPolicy) -> None:
    """A hook's output is fed back: a hook that pins every waypoint pins the result."""
    def pin(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        return torch.full_like(sample, 300.0) if step.index == step.total - 1 else sample

    out = DenoisingSampler(tiny_policy, "ddim", 5).sample(observations(2),
                                                          torch.Generator().manual_seed(0), [pin])
    torch.testing.assert_close(out, torch.full_like(out, 300.0))




def test_step_progress_runs_evenly_from_0_to_1() -> None:
    progress = [make_step(i, total=5).progress for i in range(5)]
    np.testing.assert_allclose(progress, [0.0, 0.25, 0.5, 0.75, 1.0])
    assert make_step(0, total=1).progress == 0.0

