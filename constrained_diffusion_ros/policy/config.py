"""The policy's configuration: everything needed to rebuild the network and its sampler.

Kept apart from the modelling code (as LeRobot does) so that a weights file's JSON can be read,
checked and printed without building a network.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


@dataclass(frozen=True)
class PolicyConfig:
    """Architecture, horizons and noise schedule of a low-dimensional PushT diffusion policy."""

    obs_dim: int = 20  # 9 block keypoints (x, y) + pusher (x, y)
    action_dim: int = 2  # pusher target (x, y) in workspace pixels
    n_obs_steps: int = 2
    horizon: int = 16
    n_action_steps: int = 8
    down_dims: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 5
    n_groups: int = 8
    diffusion_step_embed_dim: int = 256
    num_train_timesteps: int = 100
    beta_schedule: str = "squaredcos_cap_v2"
    prediction_type: str = "epsilon"
    clip_sample: bool = True
    normalizer: dict[str, dict[str, list[float]]] = field(default_factory=dict)

    @property
    def global_cond_dim(self) -> int:
        return self.obs_dim * self.n_obs_steps

    @property
    def first_executed(self) -> int:
        """Index of the chunk's waypoint for the current step (the reference's `To - 1`)."""
        return self.n_obs_steps - 1

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> PolicyConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown policy config keys: {', '.join(unknown)}")
        data = dict(data)
        if "down_dims" in data:
            data["down_dims"] = tuple(data["down_dims"])
        return cls(**data)
