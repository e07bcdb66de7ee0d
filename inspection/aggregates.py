"""One score per scan from its per-point scores: the aggregates (``mean``, ``max``, ``median``, ``top<P>``, ``q<P>``)."""
import math
import re

import numpy as np

_AGGREGATE_RE = re.compile(r"^(mean|max|median|top(\d+(?:\.\d+)?)|q(\d+(?:\.\d+)?))$")


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


def aggregate(values, how="top1"):
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
