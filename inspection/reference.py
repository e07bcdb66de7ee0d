"""The per-location reference: what good scans look like at each place, and its noise model.

The point scores with a reference (``'distance'``, ``'joint'``: :mod:`inspection.scores`) compare a scan's
first-order distance to its projected mean surface (:func:`field_quantity`) with what good scans show at the same
place, and a point with the plane through the good scans' own nearest points (:meth:`LocalReference.surface`).
"""
import math

import numpy as np

from datasets.local_planes import smallest_eigenpairs
from datasets.neighbours import NearestNeighbours

from .member_spread import MemberSpread

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
# scored points per block of neighbour queries: a 500,000-point scan's (m, 4 k + 1, 3) neighbourhoods and their
# arrays would take gigabytes at once, a block of this many some 150 MB
QUERY_CHUNK = 32768
_MIN_VARIANCE = 1e-20  # total variances are floored here


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
    mean, grad = field.mean_and_gradient(points)
    grad = np.linalg.norm(np.asarray(grad, dtype=np.float64), axis=1)
    mean = np.asarray(mean, dtype=np.float64)
    scale = np.maximum(grad, GRADIENT_FLOOR)
    if not with_variance:
        return mean / scale
    variance = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    return mean / scale, variance / scale**2


def _plane(points, nb, valid, k):
    """The offsets (m,) of points (m, 3) from the plane through the first ``k`` valid (m, w) of their neighbours nb
    (m, w, 3), and the neighbours' variance along its normal (m,) (:meth:`LocalReference.surface`)."""
    weight = (valid & (np.cumsum(valid, 1) <= k)).astype(np.float64)  # (m, w): the first k valid
    count = weight.sum(1)
    centroid = np.einsum("mk,mki->mi", weight, nb) / count[:, None]
    centred = nb - centroid[:, None]
    # (m, 3, 3): sum_k w_k c_k c_k^T as one batched product (a three-operand einsum is ten times slower)
    cov = np.matmul((weight[:, :, None] * centred).transpose(0, 2, 1), centred) / count[:, None, None]
    spread, normal = smallest_eigenpairs(cov)
    return np.einsum("mi,mi->m", normal, points - centroid), np.maximum(spread, 0.0)


def _surface_block(surface, k, points, normals, candidates=SURFACE_CANDIDATES):
    """:meth:`LocalReference.surface` of one block of (b, 3) points (float64) and their normals (b, 3) or None,
    against ``surface`` (the reference's ``_surface_tree()``) with ``k`` plane neighbours: offset, spread,
    supported (b,) each."""
    tree, surface_normals, self_distance = surface
    k = min(k, tree.n - 1)
    if k < 3:
        raise ValueError(f"the reference surface needs >= 4 distinct points, got {tree.n}")
    sided = normals is not None and surface_normals is not None
    wide = min(int(candidates) * k + 1, tree.n) if sided else k + 1
    offset, spread = np.empty(len(points)), np.empty(len(points))
    supported = np.ones(len(points), dtype=bool)
    todo = np.arange(len(points))
    # the k + 1 nearest first: where k of them are valid and on the point's side (most points, away from thin
    # walls), they are the first k such of the wide query too, which only the other points then need
    for width in ((k + 1, wide) if wide > k + 1 else (wide,)):
        if len(todo) == 0:
            break
        dist, idx = tree.query(points[todo], width)  # (t, width)
        valid = dist > self_distance
        if sided:
            same = np.einsum("mj,mkj->mk", normals[todo], surface_normals[idx]) > 0
            agree = (valid & same).sum(1)
            if width < wide:
                rows = agree >= k
                done = todo[rows]
                offset[done], spread[done] = _plane(points[done], tree.data[idx[rows]],
                                                    (valid & same)[rows], k)
                todo = todo[~rows]
                continue
            supported[todo] = agree >= 3
            valid &= same | ~(agree >= 3)[:, None]
        offset[todo], spread[todo] = _plane(points[todo], tree.data[idx], valid, k)
    return offset, spread, supported


