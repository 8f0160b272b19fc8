"""The report's 95% intervals on distributions whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean, wilson


def test_the_bootstrap_interval_covers_the_true_mean_about_95_percent_of_the_time() -> None:
    """200 samples of 25 episodes (the paper's protocol) from a known distribution: the
    percentile bootstrap covers the true mean in 88% to 99% of them (it runs a little short of
    95% at n = 25, as percentile intervals do), with the normal theory's width."""
    rng = np.random.default_rng(1)
    true_mean, sd, n = 0.7, 0.2, 25
    covered, widths = 0, []
    for k in range(200):
        sample = rng.normal(true_mean, sd, n)
        low, high = bootstrap_mean(sample, resamples=2000, seed=k)
        covered += low <= true_mean <= high
        widths.append(high - low)
    assert 0.88 <= covered / 200 <= 0.99
    assert np.mean(widths) == pytest.approx(2 * 1.96 * sd / np.sqrt(n), rel=0.15)


def test_the_bootstrap_is_seeded_and_collapses_on_a_constant_sample() -> None:
    values = np.arange(25.0)
    assert bootstrap_mean(values) == bootstrap_mean(values)
    assert bootstrap_mean(np.full(25, 0.0)) == (0.0, 0.0)  # r = 0 in every episode
    with pytest.raises(ValueError):
        bootstrap_mean([])


@pytest.mark.parametrize(("successes", "trials", "expected"), [
    (0, 25, (0.0, 0.1332)),  # no success is still not a rate of exactly 0
    (25, 25, (0.8668, 1.0)),
    (10, 100, (0.0552, 0.1744)),  # textbook values of Wilson's interval
])
def test_wilson_gives_the_known_intervals(successes: int, trials: int, expected) -> None:
    assert wilson(successes, trials) == pytest.approx(expected, abs=1e-4)


def test_wilson_refuses_impossible_counts() -> None:
    with pytest.raises(ValueError):
        wilson(3, 2)
    with pytest.raises(ValueError):
        wilson(0, 0)
