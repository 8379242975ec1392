"""95 % confidence intervals of evaluation statistics, the one place they are computed.

- a mean over n values: Student's t interval ``mean +- t_{0.975, n-1} s / sqrt(n)`` with ``s``
  the sample standard deviation (none for n < 2); a paired difference is the mean of the
  per-pair differences;
- a rate k / n: Wilson's score interval
  ``(p + z^2/2n +- z sqrt(p (1-p) / n + z^2 / 4n^2)) / (1 + z^2/n)``, z = 1.96, which stays
  inside [0, 1] and is not empty at k = 0;
- the difference of two independent means: Welch's t interval
  ``mean_b - mean_a +- t_{0.975, nu} sqrt(s_a^2 / n_a + s_b^2 / n_b)`` with ``nu`` the
  Welch-Satterthwaite degrees of freedom, rounded down.
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import Optional, Sequence

from mmpc.config import require_int

#: The standard normal 0.975 quantile (1.96).
Z_975 = NormalDist().inv_cdf(0.975)


def t_quantile_975(dof: int) -> float:
    """Student's t 0.975 quantile for ``dof`` >= 1 degrees of freedom.

    Exact for 1 and 2 (``tan(0.475 pi)``, ``sqrt(2) * 0.95 / sqrt(1 - 0.95^2)``); from 3 on the
    Cornish-Fisher expansion in 1/dof to the fourth order around the normal quantile (relative
    error < 2e-3 at dof = 3, < 1e-5 from dof = 10).
    """
    require_int("", low=1, dof=dof)
    if dof == 1:
        return math.tan(0.475 * math.pi)
    if dof == 2:
        return 0.95 * math.sqrt(2.0 / (1.0 - 0.95**2))
    z = Z_975
    terms = (
        (z**3 + z) / 4,
        (5 * z**5 + 16 * z**3 + 3 * z) / 96,
        (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384,
        (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160,
    )
    return z + sum(term / dof ** (k + 1) for k, term in enumerate(terms))


def _finite_values(values: Sequence[Optional[float]]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(v)]


def _mean_and_variance(finite: Sequence[float]) -> tuple[float, float]:
    """Mean and sample variance of two or more values."""
    n = len(finite)
    mean = sum(finite) / n
    return mean, sum((v - mean) ** 2 for v in finite) / (n - 1)


def mean_ci(values: Sequence[Optional[float]]) -> tuple[Optional[float], Optional[list[float]]]:
    """Mean and 95 % t interval ``[low, high]`` of the finite ``values`` (``None``: none / n < 2)."""
    finite = _finite_values(values)
    if not finite:
        return None, None
    n = len(finite)
    if n < 2:
        return sum(finite) / n, None
    mean, variance = _mean_and_variance(finite)
    half = t_quantile_975(n - 1) * math.sqrt(variance) / math.sqrt(n)
    return mean, [mean - half, mean + half]


def wilson_ci(successes: int, trials: int) -> Optional[list[float]]:
    """95 % Wilson score interval of a rate ``successes / trials`` (``None`` for no trials)."""
    if trials <= 0:
        return None
    p = successes / trials
    denominator = 1 + Z_975**2 / trials
    centre = (p + Z_975**2 / (2 * trials)) / denominator
    half = Z_975 * math.sqrt(p * (1 - p) / trials + Z_975**2 / (4 * trials**2)) / denominator
    # The bounds are exact at the ends: rounding would put 0 (or 1) just outside its own interval.
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return [low, high]


def welch_ci(a: Sequence[Optional[float]], b: Sequence[Optional[float]]) -> tuple[Optional[float], Optional[list[float]]]:
    """``mean(b) - mean(a)`` of the finite values of two independent samples and its 95 % Welch
    t interval ``[low, high]`` (``None``: a sample empty / with fewer than two values)."""
    first, second = _finite_values(a), _finite_values(b)
    if not first or not second:
        return None, None
    if len(first) < 2 or len(second) < 2:
        return sum(second) / len(second) - sum(first) / len(first), None
    (mean_a, variance_a), (mean_b, variance_b) = _mean_and_variance(first), _mean_and_variance(second)
    difference = mean_b - mean_a
    share_a, share_b = variance_a / len(first), variance_b / len(second)
    if share_a + share_b == 0.0:
        return difference, [difference, difference]
    dof = (share_a + share_b) ** 2 / (share_a**2 / (len(first) - 1) + share_b**2 / (len(second) - 1))
    half = t_quantile_975(max(1, math.floor(dof))) * math.sqrt(share_a + share_b)
    return difference, [difference - half, difference + half]
