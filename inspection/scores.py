"""Per-point anomaly scores of a scan under a stochastic field, and their aggregation into one score per scan.

Every score here is "higher = more anomalous". The point scores read the field at the scan's points, which must be
in the field's own (world) frame, i.e. the collection frame for a model trained on a collection.
"""
import math
import re
from dataclasses import dataclass

import numpy as np




@dataclass(frozen=True)
class PointScore:
    """One per-point score of the registry :data:`POINT_SCORES`.

    Attributes
    ----------
    name : str
    reference : bool
        Whether it compares the scan with good scans at the same place (a :class:`LocalReference` built from the
        model's training scans: calibration then needs them).
    in_deviations : bool
        Whether its values are standardized residuals, in standard deviations (the maps' fixed colour range,
        :mod:`inspection.maps`); the NLL is in nats.
    summary : str
        One line for the command line's help.
    """

    name: str
    reference: bool
    in_deviations: bool
    summary: str


# The per-point scores, the one list the estimator, the command line's choices, the maps and the benchmarks read
# (formulas: point_scores). The default is 'joint' where the training scans give a reference, else 'residual'.
POINT_SCORES = {s.name: s for s in (
    PointScore("joint", True, True, "the field's distance residual and the good scans' own surface together (default)"),
    PointScore("distance", True, True, "the first-order distance to the mean surface against good scans there"),
    PointScore("residual", False, True, "the standardized residual |E f| / sd (needs no reference)"),
    PointScore("nll", False, False, "the paper's negative log likelihood of f = 0"),
)}
REFERENCE_NEIGHBOURS = 16
# |grad E f| is unitless (~1 on the mean surface of a well-fitted field, -> 0 far from it, where E f saturates); the
# floor keeps E f / |grad E f| finite there while still growing well past the saturation distance
GRADIENT_FLOOR = 0.2
# the quantity the per-location point scores compare with their reference (field_quantity)
REFERENCE_QUANTITY = "distance"
# a reference point within this many reference bounding-box diagonals of a scored point is that point itself (a
# rendered view of a template shares its points with the other views of that template): the reference surface's
# plane is fitted without it
SELF_DISTANCE = 1e-6
# candidates per plane neighbour searched for points on the same side as the scored point (LocalReference.surface)
SURFACE_CANDIDATES = 4
_MIN_VARIANCE = 1e-20
_AGGREGATE_RE = re.compile(r"^(mean|max|median|top(\d+(?:\.\d+)?)|q(\d+(?:\.\d+)?))$")


