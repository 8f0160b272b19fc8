"""95% confidence intervals for the report's cells, so a difference is claimed only where the
intervals support it: a percentile bootstrap over episodes for means (s, r), Wilson's score
interval for rates (success)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

LEVEL = 0.95
RESAMPLES = 10_000
Z_95 = 1.959963984540054  # standard normal quantile at 0.975


def bootstrap_mean(values: ArrayLike, level: float = LEVEL, resamples: int = RESAMPLES,
                   seed: int = 0) -> tuple[float, float]:
    """(low, high) of the mean of `values` (one per episode): percentiles of the means of
    `resamples` resamples drawn with replacement, all at once. Seeded, so a report is
    reproducible; a constant sample gives a zero-width interval."""
    x = np.asarray(values, dtype=np.float64).ravel()
    if len(x) == 0:
        raise ValueError("no values to bootstrap")
    draws = np.random.default_rng(seed).integers(0, len(x), size=(resamples, len(x)))
    means = x[draws].mean(axis=1)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(means, [tail, 100 - tail])
    return float(low), float(high)


def wilson(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """(low, high) of a success rate (Wilson's score interval): sound at 0 or n successes,
    where the normal approximation collapses to a point."""
    if trials <= 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials > 0, got {successes} of "
                         f"{trials}")
    p, n, z2 = successes / trials, trials, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)
