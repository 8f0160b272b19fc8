"""The policy's configuration: everything needed to rebuild the network and its sampler.

Kept apart from the modelling code (as LeRobot does) so that a weights file's JSON can be read,
checked and printed without building a network.
"""

from __future__ import annotations

import dataclasses
import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

MAX_LEVELS = 6  # U-Net levels at most
MAX_WIDTH = 4096  # channels per level at most: more is a typo that would allocate gigabytes
# Upper bounds of the size fields, each far above any PushT policy (the reference: 20
# observations, 2 actions, horizon 16, kernel 5, 100 training timesteps) yet low enough that a
# typo or a hostile config.json is refused at once instead of a MemoryError a minute later (as
# a horizon or num_train_timesteps of 10**9 would give). Longest horizon of the diffusion-policy
# papers: 64; DDPM's schedule: 1000 timesteps.
SIZE_LIMITS = {
    "obs_dim": 1024, "action_dim": 1024,  # features per observation / action
    "n_obs_steps": 256, "horizon": 256, "n_action_steps": 256,  # steps of a chunk
    "kernel_size": 63,  # a kernel wider than the longest horizon sees nothing more
    "n_groups": MAX_WIDTH, "diffusion_step_embed_dim": MAX_WIDTH,  # channels
    "num_train_timesteps": 10_000,  # the noise schedule's arrays hold one entry per timestep
}
ZONE_GRIDS = (16, 32, 64)  # zone raster sizes the encoder takes (it halves them three times)
# config.json is a few kB (22 normaliser pairs); anything near this is not a policy's config.
MAX_CONFIG_BYTES = 1 << 20


def regular_file(path: str | os.PathLike) -> Path:
    """`path`, refused (ValueError, one line naming it) unless it is a regular file: a FIFO
    blocks its reader until a writer comes, a device never ends. The core's one check before
    it opens a file given by a user (config.json, weights, YAML)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None
    if not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) \
            else "a device or socket"
        raise ValueError(f"{path} is {kind}, not a regular file")
    return path


def read_text_file(path: str | os.PathLike, max_bytes: int) -> str:
    """A user's text file, whole: regular (see `regular_file`, checked again on the opened
    file, so a file swapped for a FIFO in between cannot block) and at most `max_bytes` long
    (read so far and no further, whatever its size claims: /proc files say 0); any fault is one
    ValueError line naming the file."""
    path = regular_file(path)
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opens without a writer
        with os.fdopen(descriptor, "rb") as file:
            if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
                raise ValueError(f"{path} is not a regular file")
            data = file.read(max_bytes + 1)
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None
    if len(data) > max_bytes:
        raise ValueError(f"{path} is larger than {max_bytes} bytes: not a file of this kind")
    try:
        return data.decode()
    except UnicodeDecodeError as error:
        raise ValueError(f"{path} is not UTF-8 text (byte {error.start})") from None


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
    # A zone-aware policy also takes the zones in force: a `zone_grid` x `zone_grid` raster of
    # their coverage (zones/raster.py) through a small convolutional encoder into
    # `zone_features` more numbers of the condition. 0: the policy does not see zones.
    zone_grid: int = 0
    zone_features: int = 64
    zone_workspace: tuple[float, ...] = (0.0, 0.0, 512.0, 512.0)  # x_min, y_min, x_max, y_max px

    def __post_init__(self) -> None:
        """Refuse what would load and then fail at the first observation, or allocate
        gigabytes: every problem named at once."""
        problems = []
        for name, limit in SIZE_LIMITS.items():
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= limit:
                problems.append(f"{name} must be a positive integer up to {limit}, got "
                                f"{value!r}")
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
        if self.zone_grid and (not isinstance(self.zone_grid, int)
                               or self.zone_grid not in ZONE_GRIDS):
            problems.append(f"zone_grid must be 0 or one of {ZONE_GRIDS}, got "
                            f"{self.zone_grid!r}")
        if not isinstance(self.zone_features, int) or not 1 <= self.zone_features <= MAX_WIDTH:
            problems.append(f"zone_features must be a positive integer up to {MAX_WIDTH}, got "
                            f"{self.zone_features!r}")
        bounds = self.zone_workspace
        if not (isinstance(bounds, tuple) and len(bounds) == 4
                and all(isinstance(v, int | float) and math.isfinite(v) for v in bounds)
                and bounds[0] < bounds[2] and bounds[1] < bounds[3]):
            problems.append(f"zone_workspace must be 4 finite numbers x_min, y_min, x_max, "
                            f"y_max with the minima below the maxima, got {bounds!r}")
        if self.kernel_size % 2 == 0:
            problems.append(f"kernel_size must be odd, got {self.kernel_size}")
        if self.prediction_type not in ("epsilon", "sample"):
            problems.append(f"prediction_type must be epsilon or sample, got "
                            f"{self.prediction_type!r}")
        if not isinstance(self.normalizer, dict):
            problems.append("normalizer must be a mapping of obs and action statistics")
        else:
            problems += normalizer_problems(self.normalizer, self.obs_dim, self.action_dim)
        if problems:
            raise ValueError("policy config: " + "; ".join(problems))

    @property
    def global_cond_dim(self) -> int:
        return self.obs_dim * self.n_obs_steps + (self.zone_features if self.zone_grid else 0)

    @property
    def sees_zones(self) -> bool:
        """Whether the policy takes the zones in force as part of its condition."""
        return self.zone_grid > 0

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
        for key in ("down_dims", "zone_workspace"):
            if isinstance(data.get(key), list):
                data[key] = tuple(data[key])
        return cls(**data)


def normalizer_problems(normalizer: dict, obs_dim: int, action_dim: int) -> list[str]:
    """What is wrong with a config's normaliser statistics: a NaN or an infinity maps every
    observation to NaN, and a policy so loaded ran (and scored) without a word."""
    problems = []
    for key, size in (("obs", obs_dim), ("action", action_dim)):
        stats = normalizer.get(key)
        if stats is None:
            continue
        bounds = [stats.get(b) if isinstance(stats, dict) else None for b in ("min", "max")]
        if not all(isinstance(b, list | tuple) and len(b) == size for b in bounds):
            problems.append(f"normalizer {key} needs min and max of {size} values")
        elif not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                     for b in bounds for v in b):
            problems.append(f"normalizer {key} min and max must hold finite numbers only "
                            f"(a NaN, an infinity or text found)")
        elif any(low > high for low, high in zip(*bounds, strict=True)):
            problems.append(f"normalizer {key} has a min above its max")
    return problems
