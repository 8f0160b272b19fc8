"""The denoising loop: hooks see workspace pixels once per update and their output is fed back."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from samples import CENTRE, make_step, observations

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.sampling.hooks import (
    CommittedPrefix,
    FinalProjection,
    prefix_weights,
)
from constrained_diffusion_ros.sampling.sampler import (
    DenoisingSampler,
    DenoisingStep,
    Interrupted,
)
from constrained_diffusion_ros.sampling.updates import ScheduledUpdates

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


def test_an_interrupted_sample_stops_before_the_next_step_and_else_is_unchanged(
        tiny_policy: DiffusionPolicy) -> None:
    """`interrupt` is asked before each denoising step: true, the sample stops there (no
    more network calls); never true, the sample is the plain one, bit for bit."""
    sampler, obs = DenoisingSampler(tiny_policy, "ddim", 5), observations(2)
    plain = sampler.sample(obs, torch.Generator().manual_seed(0))
    steps: list[int] = []

    def count(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        steps.append(step.index)
        return sample

    with sampler.interruptible(lambda: len(steps) == 3), pytest.raises(Interrupted):
        sampler.sample(obs, torch.Generator().manual_seed(0), [count])
    assert steps == [0, 1, 2]
    with sampler.interruptible(lambda: False):
        kept = sampler.sample(obs, torch.Generator().manual_seed(0))
    torch.testing.assert_close(kept, plain, rtol=0, atol=0)
    steps.clear()  # outside the block nothing is asked
    sampler.sample(obs, torch.Generator().manual_seed(0), [count])
    assert steps == [0, 1, 2, 3, 4]


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



# -- The committed prefix (real-time chunking by inpainting) -------------------------------------

KNOWN = torch.tensor([[[100.0, 100.0], [110.0, 104.0], [120.0, 108.0], [130.0, 112.0],
                       [140.0, 116.0]]]).expand(3, 5, 2).clone()


@pytest.mark.parametrize("kind, steps", [("ddim", 5), ("ddpm", None)])
def test_the_committed_prefix_comes_out_exactly_as_committed(
        tiny_policy: DiffusionPolicy, kind: str, steps: int | None) -> None:
    sampler, obs = DenoisingSampler(tiny_policy, kind, steps), observations(3)
    free = sampler.sample(obs, torch.Generator().manual_seed(0))
    assert (free[:, :3] - KNOWN[:, :3]).norm(dim=-1).min() > 10  # left alone, it goes elsewhere
    hook = CommittedPrefix(KNOWN[:, :3], prefix_weights(3, 0))
    out = sampler.sample(obs, torch.Generator().manual_seed(0), [hook])
    torch.testing.assert_close(out[:, :3], KNOWN[:, :3], atol=1e-3, rtol=0)
    assert out.shape == (3, 16, 2)


def test_the_prefix_is_held_at_the_noise_level_of_each_update(
        tiny_policy: DiffusionPolicy) -> None:
    """Before the last update the prefix is the committed waypoints noised, not clean ones: a
    clean prefix in a noisy sample is what the network never saw in training."""
    seen: list[torch.Tensor] = []
    hook = CommittedPrefix(KNOWN[:, :3], prefix_weights(3, 0))

    def record(sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        seen.append((sample[:, :3] - KNOWN[:, :3]).norm(dim=-1).mean())
        return sample

    sampler = DenoisingSampler(tiny_policy, "ddim", 5)
    sampler.sample(observations(3), torch.Generator().manual_seed(0), [hook, record])
    assert seen[0] > seen[2] > seen[-1] and seen[-1] < 1e-3  # noise falls to nothing


def test_the_constraints_run_after_the_prefix_and_keep_every_waypoint_out(
        tiny_policy: DiffusionPolicy) -> None:
    """Committed waypoints of the new chunk are skipped when it is installed (their steps have
    passed), so the constraints may move them; the soft ones after them, drawn toward a chunk
    a new zone made unsafe, must not stay inside."""
    inside = KNOWN + torch.tensor([200.0, 200.0])  # the chunk in force runs through CENTRE
    hooks = [CommittedPrefix(inside, prefix_weights(2, 3)), FinalProjection(CENTRE)]
    out = DenoisingSampler(tiny_policy, "ddim", 5).sample(observations(3),
                                                          torch.Generator().manual_seed(0), hooks)
    assert not CENTRE.contains(out).any()


def test_per_row_weights_leave_rows_without_a_chunk_free(tiny_policy: DiffusionPolicy) -> None:
    sampler, obs = DenoisingSampler(tiny_policy, "ddim", 5), observations(3)
    free = sampler.sample(obs, torch.Generator().manual_seed(0))
    weights = prefix_weights(3, 0)[None].repeat(3, 1)
    weights[1] = 0.0
    out = sampler.sample(obs, torch.Generator().manual_seed(0),
                         [CommittedPrefix(KNOWN[:, :3], weights)])
    torch.testing.assert_close(out[[0, 2], :3], KNOWN[[0, 2], :3], atol=1e-3, rtol=0)
    torch.testing.assert_close(out[1], free[1], atol=1e-3, rtol=0)  # px round trip


def test_soft_weights_draw_the_waypoints_after_the_prefix_toward_the_old_chunk(
        tiny_policy: DiffusionPolicy) -> None:
    sampler, obs = DenoisingSampler(tiny_policy, "ddim", 5), observations(3)
    hard = sampler.sample(obs, torch.Generator().manual_seed(0),
                          [CommittedPrefix(KNOWN[:, :2], prefix_weights(2, 0))])
    soft = sampler.sample(obs, torch.Generator().manual_seed(0),
                          [CommittedPrefix(KNOWN, prefix_weights(2, 3))])
    np.testing.assert_allclose(prefix_weights(2, 3).numpy(), [1, 1, 0.75, 0.5, 0.25])
    gap_hard = (hard[:, 2:5] - KNOWN[:, 2:5]).norm(dim=-1).mean()
    gap_soft = (soft[:, 2:5] - KNOWN[:, 2:5]).norm(dim=-1).mean()
    assert gap_soft < 0.8 * gap_hard
    with pytest.raises(ValueError, match="weights"):
        CommittedPrefix(KNOWN, prefix_weights(2, 0))


def test_timestep_spacing_and_eta_shape_the_ddim_schedule(tiny_policy: DiffusionPolicy) -> None:
    """Trailing starts at the noisiest training step, leading below it; eta reaches the
    scheduler's step (eta 1 adds noise at every step: another chunk from the same seed)."""
    leading = DenoisingSampler(tiny_policy, "ddim", 10)
    trailing = DenoisingSampler(tiny_policy, "ddim", 10, timestep_spacing="trailing")
    assert leading.scheduler.timesteps[0] == 90 and leading.scheduler.timesteps[-1] == 0
    assert trailing.scheduler.timesteps[0] == 99 and trailing.scheduler.timesteps[-1] == 9
    with pytest.raises(ValueError, match="timestep spacing"):
        DenoisingSampler(tiny_policy, "ddim", 10, timestep_spacing="sideways")
    obs = observations(2)
    deterministic, stochastic = (
        DenoisingSampler(tiny_policy, "ddim", 4, "trailing", eta).sample(
            obs, torch.Generator().manual_seed(0)) for eta in (0.0, 1.0))
    again = DenoisingSampler(tiny_policy, "ddim", 4, "trailing", 0.0).sample(
        obs, torch.Generator().manual_seed(0))
    assert torch.equal(deterministic, again) and not torch.equal(deterministic, stochastic)