def point_scores(field, points, kind="residual", noise=None, reference=None, normals=None, origin=None):
    """Per-point anomaly scores of ``points`` under ``field`` (higher = more anomalous).

    With m = E f(p), v = Var f(p) and total = v + noise^2 (the noise floor):

    * ``'nll'``: the paper's negative log likelihood of f(p) = 0, 0.5 * (m^2 / total + log(2 pi total));
    * ``'residual'``: the standardized residual |m| / sqrt(total), the square root of twice the NLL's data term.
      It drops the log-variance term, which varies from view to view with how densely training covered a region
      (measured: docs/results.md, "The per-cloud NLL") and carries no information about the point itself, and it
      is unitless (in standard deviations), so one colour range serves every part.
    * ``'distance'``: d = m / max(|grad m|, ``GRADIENT_FLOOR``), the first-order signed distance to the mean
      surface (world units), standardized against good scans at the same place, |d - d_ref| / sqrt(s_ref^2 +
      noise^2), where d_ref and s_ref are the mean and standard deviation of d over the ``REFERENCE_NEIGHBOURS``
      nearest points of good scans, each under its own projected field (a :class:`LocalReference`). A field that
      misses the part in the same way on every good scan (a rounded edge, a drifting face) then stops looking
      anomalous there: the noise floor is modelled per location. The distance rather than E f itself:
      E f is an integral of the GP's normal field, which vanishes two kernel lengthscales off the points, so E f
      saturates there: a pit or a bump deeper than that scores no higher than a shallow one under E f,
      ``'residual'`` or ``'nll'``, and no higher than the model's own error on good parts at a hard feature. d
      follows the depth while |grad m| >= the floor and then stays at |m| / floor: points off the field's shell
      are lifted by up to 1 / floor = 5 x relative to points near the mean surface (where |grad m| ~ 1), which is
      where the defects are and good scans are not (figures: docs/results.md#the-per-point-score).
    * ``'joint'`` (the default with a reference): the ``'distance'`` score z_d and the reference surface's z_s (:meth:`LocalReference.surface_scores`:
      the point's offset from the plane through its nearest good-scan points) taken together as two independent
      standardized residuals, sqrt((z_d^2 + z_s^2) / 2) (:func:`joint_score`). The projected field errs at a
      scan's borders and at grazing angles, where the good scans' points still lie on the part; the good scans'
      points do not follow the scan's own field and are noisy and sparse, where the field is smooth. A point scores
      high only when its residual is large under both on average, in the same units as the other scores.

    Parameters
    ----------
    field : object with ``mean(x)`` and ``variance(x)`` ((m, 3) -> (m,)) and a ``noise`` attribute
        E.g. a :class:`autodecoder.StochasticField`.
    points : (m, 3) array
        In the field's frame.
    kind : str
        A name of :data:`POINT_SCORES`.
    noise : float, optional
        Measurement noise standard deviation (the noise floor), in the field's length units; default
        ``field.noise``.
    reference : LocalReference
        Needed by the scores with ``POINT_SCORES[kind].reference`` (``'distance'`` and ``'joint'``).
    normals, origin : (m, 3) array and (3,) array, optional
        The scan's normals and sensor origin: with both, the reference scores' noise grows where the sensor's ray
        grazes the surface (:func:`autodecoder.scanning.sensor.grazing_factor`, weighted by the reference's ``grazing_scale``); with the
        normals, ``'joint'``'s reference surface is fitted through points on the same side
        (:meth:`LocalReference.surface`).

    Returns
    -------
    (m,) float64 array
    """
    if kind not in POINT_SCORES:
        raise ValueError(f"point_score must be one of {tuple(POINT_SCORES)}, got {kind!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (m, 3), got {points.shape}")
    if len(points) == 0:
        raise ValueError("points: the scan has no points to score")
    noise = float(getattr(field, "noise", 0.0) if noise is None else noise)
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    if POINT_SCORES[kind].reference:
        if reference is None:
            raise ValueError(f"point_score {kind!r} needs a LocalReference (calibrate with the training scans)")
        value, variance = field_quantity(field, points, reference.quantity, with_variance=True)
        from autodecoder.scanning.sensor import grazing_factor

        grazing = None if origin is None or normals is None else grazing_factor(points, normals, origin)
        return reference_scores(reference, kind, points, value, variance, noise, grazing, normals)
    mean = np.asarray(field.mean(points), dtype=np.float64)
    var = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    total = np.maximum(var + noise**2, _MIN_VARIANCE)
    if kind == "residual":
        return np.abs(mean) / np.sqrt(total)
    return 0.5 * (mean**2 / total + np.log(2 * math.pi * total))


def joint_score(distance_scores, surface_scores):
    """sqrt((z_d^2 + z_s^2) / 2) of two standardized residuals of the same points, elementwise.

    Under a good part each residual is ~N(0, 1); taken as independent, -log of their joint density is
    (z_d^2 + z_s^2) / 2 up to a constant, and its square root keeps the score in standard deviations (a point 2
    deviations off under both scores 2), which the log-normal tail of :mod:`inspection.threshold` and the maps'
    fixed colour range expect. Equal weights: neither residual is trusted more a priori.

    Parameters
    ----------
    distance_scores, surface_scores : (m,) arrays >= 0

    Returns
    -------
    (m,) float64 array
    """
    a = np.asarray(distance_scores, dtype=np.float64)
    b = np.asarray(surface_scores, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"joint_score needs one surface score per distance score, got shapes {a.shape} and {b.shape}")
    return np.sqrt((a**2 + b**2) / 2)


def reference_scores(reference, kind, points, value, variance, noise, grazing=None, normals=None):
    """The per-location point score ``kind`` (``'distance'`` or ``'joint'``) of (m, 3) points whose
    compared quantity (m,) and field variance (m,) are given, against ``reference`` (a :class:`LocalReference`);
    ``grazing`` (m,) and the points' ``normals`` (m, 3) (for the reference surface's side) or None. Returns (m,)
    float64."""
    scores = reference.standardized(points, value, variance, noise, grazing)
    if kind == "joint":
        scores = joint_score(scores, reference.surface_scores(points, noise, grazing, normals))
    return scores


