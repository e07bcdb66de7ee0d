"""Per-point anomaly scores of a scan under a stochastic field, and their aggregation into one score per scan.

Every score here is "higher = more anomalous". The point scores read the field at the scan's points, which must be
in the field's own (world) frame, i.e. the collection frame for a model trained on a collection.
"""
import math
import re

import numpy as np

POINT_SCORES = ("residual", "nll", "local", "distance")
REFERENCE_NEIGHBOURS = 16
# |grad E f| is unitless (~1 on the mean surface of a well-fitted field, -> 0 far from it, where E f saturates); the
# floor keeps E f / |grad E f| finite there while still growing well past the saturation distance
GRADIENT_FLOOR = 0.2
# which quantity each per-location point score compares with its reference
REFERENCE_QUANTITY = {"local": "mean", "distance": "distance"}
_MIN_VARIANCE = 1e-20
_AGGREGATE_RE = re.compile(r"^(mean|max|median|top(\d+(?:\.\d+)?)|q(\d+(?:\.\d+)?))$")


def point_scores(field, points, kind="residual", noise=None, reference=None):
    """Per-point anomaly scores of ``points`` under ``field`` (higher = more anomalous).

    With m = E f(p), v = Var f(p) and total = v + noise^2 (the noise floor):

    * ``'nll'``: the paper's negative log likelihood of f(p) = 0, 0.5 * (m^2 / total + log(2 pi total));
    * ``'residual'``: the standardized residual |m| / sqrt(total), the square root of twice the NLL's data term.
      It drops the log-variance term, which varies from view to view with how densely training covered a region
      (DESIGN.md) and carries no information about the point itself, and it is unitless (in standard deviations),
      so one colour range serves every part.
    * ``'local'``: the residual standardized against good scans at the same place, |m - m_ref| /
      sqrt(s_ref^2 + noise^2), where m_ref and s_ref are the mean and standard deviation of E f over the
      ``REFERENCE_NEIGHBOURS`` nearest points of good scans, each under its own projected field (a
      :class:`LocalReference`). A field that misses the part in the same way on every good scan (a rounded edge, a
      drifting face) then stops looking anomalous there: the noise floor is modelled per location.
    * ``'distance'`` (the default with a reference): like ``'local'``, but on d = m / max(|grad m|,
      ``GRADIENT_FLOOR``), the first-order signed distance to the mean surface (world units), instead of m itself.
      E f is an integral of the GP's normal field, which vanishes two kernel lengthscales off the points, so E f
      saturates there: a pit or a bump deeper than that scores no higher than a shallow one under ``'local'``,
      ``'residual'`` or ``'nll'``, and no higher than the model's own error on good parts at a hard feature. d
      follows the depth while |grad m| >= the floor and then stays at |m| / floor: points off the field's shell
      are lifted by up to 1 / floor = 5 x relative to points near the mean surface (where |grad m| ~ 1), which is
      where the defects are and good scans are not. (Measured on fandisk with ``benchmarks/inspect_fandisk.py``:
      object AUROC 0.977 -> 0.994, missing material 0.938 -> 1.000.)

    Parameters
    ----------
    field : object with ``mean(x)`` and ``variance(x)`` ((m, 3) -> (m,)) and a ``noise`` attribute
        E.g. a :class:`autodecoder.StochasticField`.
    points : (m, 3) array
        In the field's frame.
    kind : {'residual', 'nll', 'local', 'distance'}
    noise : float, optional
        Measurement noise standard deviation (the noise floor), in the field's length units; default
        ``field.noise``.
    reference : LocalReference
        Needed by ``'local'`` and ``'distance'``, built on the same quantity (``REFERENCE_QUANTITY[kind]``).

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
    if kind in REFERENCE_QUANTITY:
        if reference is None:
            raise ValueError(f"point_score {kind!r} needs a LocalReference (calibrate with the training scans)")
        if reference.quantity != REFERENCE_QUANTITY[kind]:
            raise ValueError(f"point_score {kind!r} needs a reference of {REFERENCE_QUANTITY[kind]!r} values, got one "
                             f"of {reference.quantity!r} values")
        value = field_quantity(field, points, reference.quantity)
        m_ref, s_ref = reference.stats(points)
        return np.abs(value - m_ref) / np.sqrt(s_ref**2 + max(noise**2, _MIN_VARIANCE))
    mean = np.asarray(field.mean(points), dtype=np.float64)
    var = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    total = np.maximum(var + noise**2, _MIN_VARIANCE)
    if kind == "residual":
        return np.abs(mean) / np.sqrt(total)
    return 0.5 * (mean**2 / total + np.log(2 * math.pi * total))


def field_quantity(field, points, quantity):
    """What a per-location reference compares: E f (``'mean'``) or the first-order signed distance E f /
    max(|grad E f|, ``GRADIENT_FLOOR``) (``'distance'``, needs ``field.mean_gradient``) at (m, 3) points -> (m,)."""
    mean = np.asarray(field.mean(points), dtype=np.float64)
    if quantity == "mean":
        return mean
    if quantity == "distance":
        if not hasattr(field, "mean_gradient"):
            raise ValueError(f"the 'distance' point score needs a field with mean_gradient(x); "
                             f"{type(field).__name__} has none (use point_score 'local' or 'residual')")
        grad = np.linalg.norm(np.asarray(field.mean_gradient(points), dtype=np.float64), axis=1)
        return mean / np.maximum(grad, GRADIENT_FLOOR)
    raise ValueError(f"reference quantity must be 'mean' or 'distance', got {quantity!r}")


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


class LocalReference:
    """What E f looks like at the points of good scans, each under its own projected field: the per-location noise
    floor of the ``'local'`` point score.

    Parameters
    ----------
    points : (n, 3) array
        Points of good scans (model frame).
    values : (n,) array
        The quantity at each point under its own scan's projected field.
    k : int
        Neighbours averaged per query point.
    quantity : {'mean', 'distance'}
        What ``values`` are (:func:`field_quantity`).
    """

    def __init__(self, points, values, k=REFERENCE_NEIGHBOURS, quantity="mean"):
        self.points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        self.values = np.asarray(values, dtype=np.float32).reshape(-1)
        if len(self.points) != len(self.values) or len(self.points) < k:
            raise ValueError(f"LocalReference needs >= {k} points with one value each, got {len(self.points)} "
                             f"points and {len(self.values)} values")
        if quantity not in ("mean", "distance"):
            raise ValueError(f"reference quantity must be 'mean' or 'distance', got {quantity!r}")
        self.k = int(k)
        self.quantity = quantity
        self._tree = None

    @classmethod
    def from_fields(cls, scans_and_fields, max_points=60000, seed=0, k=REFERENCE_NEIGHBOURS, quantity="mean"):
        """Build from (points (m, 3), field) pairs; randomly subsampled to ``max_points`` (seeded)."""
        pts, vals = [], []
        for points, field in scans_and_fields:
            points = np.asarray(points, dtype=np.float64)
            pts.append(points)
            vals.append(field_quantity(field, points, quantity))
        pts, vals = np.concatenate(pts), np.concatenate(vals)
        if len(pts) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
            pts, vals = pts[keep], vals[keep]
        return cls(pts, vals, k, quantity)

    def stats(self, points):
        """Local mean and standard deviation of the reference values around each point: (m,), (m,)."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.points)
        _, idx = self._tree.query(np.asarray(points, dtype=np.float64), self.k)
        v = self.values[idx].astype(np.float64)  # (m, k)
        return v.mean(1), v.std(1)

    def as_dict(self):
        import torch

        return {"points": torch.from_numpy(self.points.copy()), "values": torch.from_numpy(self.values.copy()),
                "k": self.k, "quantity": self.quantity}

    @classmethod
    def from_dict(cls, d):
        return cls(np.asarray(d["points"]), np.asarray(d["values"]), int(d.get("k", REFERENCE_NEIGHBOURS)),
                   str(d.get("quantity", "mean")))
