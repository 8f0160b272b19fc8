"""Noise schedulers (diffusers) built from a policy config, so training and sampling agree."""

from __future__ import annotations

from typing import Literal

from diffusers import DDIMScheduler, DDPMScheduler

from constrained_diffusion_ros.policy.config import PolicyConfig

SchedulerKind = Literal["ddpm", "ddim"]


def make_scheduler(config: PolicyConfig, kind: SchedulerKind = "ddpm") -> DDPMScheduler:
    common = {
        "num_train_timesteps": config.num_train_timesteps,
        "beta_schedule": config.beta_schedule,
        "clip_sample": config.clip_sample,
        "prediction_type": config.prediction_type,
    }
    if kind == "ddpm":
        return DDPMScheduler(variance_type="fixed_small", **common)
    if kind == "ddim":
        return DDIMScheduler(set_alpha_to_one=True, steps_offset=0, **common)
    raise ValueError(f"unknown scheduler {kind!r}; choose 'ddpm' or 'ddim'")