def field_quantity(field, points, quantity=REFERENCE_QUANTITY, with_variance=False):
    """What a per-location reference compares, at (m, 3) points: the first-order signed distance to the mean surface
    d = E f / max(|grad E f|, ``GRADIENT_FLOOR``) (world units; needs ``field.mean_gradient``).

    Returns
    -------
    value : (m,) float64
    variance : (m,) float64, only with ``with_variance``
        The field's own variance in the same units, Var f / max(|grad E f|, ``GRADIENT_FLOOR``)^2 (the first-order
        propagation of Var f through d).
    """
    if quantity != REFERENCE_QUANTITY:
        raise ValueError(f"reference quantity must be {REFERENCE_QUANTITY!r} (the point score 'local', on E f itself, "
                         f"is retired), got {quantity!r}")
    from autodecoder.field.protocol import check_field

    check_field(field)
    mean = np.asarray(field.mean(points), dtype=np.float64)
    grad = np.linalg.norm(np.asarray(field.mean_gradient(points), dtype=np.float64), axis=1)
    scale = np.maximum(grad, GRADIENT_FLOOR)
    if not with_variance:
        return mean / scale
    variance = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    return mean / scale, variance / scale**2


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
    """What good scans look like at each place: the per-location noise floor of the ``'distance'`` and ``'joint'``
    point scores.

    A point p of a scan, with quantity v(p) under the scan's projected field (:func:`field_quantity`) and the field's
    own variance u(p) in the same units, is scored

        |v(p) - m_ref(p)| / sqrt(s_ref(p)^2 + variance_scale * u(p) + noise^2 (1 + grazing_scale * g(p))),

    where m_ref and s_ref are the mean and standard deviation of v over the ``k`` nearest points of good scans, each
    under its own projected field. s_ref models how much good scans vary where many of them were seen; u, the
    stochastic field's variance, is large where the training saw little (a surface seen by few views, or at a grazing
    angle), where s_ref rests on few or distant neighbours. g = 1 / cos^2 - 1 (:func:`autodecoder.scanning.sensor.grazing_factor`, 0 when the
    sensor origin is unknown) lets the measurement noise grow where the sensor's ray grazes the surface, which is
    where good scans' worst points lie (at a view's border, near silhouettes). ``variance_scale`` and
    ``grazing_scale`` are calibrated on good scans (:meth:`fit_noise_model`); both 0 is the reference alone.

    The good scans' points also describe the part's surface by themselves, independently of any field:
    :meth:`surface_scores` scores a point by its offset from the plane through its ``k`` nearest distinct reference
    points (the ``'joint'`` point score).

    Parameters
    ----------
    points : (n, 3) array
        Points of good scans (model frame).
    values : (n,) array
        The quantity at each point under its own scan's projected field.
    k : int
        Neighbours averaged per query point.
    quantity : {'distance'}
        What ``values`` are (:func:`field_quantity`).
    variance_scale : float >= 0
        Weight of the field's own variance in the score's denominator.
    grazing_scale : float >= 0
        Growth of the noise with the grazing factor.
    owners : (n,) int array, optional
        Which good scan each point came from; lets :meth:`without` leave one scan out (cross-fitting). Not stored.
    surface_points : (n2, 3) array, optional
        The points of :meth:`surface` (model frame), when they should be more than ``points``: every good training
        scan's points, not only those of the scans projected for the values (a part seen by few views is missing
        from a subset of them). None: ``points``.
    surface_owners : (n2,) int array, optional
        Like ``owners``, for ``surface_points`` (the same scan numbers; a scan that is not one of ``points``' gets a
        number no ``owners`` entry has). Not stored.
    surface_normals : (n2, 3) array, optional
        Unit outward normals of ``surface_points``: with the scored points' normals, a plane is fitted only through
        points on the same side of a thin wall (:meth:`surface`).
    """

    def __init__(self, points, values, k=REFERENCE_NEIGHBOURS, quantity=REFERENCE_QUANTITY, variance_scale=0.0, owners=None,
                 grazing_scale=0.0, surface_points=None, surface_owners=None, surface_normals=None):
        self.points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        self.values = np.asarray(values, dtype=np.float32).reshape(-1)
        if len(self.points) != len(self.values) or len(self.points) < k:
            raise ValueError(f"LocalReference needs >= {k} points with one value each, got {len(self.points)} "
                             f"points and {len(self.values)} values")
        if quantity != REFERENCE_QUANTITY:
            raise ValueError(f"reference quantity must be {REFERENCE_QUANTITY!r} (the point score 'local', on E f "
                             f"itself, is retired), got {quantity!r}")
        if not (float(variance_scale) >= 0 and float(grazing_scale) >= 0):
            raise ValueError(f"variance_scale and grazing_scale must be >= 0, got {variance_scale!r}, "
                             f"{grazing_scale!r}")
        self.k = int(k)
        self.quantity = quantity
        self.variance_scale = float(variance_scale)
        self.grazing_scale = float(grazing_scale)
        self.owners = None if owners is None else np.asarray(owners, dtype=np.int64).reshape(-1)
        if self.owners is not None and len(self.owners) != len(self.points):
            raise ValueError(f"owners must have one entry per point ({len(self.points)}), got {len(self.owners)}")
        self.surface_points = None if surface_points is None else \
            np.asarray(surface_points, dtype=np.float32).reshape(-1, 3)
        self.surface_owners = None if surface_owners is None else np.asarray(surface_owners, np.int64).reshape(-1)
        self.surface_normals = None if surface_normals is None else \
            np.asarray(surface_normals, dtype=np.float32).reshape(-1, 3)
        for name, a in (("surface_owners", self.surface_owners), ("surface_normals", self.surface_normals)):
            if a is not None and (self.surface_points is None or len(a) != len(self.surface_points)):
                raise ValueError(f"{name} must have one entry per surface point")
        self._tree = None
        self._surface = None

    @classmethod
    def from_values(cls, scans, max_points=60000, seed=0, k=REFERENCE_NEIGHBOURS, quantity=REFERENCE_QUANTITY):
        """Build from (points (m, 3), values (m,)) pairs of good scans, randomly subsampled to ``max_points``
        (seeded); ``owners`` records each point's scan."""
        pts = np.concatenate([np.asarray(p, dtype=np.float64) for p, _ in scans])
        vals = np.concatenate([np.asarray(v, dtype=np.float64) for _, v in scans])
        owners = np.concatenate([np.full(len(p), i) for i, (p, _) in enumerate(scans)])
        if len(pts) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
            pts, vals, owners = pts[keep], vals[keep], owners[keep]
        return cls(pts, vals, k, quantity, owners=owners)

    @classmethod
    def from_fields(cls, scans_and_fields, max_points=60000, seed=0, k=REFERENCE_NEIGHBOURS, quantity=REFERENCE_QUANTITY):
        """Build from (points (m, 3), field) pairs; see :meth:`from_values`."""
        return cls.from_values([(p, field_quantity(f, np.asarray(p, dtype=np.float64), quantity))
                                for p, f in scans_and_fields], max_points, seed, k, quantity)

    def without(self, owner):
        """The same reference without the points of good scan ``owner`` (needs ``owners``)."""
        if self.owners is None:
            raise ValueError("this LocalReference does not know which scan each point came from (owners)")
        keep = self.owners != owner
        surface, surface_owners, surface_normals = self.surface_points, self.surface_owners, self.surface_normals
        if surface_owners is not None:
            other = surface_owners != owner
            surface, surface_owners = surface[other], surface_owners[other]
            surface_normals = None if surface_normals is None else surface_normals[other]
        return LocalReference(self.points[keep], self.values[keep], self.k, self.quantity, self.variance_scale,
                              self.owners[keep], self.grazing_scale, surface, surface_owners, surface_normals)

    @property
    def tree(self):
        """The KD-tree of the reference points (built once, on first use; the ray score's surface band shares it)."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def _surface_tree(self):
        """(KD-tree over the distinct surface points, their normals (or None), self distance): a point that several
        good scans share (rendered views of one template) counts once in the plane fits."""
        from scipy.spatial import cKDTree

        if self._surface is None:
            points = self.points if self.surface_points is None else self.surface_points
            distinct, first = np.unique(points, axis=0, return_index=True)
            normals = None if self.surface_normals is None else self.surface_normals[first].astype(np.float64)
            diagonal = float(np.linalg.norm(np.ptp(distinct, axis=0)))
            self._surface = (cKDTree(distinct), normals, SELF_DISTANCE * max(diagonal, 1e-12))
        return self._surface

    def surface(self, points, normals=None):
        """Offsets of points from the good scans' surface, without any field.

        For each point p, the plane through its ``k`` nearest distinct surface points (``surface_points``, else the
        reference points), p itself left out when it is one of them (a calibration view of a template shares its
        points with the reference's views of that template; a point is not evidence for itself), and, when both p's
        normal and ``surface_normals`` are known, only points whose normal faces the same side as p's (the nearest
        of ``SURFACE_CANDIDATES`` x k; all of them when fewer than 3 agree): across a wall thinner than the points'
        spacing the nearest points lie on both faces, and a plane through both would sit inside the wall. The plane:
        centroid c, unit normal n (the direction of least spread), and the points' variance along n, which holds
        their noise and the surface's curvature within the neighbourhood.

        Parameters
        ----------
        points : (m, 3) array
            Model frame.
        normals : (m, 3) array, optional
            The points' outward normals (any length; only their sign against the surface normals is used).

        Returns
        -------
        offset : (m,) float64
            n . (p - c), world units, the sign arbitrary.
        spread : (m,) float64
            The neighbours' variance along n, squared world units (>= 0).
        """
        tree, surface_normals, self_distance = self._surface_tree()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        k = min(self.k, tree.n - 1)
        if k < 3:
            raise ValueError(f"the reference surface needs >= 4 distinct points, got {tree.n}")
        sided = normals is not None and surface_normals is not None
        wide = min(SURFACE_CANDIDATES * k + 1, tree.n) if sided else k + 1
        dist, idx = tree.query(points, wide)  # (m, wide)
        valid = dist > self_distance
        if sided:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
            same = np.einsum("mj,mkj->mk", normals, surface_normals[idx]) > 0
            enough = (valid & same).sum(1) >= 3
            valid &= same | ~enough[:, None]
        weight = (valid & (np.cumsum(valid, 1) <= k)).astype(np.float64)  # (m, wide): the first k valid
        nb = tree.data[idx]  # (m, wide, 3)
        count = weight.sum(1)
        centroid = np.einsum("mk,mki->mi", weight, nb) / count[:, None]
        centred = nb - centroid[:, None]
        cov = np.einsum("mk,mki,mkj->mij", weight, centred, centred) / count[:, None, None]  # (m, 3, 3)
        eigval, eigvec = np.linalg.eigh(cov)  # ascending
        normal = eigvec[:, :, 0]
        return np.einsum("mi,mi->m", normal, points - centroid), np.maximum(eigval[:, 0], 0.0)

    def surface_scores(self, points, noise, grazing=None, normals=None):
        """|offset| / sqrt(spread + noise^2 (1 + grazing_scale * g)) with offset, spread of :meth:`surface` (with the
        points' ``normals`` (m, 3), optional): how many standard deviations a point lies off the good scans'
        surface. The neighbours' spread holds their own noise and the surface's curvature; the point's own
        measurement noise grows with the grazing factor g (m,) (None: 0) as in :meth:`standardized`. (m,)
        float64."""
        offset, spread = self.surface(points, normals)
        return np.abs(offset) / np.sqrt(self._total(spread, 0.0, float(noise) ** 2, grazing, 0.0, self.grazing_scale))

    def stats(self, points):
        """Local mean and standard deviation of the reference values around each point: (m,), (m,)."""
        _, idx = self.tree.query(np.asarray(points, dtype=np.float64), self.k)
        v = self.values[idx].astype(np.float64)  # (m, k)
        return v.mean(1), v.std(1)

    def standardized(self, points, value, variance, noise, grazing=None):
        """The point score (class docstring) of values (m,) with field variances (m,) and grazing factors (m,)
        (None: 0) at points (m, 3)."""
        m_ref, s_ref = self.stats(points)
        return np.abs(value - m_ref) / np.sqrt(self._total(s_ref**2, variance, noise**2, grazing,
                                                           self.variance_scale, self.grazing_scale))

    @staticmethod
    def _total(reference_var, field_var, noise_var, grazing, variance_scale, grazing_scale):
        g = 0.0 if grazing is None else np.maximum(grazing, 0.0)
        total = reference_var + variance_scale * np.maximum(field_var, 0.0) + noise_var * (1.0 + grazing_scale * g)
        return np.maximum(total, _MIN_VARIANCE)

    @staticmethod
    def fit_noise_model(residuals, reference_variances, field_variances, noise_variances, grazing=None):
        """``variance_scale`` and ``grazing_scale`` that make good scans' residuals most likely.

        Maximum likelihood of r_i ~ N(0, b_i + kappa u_i + e_i (1 + lambda g_i)) over kappa, lambda >= 0, with r the
        residuals v - m_ref of good scans not in the reference they are compared with (held-back scans, or
        cross-fitted ones), b = s_ref^2, u the field's variance, e = noise^2 and g the grazing factor. Solved on
        log kappa, log lambda (Nelder-Mead from two starts), then compared with the boundaries kappa = 0 and
        lambda = 0.

        Parameters
        ----------
        residuals, reference_variances, field_variances, noise_variances : (n,) arrays
        grazing : (n,) array, optional
            None (sensor origins unknown): lambda is 0.

        Returns
        -------
        (kappa, lambda) : floats in [0, 1e4]
        """
        from scipy.optimize import minimize

        r2 = np.asarray(residuals, dtype=np.float64).reshape(-1) ** 2
        b, u, e = (np.broadcast_to(np.asarray(a, dtype=np.float64).reshape(-1), r2.shape)
                   for a in (reference_variances, field_variances, noise_variances))
        g = None if grazing is None else np.asarray(grazing, dtype=np.float64).reshape(-1)
        if len(r2) == 0 or (g is not None and g.shape != r2.shape):
            raise ValueError(f"fit_noise_model needs residuals and, optionally, one grazing factor each; got "
                             f"{len(r2)} and {None if g is None else len(g)}")

        def nll(kappa, lam):
            total = LocalReference._total(b, u, e, g, kappa, lam)
            return float(np.mean(r2 / total + np.log(total)))

        lo, hi = math.log(1e-6), math.log(1e4)
        clip = lambda t: math.exp(min(max(t, lo), hi))  # noqa: E731
        candidates = [(0.0, 0.0)]
        for start in (0.0, -3.0):
            if g is None:
                best = minimize(lambda t: nll(clip(t[0]), 0.0), [start], method="Nelder-Mead",
                                options={"xatol": 1e-4, "fatol": 1e-10})
                candidates.append((clip(best.x[0]), 0.0))
            else:
                best = minimize(lambda t: nll(clip(t[0]), clip(t[1])), [start, start], method="Nelder-Mead",
                                options={"xatol": 1e-4, "fatol": 1e-10})
                kappa, lam = clip(best.x[0]), clip(best.x[1])
                candidates += [(kappa, lam), (kappa, 0.0), (0.0, lam)]
        return min(candidates, key=lambda c: nll(*c))

    def as_dict(self):
        import torch

        surface = normals = None
        if self.surface_points is not None:
            distinct, first = np.unique(self.surface_points, axis=0, return_index=True)
            surface = torch.from_numpy(distinct)
            normals = None if self.surface_normals is None else torch.from_numpy(self.surface_normals[first].copy())
        return {"points": torch.from_numpy(self.points.copy()), "values": torch.from_numpy(self.values.copy()),
                "k": self.k, "quantity": self.quantity, "variance_scale": self.variance_scale,
                "grazing_scale": self.grazing_scale, "surface_points": surface, "surface_normals": normals}

    @classmethod
    def from_dict(cls, d):
        surface, normals = d.get("surface_points"), d.get("surface_normals")
        return cls(np.asarray(d["points"]), np.asarray(d["values"]), int(d.get("k", REFERENCE_NEIGHBOURS)),
                   str(d.get("quantity", REFERENCE_QUANTITY)), float(d.get("variance_scale", 0.0)),
                   grazing_scale=float(d.get("grazing_scale", 0.0)),
                   surface_points=None if surface is None else np.asarray(surface),
                   surface_normals=None if normals is None else np.asarray(normals))
