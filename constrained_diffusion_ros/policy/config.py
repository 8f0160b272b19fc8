"""The policy's configuration: everything needed to rebuild the network and its sampler.

Kept apart from the modelling code (as LeRobot does) so that a weights file's JSON can be read,
checked and printed without building a network.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

MAX_LEVELS = 6  # U-Net levels at most
MAX_WIDTH = 4096  # channels per level at most: more is a typo that would allocate gigabytes


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

    def __post_init__(self) -> None:
        """Refuse what would load and then fail at the first observation, or allocate
        gigabytes: every problem named at once."""
        problems = []
        for name in ("obs_dim", "action_dim", "n_obs_steps", "horizon", "n_action_steps",
                     "kernel_size", "n_groups", "diffusion_step_embed_dim",
                     "num_train_timesteps"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                problems.append(f"{name} must be a positive integer, got {value!r}")
        if problems:
            raise ValueError("policy config: " + "; ".join(problems))
        dims = self.down_dims
        if not 1 <= len(dims) <= MAX_LEVELS or not all(
                isinstance(d, int) and 1 <= d <= MAX_WIDTH and d % self.n_groups == 0
                for d in dims):
            problems.append(f"down_dims must be 1 to {MAX_LEVELS} widths of at most "
                            f"{MAX_WIDTH}, multiples of n_groups {self.n_groups}; got "
                            f"{list(dims)}")
        if self.horizon % 2 ** (len(dims) - 1):
            problems.append(f"horizon {self.horizon} must be a multiple of "
                            f"{2 ** (len(dims) - 1)} (the U-Net halves it {len(dims) - 1} times)")
        if self.first_executed + self.n_action_steps > self.horizon:
            problems.append(f"n_obs_steps - 1 + n_action_steps ({self.first_executed} + "
                            f"{self.n_action_steps}) exceeds horizon {self.horizon}")
        if self.kernel_size % 2 == 0:
            problems.append(f"kernel_size must be odd, got {self.kernel_size}")
        if self.prediction_type not in ("epsilon", "sample"):
            problems.append(f"prediction_type must be epsilon or sample, got "
                            f"{self.prediction_type!r}")
        for key, size in (("obs", self.obs_dim), ("action", self.action_dim)):
            stats = self.normalizer.get(key)
            if stats is not None and any(len(stats.get(b, ())) != size for b in ("min", "max")):
                problems.append(f"normalizer {key} needs min and max of {size} values")
        if problems:
            raise ValueError("policy config: " + "; ".join(problems))

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
