"""Per-point anomaly scores of a scan under a stochastic field, and their aggregation into one score per scan.

Every score here is "higher = more anomalous". The point scores read the field at the scan's points, which must be
in the field's own (world) frame, i.e. the collection frame for a model trained on a collection.
"""
import math
import re

import numpy as np

POINT_SCORES = ("residual", "nll")
_MIN_VARIANCE = 1e-20
_AGGREGATE_RE = re.compile(r"^(mean|max|median|top(\d+(?:\.\d+)?)|q(\d+(?:\.\d+)?))$")


def point_scores(field, points, kind="residual", noise=None):
    """Per-point anomaly scores of ``points`` under ``field`` (higher = more anomalous).

    With m = E f(p), v = Var f(p) and total = v + noise^2 (the noise floor):

    * ``'nll'``: the paper's negative log likelihood of f(p) = 0, 0.5 * (m^2 / total + log(2 pi total));
    * ``'residual'``: the standardized residual |m| / sqrt(total), the square root of twice the NLL's data term.
      It drops the log-variance term, which varies from view to view with how densely training covered a region
      (DESIGN.md) and carries no information about the point itself, and it is unitless (in standard deviations),
      so one colour range serves every part.

    Parameters
    ----------
    field : object with ``mean(x)`` and ``variance(x)`` ((m, 3) -> (m,)) and a ``noise`` attribute
        E.g. a :class:`autodecoder.StochasticField`.
    points : (m, 3) array
        In the field's frame.
    kind : {'residual', 'nll'}
    noise : float, optional
        Measurement noise standard deviation (the noise floor), in the field's length units; default
        ``field.noise``.

    Returns
    -------
    (m,) float64 array
    """
    if kind not in POINT_SCORES:
        raise ValueError(f"point_score must be one of {POINT_SCORES}, got {kind!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (m, 3), got {points.shape}")
    if len(points) == 0:
        raise ValueError("points: the scan has no points to score")
    noise = float(getattr(field, "noise", 0.0) if noise is None else noise)
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    mean = np.asarray(field.mean(points), dtype=np.float64)
    var = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    total = np.maximum(var + noise**2, _MIN_VARIANCE)
    if kind == "residual":
        return np.abs(mean) / np.sqrt(total)
    return 0.5 * (mean**2 / total + np.log(2 * math.pi * total))


def check_aggregate(name):
    """Validate an aggregate name; returns it. See :func:`aggregate` for the names."""
    if not isinstance(name, str) or not _AGGREGATE_RE.match(name):
        raise ValueError(f"aggregate must be 'mean', 'max', 'median', 'top<P>' (mean of the worst P % of the "
                         f"points, 0 < P <= 100) or 'q<P>' (P-th percentile), got {name!r}")
    m = _AGGREGATE_RE.match(name)
    p = m.group(2) or m.group(3)
    if p is not None and not 0 < float(p) <= 100:
        raise ValueError(f"aggregate {name!r}: the percentage must be in (0, 100], got {p}")
    return name


def aggregate(values, how="top5"):
    """One score per scan from its per-point scores (higher = more anomalous).

    Parameters
    ----------
    values : (m,) array
        Per-point scores, m >= 1.
    how : str
        ``'mean'`` (the paper's), ``'max'``, ``'median'``, ``'top<P>'``: the mean of the ceil(P % * m) largest
        values (``'top5'``: the worst 5 % of the points), ``'q<P>'``: the P-th percentile (linear interpolation).

    Returns
    -------
    float
    """
    check_aggregate(how)
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(values) == 0:
        raise ValueError("cannot aggregate the scores of a scan with no points")
    if how == "mean":
        return float(values.mean())
    if how == "max":
        return float(values.max())
    if how == "median":
        return float(np.median(values))
    if how.startswith("top"):
        k = max(1, int(math.ceil(float(how[3:]) / 100 * len(values))))
        return float(np.partition(values, len(values) - k)[len(values) - k:].mean())
    return float(np.percentile(values, float(how[1:])))
