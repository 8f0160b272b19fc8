"""The schedulers' denoising updates with their coefficients computed once per schedule.

diffusers' `step` recomputes a handful of scalars, looks up the previous timestep and builds an
output object at every call: at batch 1 that Python is a tenth of a plan. `ScheduledUpdates`
takes the scalars from the scheduler itself once (the same tensor operations, in the same
dtype) and applies the update with the operations of diffusers' `step`, in its order, drawing
its noise the same way: the result is bit for bit diffusers' (`test_sampler.py` checks it). It
covers what the package configures (epsilon prediction, clipping or not, DDPM with its fixed
small variance, DDIM with any eta); anything else is refused at construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:  # imported where a scheduler is built (policy/schedulers.py)
    from diffusers import DDIMScheduler, DDPMScheduler


@dataclass(frozen=True)
class Update:
    """One update's scalars, computed as 0-d tensors in the scheduler's dtype and kept as the
    Python floats of those values: a tensor times a Python float is the same product in the
    tensor's dtype, without a 0-d tensor's dispatch at every operation."""

    sqrt_beta: float  # (1 - alpha_prod_t) ** 0.5
    sqrt_alpha: float  # alpha_prod_t ** 0.5
    original: float  # weight of the predicted clean sample
    current: float | None  # DDPM: weight of the current sample
    direction: float | None  # DDIM: weight of the predicted noise
    noise: float | None  # standard deviation of the noise added; None: none

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if value is not None:
                object.__setattr__(self, name, float(value))


@dataclass(frozen=True)
class Noising:
    """The scheduler's `add_noise` at one level, for float32 samples: clean samples and a
    noise draw -> `sqrt_alpha * clean + sqrt_one_minus * noise`, its scalars taken once as
    Update's are (the same products, bit for bit)."""

    sqrt_alpha: float  # alpha_prod ** 0.5
    sqrt_one_minus: float  # (1 - alpha_prod) ** 0.5

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            object.__setattr__(self, name, float(value))

    def __call__(self, clean: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        return self.sqrt_alpha * clean + self.sqrt_one_minus * noise


class ScheduledUpdates:
    """`apply(index, model_output, sample, generator)`: the update of the schedule's step
    `index`, as `scheduler.step(...).prev_sample`; `noising[index]`: `add_noise` at the level
    that update leaves the sample at (None after the last: clean)."""

    def __init__(self, scheduler: DDPMScheduler | DDIMScheduler, eta: float = 0.0) -> None:
        from diffusers import DDIMScheduler, DDPMScheduler

        config = scheduler.config
        if config.prediction_type != "epsilon" or config.thresholding:
            raise ValueError("precomputed updates cover epsilon prediction without "
                             "thresholding")
        self.clip = config.clip_sample_range if config.clip_sample else None
        if isinstance(scheduler, DDIMScheduler):
            self.updates = [self._ddim(scheduler, int(t), eta) for t in scheduler.timesteps]
        elif isinstance(scheduler, DDPMScheduler) and config.variance_type == "fixed_small":
            self.updates = [self._ddpm(scheduler, int(t)) for t in scheduler.timesteps]
        else:
            raise ValueError(f"no precomputed updates for {type(scheduler).__name__} "
                             f"({config.variance_type})")
        # After update i the sample is at the level of timestep i + 1 (clean after the last).
        alphas = scheduler.alphas_cumprod.to(torch.float32)  # add_noise's, in the samples' dtype
        self.noising: list[Noising | None] = [
            Noising(alphas[t] ** 0.5, (1 - alphas[t]) ** 0.5)
            for t in scheduler.timesteps[1:].tolist()] + [None]

    @staticmethod
    def _ddpm(scheduler: DDPMScheduler, t: int) -> Update:
        prev_t = scheduler.previous_timestep(t)
        alpha_prod_t = scheduler.alphas_cumprod[t]
        alpha_prod_t_prev = scheduler.alphas_cumprod[prev_t] if prev_t >= 0 else scheduler.one
        beta_prod_t = 1 - alpha_prod_t
        beta_prod_t_prev = 1 - alpha_prod_t_prev
        current_alpha_t = alpha_prod_t / alpha_prod_t_prev
        current_beta_t = 1 - current_alpha_t
        noise = scheduler._get_variance(t) ** 0.5 if t > 0 else None
        return Update(beta_prod_t ** 0.5, alpha_prod_t ** 0.5,
                      (alpha_prod_t_prev ** 0.5 * current_beta_t) / beta_prod_t,
                      current_alpha_t ** 0.5 * beta_prod_t_prev / beta_prod_t, None, noise)

    @staticmethod
    def _ddim(scheduler: DDIMScheduler, t: int, eta: float) -> Update:
        prev_t = t - scheduler.config.num_train_timesteps // scheduler.num_inference_steps
        alpha_prod_t = scheduler.alphas_cumprod[t]
        alpha_prod_t_prev = (scheduler.alphas_cumprod[prev_t] if prev_t >= 0
                             else scheduler.final_alpha_cumprod)
        beta_prod_t = 1 - alpha_prod_t
        std_dev_t = eta * scheduler._get_variance(t, prev_t) ** 0.5
        return Update(beta_prod_t ** 0.5, alpha_prod_t ** 0.5, alpha_prod_t_prev ** 0.5, None,
                      (1 - alpha_prod_t_prev - std_dev_t ** 2) ** 0.5,
                      std_dev_t if eta > 0 else None)

    def apply(self, index: int, model_output: torch.Tensor, sample: torch.Tensor,
              generator: torch.Generator | None) -> torch.Tensor:
        update = self.updates[index]
        original = (sample - update.sqrt_beta * model_output) / update.sqrt_alpha
        if self.clip is not None:
            original = original.clamp(-self.clip, self.clip)
        if update.current is not None:  # DDPM
            prev = update.original * original + update.current * sample
        else:  # DDIM
            prev = update.original * original + update.direction * model_output
        if update.noise is not None:
            noise = torch.randn(model_output.shape, generator=generator,
                                device=model_output.device, dtype=model_output.dtype)
            prev = prev + update.noise * noise
        return prev