@pytest.mark.parametrize(("kind", "steps", "eta", "batch"),
                         [("ddpm", 100, 0.0, 1), ("ddpm", 10, 0.0, 4), ("ddim", 10, 0.0, 1),
                          ("ddim", 10, 1.0, 300)])
def test_the_precomputed_updates_are_the_schedulers_own_bit_for_bit(
        tiny_policy: DiffusionPolicy, kind: str, steps: int, eta: float, batch: int) -> None:
    """A whole schedule of updates, noise drawn from the same generator: equal to diffusers'
    `step` to the last bit, so the sampler's results (and the committed reports) stay theirs."""
    sampler = DenoisingSampler(tiny_policy, kind, steps, eta=eta)
    updates = ScheduledUpdates(sampler.scheduler, eta)
    theirs = torch.Generator().manual_seed(3)
    ours = torch.Generator().manual_seed(3)
    reference = torch.randn(batch, 16, 2, generator=torch.Generator().manual_seed(1))
    fast = reference.clone()
    outputs = torch.Generator().manual_seed(2)
    for index, timestep in enumerate(sampler.scheduler.timesteps):
        output = torch.randn(batch, 16, 2, generator=outputs)
        reference = sampler.scheduler.step(output, timestep, reference, generator=theirs,
                                           eta=eta).prev_sample if kind == "ddim" else \
            sampler.scheduler.step(output, timestep, reference, generator=theirs).prev_sample
        fast = updates.apply(index, output, fast, ours)
        assert torch.equal(fast, reference), index
    assert not torch.equal(fast, torch.zeros_like(fast))


@pytest.mark.parametrize(("kind", "steps"), [("ddpm", 100), ("ddim", 10)])
def test_the_precomputed_noising_is_the_schedulers_add_noise_bit_for_bit(
        tiny_policy: DiffusionPolicy, kind: str, steps: int) -> None:
    """What the prefix hook holds its known waypoints to after each update: the scheduler's own
    `add_noise` at the level that update reached, to the last bit, as each hook is handed it
    (`DenoisingStep.noised`, in workspace px); unchanged after the last."""
    sampler = DenoisingSampler(tiny_policy, kind, steps)
    generator = torch.Generator().manual_seed(4)
    clean, noise = torch.rand(3, 16, 2, generator=generator) * 512, torch.randn(3, 16, 2)
    seen: list[DenoisingStep] = []
    sampler.sample(observations(1), torch.Generator().manual_seed(0),
                   [lambda sample, step: seen.append(step) or sample])
    assert [step.next_timestep for step in seen] == [*sampler.scheduler.timesteps.tolist()[1:],
                                                     None]
    normalizer = tiny_policy.action_normalizer
    for step in seen[:-1]:
        level = torch.tensor([step.next_timestep])
        expected = normalizer.unnormalize(
            sampler.scheduler.add_noise(normalizer.normalize(clean), noise, level))
        assert torch.equal(step.noised(clean, noise), expected), step.index
    assert torch.equal(seen[-1].noised(clean, noise), clean)
