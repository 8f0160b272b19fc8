"""Min-max normalisation to [-1, 1], the reference's "limits" mode, with stats kept in JSON."""

from __future__ import annotations

import numpy as np
import torch


class MinMaxNormalizer:
    """Maps each feature linearly so that its [min, max] becomes [-1, 1].

    Features that never vary in the data (max == min) are only centred, so they cannot blow up.
    """

    def __init__(self, minimum: torch.Tensor, maximum: torch.Tensor) -> None:
        self.minimum = torch.as_tensor(minimum, dtype=torch.float32)
        self.maximum = torch.as_tensor(maximum, dtype=torch.float32)
        span = self.maximum - self.minimum
        self.scale = torch.where(span > 1e-6, 2.0 / span.clamp_min(1e-6), torch.ones_like(span))
        self.offset = -1.0 - self.minimum * self.scale
        self.offset = torch.where(span > 1e-6, self.offset, -self.minimum)

    @classmethod
    def fit(cls, data: np.ndarray | torch.Tensor) -> MinMaxNormalizer:
        flat = torch.as_tensor(np.asarray(data), dtype=torch.float32).reshape(-1, data.shape[-1])
        return cls(flat.min(dim=0).values, flat.max(dim=0).values)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale.to(x) + self.offset.to(x)

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.offset.to(x)) / self.scale.to(x)

    def to_dict(self) -> dict[str, list[float]]:
        return {"min": self.minimum.tolist(), "max": self.maximum.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, list[float]]) -> MinMaxNormalizer:
        try:
            minimum, maximum = torch.tensor(data["min"]), torch.tensor(data["max"])
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"normaliser stats need 'min' and 'max' lists: {error}") from error
        # Checked on the lists, which hold values wherever the tensors are made.
        if not all(np.isfinite(np.asarray(data[b], dtype=np.float64)).all()
                   for b in ("min", "max")):
            # NaN or inf turns every normalised value into NaN: the policy would run on noise
            raise ValueError("normaliser stats hold NaN or inf")
        return cls(minimum, maximum)
