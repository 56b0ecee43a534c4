"""Small statistics shared by the stages' measurements.

:func:`bootstrap_interval`: how far a number measured over a few dozen trials (synthesis trials,
processed sessions) can be trusted, by resampling the trials with replacement.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.stats import bootstrap

__all__ = ["bootstrap_interval"]


def bootstrap_interval(statistic: Callable[[np.ndarray], float], trials: int, *,
                       level: float = 0.95, resamples: int = 2000, seed: int = 0
                       ) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic(indices)`` over ``trials`` trials.

    Args:
        statistic: the number, computed from an (n,) int array of trial indices (a resample
            repeats some trials and leaves others out; the full set is ``np.arange(trials)``).
        trials: how many trials there are.
        level: confidence level; resamples, seed: bootstrap resamples and their random seed.

    Returns:
        (low, high); (NaN, NaN) with fewer than two trials.
    """
    if trials < 2:
        return math.nan, math.nan
    ci = bootstrap((np.arange(trials),), statistic, vectorized=False, n_resamples=resamples,
                   confidence_level=level, method="percentile",
                   rng=np.random.default_rng(seed)).confidence_interval
    return float(ci.low), float(ci.high)
