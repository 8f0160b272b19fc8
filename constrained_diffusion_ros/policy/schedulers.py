"""Noise schedulers (diffusers) built from a policy config, so training and sampling agree.

diffusers is imported when a scheduler is first built, not with this module: its import is slow
(it imports torch's compiler stack), and a process that only checks configurations or guards
setpoints (the live policy node, whose plans come from its planning process) need not wait for
it at start-up.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from constrained_diffusion_ros.policy.policy_config import PolicyConfig

if TYPE_CHECKING:
    from diffusers import DDIMScheduler, DDPMScheduler

SchedulerKind = Literal["ddpm", "ddim"]
TimestepSpacing = Literal["leading", "trailing", "linspace"]
SPACINGS = ("leading", "trailing", "linspace")


def make_scheduler(config: PolicyConfig, kind: SchedulerKind = "ddpm",
                   timestep_spacing: TimestepSpacing = "leading"
                   ) -> DDPMScheduler | DDIMScheduler:
    """`timestep_spacing` (diffusers'): which training timesteps a shorter schedule visits.
    "leading" (10 of 100: 90, 80, .., 0) starts below the noisiest step, where the sample is
    still assumed to hold some signal; "trailing" (99, 89, .., 9) starts at pure noise."""
    if timestep_spacing not in SPACINGS:
        raise ValueError(f"unknown timestep spacing {timestep_spacing!r}; choose one of "
                         f"{', '.join(SPACINGS)}")
    common = {
        "num_train_timesteps": config.num_train_timesteps,
        "beta_schedule": config.beta_schedule,
        "clip_sample": config.clip_sample,
        "prediction_type": config.prediction_type,
        "timestep_spacing": timestep_spacing,
    }
    from diffusers import DDIMScheduler, DDPMScheduler

    if kind == "ddpm":
        return DDPMScheduler(variance_type="fixed_small", **common)
    if kind == "ddim":
        return DDIMScheduler(set_alpha_to_one=True, steps_offset=0, **common)
    raise ValueError(f"unknown scheduler {kind!r}; choose 'ddpm' or 'ddim'")
