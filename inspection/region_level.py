"""The region level: the anomaly-map value above which a good scan shows a defect region at the calibration's rate.

What it is drawn from
    Each good calibration scan's **map maximum** (:func:`inspection.regions.map_maximum`: the highest level at which
    its map still shows a region), one per scan, with the role its score had (:data:`inspection.threshold.ROLES`). A
    scan shows a region exactly when its map maximum exceeds the level, so the level is a threshold on map maxima,
    as the verdict's is on scores.

Exact when there are enough
    With at least 1 / alpha - 1 out-of-sample maxima the level is split-conformal on them
    (:func:`inspection.threshold.fit_threshold`): exact, whatever the maxima's distribution.

A predictive Pareto tail when there are not (:func:`pareto_tail_level`)
    A map maximum is the largest of many correlated point values: most good scans' lie in a narrow bulk, a few
    reach far above it where a view saw surface the model knows less well. Their logarithm is still right-skewed, so
    the verdict's log-normal tail (:mod:`inspection.threshold`) under-states the rate: over nine runs (three parts,
    three seeds), held-out good scans passed it 3.8-5.4 % of the time at a stated 2 % (docs/results_archive.md,
    "Region level"). The level models the upper half of the n maxima as Pareto: with k = n // 2 and u the (k+1)-th
    largest, the k log excesses y_i = log(x_i / u) are Exponential with an unknown rate a. With S = sum y_i and a's
    scale-invariant prior (1 / a), a new exceedance's log excess has the predictive tail P(Y > y) = (S / (S + y))^k;
    a new good scan passes u with probability p_u = (k + 1) / (n + 1) (an order statistic). So

        level = u exp(S ((p_u / alpha)^(1 / k) - 1))

    flags a new good scan with probability exactly alpha, averaged over calibration draws, when the maxima are Pareto
    above their median: the chance of passing u averages p_u and, independently of it (the Exponential's lack of
    memory), the chance of then passing the level averages E[exp(-a S c)] = (1 + c)^-k = alpha / p_u, aS being
    Gamma(k, 1). The tail's weight is the data's own, not a fixed family's. Every role's maxima enter it: a
    cross-fitted training scan's map maximum was measured no lower than a held-back scan's (the same archive
    section), unlike its score.
"""
import math

import numpy as np

from .threshold import OUT_OF_SAMPLE, allowed_exceedances, check_alpha, fit_threshold

MIN_TAIL_MAXIMA = 3  # the tail needs k = n // 2 >= 1 exceedances above a (k+1)-th largest


def pareto_tail_level(maxima, alpha):
    """The predictive Pareto level (module docstring) of ``maxima`` (n,) positive, at rate ``alpha`` in (0, 1).

    Returns
    -------
    float
        u exp(S ((p_u / alpha)^(1 / k) - 1)) with k = n // 2; the (k+1)-th largest maximum itself when alpha >= p_u.
    """
    x = np.sort(np.asarray(maxima, dtype=np.float64).reshape(-1))[::-1]
    if len(x) < MIN_TAIL_MAXIMA or not np.all(np.isfinite(x)) or np.any(x <= 0):
        raise ValueError(f"the Pareto tail needs >= {MIN_TAIL_MAXIMA} positive finite map maxima, got {x.tolist()}")
    alpha = check_alpha(alpha)
    n = len(x)
    k = n // 2
    u = float(x[k])
    spread = float(np.sum(np.log(x[:k] / u)))
    passes_u = (k + 1) / (n + 1)
    if alpha >= passes_u:
        return u
    return u * math.exp(spread * ((passes_u / alpha) ** (1 / k) - 1))


def region_level(maxima, alpha, roles=None):
    """The region level (standard deviations of the map) from good calibration scans' map maxima (n,) with their
    ``roles`` (None: all held back) at rate ``alpha``: split-conformal on the out-of-sample maxima when there are at
    least 1 / alpha - 1 of them, else :func:`pareto_tail_level` of all, else (fewer than ``MIN_TAIL_MAXIMA``) the
    verdict threshold's rule (:func:`inspection.threshold.fit_threshold`). A good scan's map exceeds it anywhere at
    about rate ``alpha``."""
    alpha = check_alpha(alpha)
    maxima = np.asarray(maxima, dtype=np.float64).reshape(-1)
    if len(maxima) == 0 or not np.all(np.isfinite(maxima)):
        raise ValueError(f"region_level needs finite map maxima of good scans, got {maxima!r}")
    maxima = np.maximum(maxima, 1e-6)  # a scan too small to show any region has maximum 0
    if roles is not None and len(list(roles)) != len(maxima):
        raise ValueError(f"region_level needs one role per map maximum ({len(maxima)}), got {len(list(roles))}")
    out_of_sample = (np.ones(len(maxima), bool) if roles is None else np.isin(np.asarray(list(roles)), OUT_OF_SAMPLE))
    if allowed_exceedances(int(out_of_sample.sum()), alpha) >= 0 or len(maxima) < MIN_TAIL_MAXIMA:
        return float(fit_threshold(maxima, alpha, roles).value)
    return pareto_tail_level(maxima, alpha)