def checked_term_variances(variances):
    """(v_d, v_s) as two positive finite floats (the variances that weigh the joint score's two terms); a ValueError
    for anything else (a calibration record stored with a damaged entry among them)."""
    try:
        values = tuple(float(v) for v in variances)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"term_variances must be two positive finite numbers, got {variances!r}")
    return values


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
    ``grazing_scale`` are calibrated on good scans (:func:`fit_noise_model`); both 0 is the reference alone.

    The good scans' points also describe the part's surface by themselves, independently of any field:
    :meth:`surface_scores` scores a point by its offset from the plane through its ``k`` nearest distinct reference
    points (the ``'joint'`` point score). ``term_variances`` says how much each of the two terms spreads on good scans
    (:func:`inspection.scores.fit_term_variances`): the joint score weighs each by it.

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
    term_variances : (v_d, v_s), positive floats
        The variances of the field's term (:meth:`standardized`) and of the good points' term (:meth:`surface_scores`)
        on good scans; (1, 1), equal weights, is the reference of a calibration stored before they were fitted.
    field_on_unseen_faces : bool
        Whether the joint score takes the field's term for the good points' where no good scan saw the point's side
        of the surface (:func:`inspection.scores.reference_terms`); False is the reference of a calibration stored
        before that rule, which scores as it was calibrated.
    member_spread : inspection.member_spread.MemberSpread, optional
        How much the good scans' members differ in shape, place by place: where they do, the good points' term
        compares a scan with the good surface carried to its own member (:mod:`inspection.member_surface`). None
        (a calibration stored before it): the surface as the good scans left it.
    """

    def __init__(self, points, values, k=REFERENCE_NEIGHBOURS, quantity=REFERENCE_QUANTITY, variance_scale=0.0, owners=None,
                 grazing_scale=0.0, surface_points=None, surface_owners=None, surface_normals=None,
                 term_variances=(1.0, 1.0), field_on_unseen_faces=True, member_spread=None):
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
        self.term_variances = checked_term_variances(term_variances)
        self.field_on_unseen_faces = bool(field_on_unseen_faces)
        self.member_spread = member_spread
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
        self._neighbours = None
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
                              self.owners[keep], self.grazing_scale, surface, surface_owners, surface_normals,
                              self.term_variances, self.field_on_unseen_faces, self.member_spread)

    @property
    def neighbours(self):
        """The k-nearest-neighbour index of the reference points (:class:`datasets.neighbours.NearestNeighbours`;
        built once, on first use) that :meth:`stats` queries (the ray score's surface band shares it)."""
        if self._neighbours is None:
            self._neighbours = NearestNeighbours(self.points)
        return self._neighbours

    def _surface_tree(self):
        """(KD-tree over the distinct surface points, their normals (or None), self distance): a point that several
        good scans share (rendered views of one template) counts once in the plane fits."""
        from scipy.spatial import cKDTree

        if self._surface is None:
            points = self.points if self.surface_points is None else self.surface_points
            distinct, first = np.unique(points, axis=0, return_index=True)
            # stored in a KD-tree's leaf order, so that a point's neighbours lie together in memory: gathering them
            # (data[idx], normals[idx]) from the order of many interleaved scans cost about as much as the query
            first = first[cKDTree(distinct).indices]
            distinct = points[first]
            normals = None if self.surface_normals is None else self.surface_normals[first].astype(np.float64)
            diagonal = float(np.linalg.norm(np.ptp(distinct, axis=0)))
            self._surface = (NearestNeighbours(distinct), normals, SELF_DISTANCE * max(diagonal, 1e-12))
        return self._surface

    def distinct_surface(self):
        """(index over the distinct surface points, their unit normals or None): what coverage measures against."""
        return self._surface_tree()[:2]

    def self_distance(self):
        """The distance (world units) within which a surface point is the scored point itself (``SELF_DISTANCE``
        surface diagonals): :meth:`surface` leaves such a point out of the point's plane."""
        return self._surface_tree()[2]

    def surface_distance(self, points):
        """(m,) distance of each of (m, 3) points to the nearest distinct surface point (the good scans' own
        surface, :meth:`surface`), in the points' units."""
        index, _, _ = self._surface_tree()
        return index.query(np.asarray(points, dtype=np.float64).reshape(-1, 3), 1)[0][:, 0]

    def oriented_surface(self):
        """(index, normals): a :class:`datasets.neighbours.NearestNeighbours` over the distinct surface points and
        their unit outward normals (n2, 3), row for row (what the ray score's band needs to tell where a ray skims
        past the good surface, :class:`autodecoder.scanning.free_space.SurfaceBand`); None when the good scans have
        no normals."""
        index, normals, _ = self._surface_tree()
        return None if normals is None else (index, normals)

    def surface(self, points, normals=None, with_support=False, candidates=SURFACE_CANDIDATES):
        """Offsets of points from the good scans' surface, without any field.

        For each point p, the plane through its ``k`` nearest distinct surface points (``surface_points``, else the
        reference points), p itself left out when it is one of them (a calibration view of a template shares its
        points with the reference's views of that template; a point is not evidence for itself), and, when both p's
        normal and ``surface_normals`` are known, only points whose normal faces the same side as p's (the nearest
        of ``candidates`` x k; all when fewer than 3 agree): across a wall thinner than the points' spacing the
        nearest points lie on both faces, and a plane through both would sit inside the wall. The plane: centroid c,
        normal n (least spread), the points' variance along n (their noise and the surface's curvature).

        Parameters
        ----------
        points : (m, 3) array
            Model frame.
        normals : (m, 3) array, optional
            The points' outward normals (any length; only their sign against the surface normals is used).
        with_support : bool
            Also return ``supported``.
        candidates : int >= 1
            The side's points are sought among ``candidates`` x k nearest (``SURFACE_CANDIDATES``, above).

        Returns
        -------
        offset : (m,) float64
            n . (p - c), world units, the sign arbitrary.
        spread : (m,) float64
            The neighbours' variance along n, squared world units (>= 0).
        supported : (m,) bool, with ``with_support``
            False where the point's side had fewer than 3 good points among the candidates (the plane then came
            from both faces): no good scan saw that side of the surface there. All True without normals.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        offset, spread = np.empty(len(points)), np.empty(len(points))
        supported = np.ones(len(points), dtype=bool)
        for start in range(0, len(points), QUERY_CHUNK):  # blocks keep a full-resolution scan's memory bounded
            block = slice(start, start + QUERY_CHUNK)
            offset[block], spread[block], supported[block] = _surface_block(
                self._surface_tree(), self.k, points[block], None if normals is None else normals[block], candidates)
        return (offset, spread, supported) if with_support else (offset, spread)

    def surface_scores(self, points, noise, grazing=None, normals=None, with_support=False):
        """|offset| / sqrt(spread + noise^2 (1 + grazing_scale * g)) with offset, spread of :meth:`surface` (with the
        points' ``normals`` (m, 3), optional): how many standard deviations a point lies off the good scans'
        surface. The neighbours' spread holds their own noise and the surface's curvature; the point's own
        measurement noise grows with the grazing factor g (m,) (None: 0) as in :meth:`standardized`. (m,)
        float64; with ``with_support`` also :meth:`surface`'s ``supported`` (m,) bool."""
        offset, spread, supported = self.surface(points, normals, with_support=True)
        scores = np.abs(offset) / np.sqrt(total_variance(spread, 0.0, float(noise) ** 2, grazing, 0.0,
                                                          self.grazing_scale))
        return (scores, supported) if with_support else scores

    def stats(self, points):
        """Local mean and standard deviation of the reference values around each point: (m,), (m,)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        mean, std = np.empty(len(points)), np.empty(len(points))
        for start in range(0, len(points), QUERY_CHUNK):
            block = slice(start, start + QUERY_CHUNK)
            _, idx = self.neighbours.query(points[block], self.k)
            v = self.values[idx].astype(np.float64)  # (b, k)
            mean[block], std[block] = v.mean(1), v.std(1)
        return mean, std

    def standardized(self, points, value, variance, noise, grazing=None):
        """The point score (class docstring) of values (m,) with field variances (m,) and grazing factors (m,)
        (None: 0) at points (m, 3)."""
        m_ref, s_ref = self.stats(points)
        return np.abs(value - m_ref) / np.sqrt(total_variance(s_ref**2, variance, noise**2, grazing,
                                                               self.variance_scale, self.grazing_scale))

    def as_dict(self):
        """Plain values (torch tensors for the arrays) to store in a calibration record; the owners are not stored."""
        import torch

        surface = normals = None
        if self.surface_points is not None:
            distinct, first = np.unique(self.surface_points, axis=0, return_index=True)
            surface = torch.from_numpy(distinct)
            normals = None if self.surface_normals is None else torch.from_numpy(self.surface_normals[first].copy())
        return {"points": torch.from_numpy(self.points.copy()), "values": torch.from_numpy(self.values.copy()),
                "k": self.k, "quantity": self.quantity, "variance_scale": self.variance_scale,
                "grazing_scale": self.grazing_scale, "surface_points": surface, "surface_normals": normals,
                "term_variances": list(self.term_variances), "field_on_unseen_faces": self.field_on_unseen_faces,
                "member_spread": None if self.member_spread is None else self.member_spread.as_dict()}

    @classmethod
    def from_dict(cls, d):
        """The reference :meth:`as_dict` stored (a record of the current calibration version: an older one is
        upgraded by :func:`inspection.calibration.migrate` first)."""
        surface, normals = d["surface_points"], d["surface_normals"]
        return cls(np.asarray(d["points"]), np.asarray(d["values"]), int(d["k"]), str(d["quantity"]),
                   float(d["variance_scale"]), grazing_scale=float(d["grazing_scale"]),
                   surface_points=None if surface is None else np.asarray(surface),
                   surface_normals=None if normals is None else np.asarray(normals),
                   term_variances=d["term_variances"], field_on_unseen_faces=bool(d["field_on_unseen_faces"]),
                   member_spread=MemberSpread.from_dict(d["member_spread"]))


def total_variance(reference_var, field_var, noise_var, grazing, variance_scale, grazing_scale):
    """The variance (m,) a reference score divides by: reference_var + variance_scale * field_var + noise_var * (1 +
    grazing_scale * g), with the field's variance and the grazing factor g (None: 0) floored at 0, the total at
    ``_MIN_VARIANCE`` (:class:`LocalReference`'s docstring; squared world units)."""
    g = 0.0 if grazing is None else np.maximum(grazing, 0.0)
    total = reference_var + variance_scale * np.maximum(field_var, 0.0) + noise_var * (1.0 + grazing_scale * g)
    return np.maximum(total, _MIN_VARIANCE)


def fit_noise_model(residuals, reference_variances, field_variances, noise_variances, grazing=None):
    """The noise model of a :class:`LocalReference`: ``variance_scale`` and ``grazing_scale`` that make good scans'
    residuals most likely.

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
        total = total_variance(b, u, e, g, kappa, lam)
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
