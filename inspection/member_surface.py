"""The good scans' surface carried to the scanned member of a family whose members differ in shape.

Why: the joint score's good points' term measures a point's offset from the plane through the nearest good points
(:meth:`inspection.reference.LocalReference.surface`). In a product family whose members differ by more than the
noise (a bracket bent to several angles), the nearest good points belong to other members: a good scan of a member
between them reads as far off as a defect, where the field's term, which follows the projected member, does not
(fandisk bent 24-48 degrees either way: the good test scans' worst points lie 9-21 of the good points' spreads off
them and 1.4-5 of the field's; docs/results_archive.md, "Families that bend: the good surface carried to the
member").

How. At calibration (:func:`fit_member_spread`), at anchor points of the good surface, the reference scans' own
projected fields give the first-order distance d_j(a) (:func:`inspection.reference.field_quantity`), each field
counted where its scan saw the anchor's side within one kernel lengthscale of the anchor's place on its own member
(the anchor carried onto the field's mean surface): a field is the surface only where its scan looked, and a thin
wall's other face is where it guesses. Their variance beyond ``MEMBER_SPREAD_FLOOR`` times the
reference's own spread there (s_ref^2: how far good scans' fields miss their own points) is the members' variance
tau^2: the part of how the good scans' surfaces differ that their noise does not explain. One shape gives tau^2 = 0
nearly everywhere. At scoring (:func:`carried_surface`) a good point p near the scan moves along the scan's field's
normal by w (d_z(p) - m_ref(p)), d_z the scan's field's first-order distance and m_ref the good scans' own there,
with w = tau^2 / (tau^2 + s_ref^2): the mean of the member's displacement given the field's, when the displacement
has variance tau^2 among the members and the field's noise s_ref^2. The remaining variance of the carried point's
place, w s_ref^2, widens the plane's spread. Where tau^2 is 0 nothing moves; where the members differ over less
than ``inspection.member_spread.MEMBER_SHARE`` of the anchors (partial views of one part), nothing moves anywhere.

A defect where the members differ is carried with them only as far as the field follows it (the field's own term
still sees it); on a part of one shape nothing changes.
"""
import numpy as np

from .member_spread import MemberSpread
from .reference import GRADIENT_FLOOR, LocalReference, total_variance

# anchor points of the good surface where the members' spread is measured (a seeded subsample)
MEMBER_ANCHORS = 6000
# the members' variance is what the good scans' fields spread beyond this many times the reference's own spread
# s_ref^2: partial views of one part spread up to about twice s_ref where they saw the surface (its 90th
# percentile; fandisk, the cup), members bent 24-48 degrees either way 8 times (docs/results_archive.md, issue 52)
MEMBER_SPREAD_FLOOR = 4.0
# anchors whose members' variance is smoothed together (the median of each anchor's nearest)
SMOOTHING_ANCHORS = 8
# fields counted at an anchor: at least this many reference scans saw its side there
MEMBER_MIN_SCANS = 3
# a scan's nearest points searched for one on the anchor's side (whether its scan saw the anchor's place on its own
# member's surface)
SIDE_CANDIDATES = 8
# Newton steps that carry an anchor onto a reference scan's own member's surface (where that scan saw it, or not)
FOOT_STEPS = 2
# good points within this many kernel lengthscales (and the members' extent, MemberSpread.extent) of a scanned point
# are carried to its member (its plane's neighbours lie a few point spacings from it, well within one)
CARRY_REACH_LENGTHSCALES = 1.0
# scanned points within this many kernel lengthscales (and the members' extent) of an anchor where the members differ
# are compared with the carried surface (farther, their good neighbours' 4 nearest anchors all have tau^2 = 0:
# nothing near them moves)
AFFECTED_LENGTHSCALES = 2.0


def fit_member_spread(reference, goods, seed=0, anchors=MEMBER_ANCHORS, floor=MEMBER_SPREAD_FLOOR):
    """The :class:`MemberSpread` of the good scans a reference was built from (module docstring), or None when it
    cannot be measured (fewer than ``MEMBER_MIN_SCANS`` scans with fields and normals, or fields without a kernel
    lengthscale).

    Parameters
    ----------
    reference : LocalReference
        Its distinct surface points and normals give the anchors; its :meth:`~LocalReference.stats` the own spread.
    goods : list of inspection.evidence.ScanEvidence
        The reference scans, each with its projected field, points and normals (model frame).
    seed : int
        Of the anchors' subsample.
    anchors : int
        At most this many anchors.
    floor : float
        ``MEMBER_SPREAD_FLOOR``.
    """
    from datasets.neighbours import NearestNeighbours

    usable = [g for g in goods if g.field is not None and g.normals is not None and len(g.points) > 0]
    lengthscale = getattr(usable[0].field, "lengthscale", None) if usable else None
    index, surface_normals = reference.distinct_surface()
    if len(usable) < MEMBER_MIN_SCANS or surface_normals is None or not lengthscale or not np.isfinite(lengthscale):
        return None
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(index.n, min(int(anchors), index.n), replace=False))
    where, side = index.data[pick], surface_normals[pick]
    distances, saw = seen_distances(usable, where, side, lengthscale)
    count = saw.sum(0)
    mean = (distances * saw).sum(0) / np.maximum(count, 1)
    variance = ((distances - mean) ** 2 * saw).sum(0) / np.maximum(count - 1, 1)
    _, own = reference.stats(where)
    counted = count >= MEMBER_MIN_SCANS
    raw = np.where(counted, np.maximum(variance - floor * own**2, 0.0), 0.0)
    # the trained members' envelope (inspection.family_range): the least and greatest distance over every field, not
    # only those whose scans saw the anchor: each code decodes a whole member, and a member between two others is
    # seen at an anchor by scans of one side only as often as not (fandisk bent 24-48 degrees either way: the
    # untrained member at 0 then lay beyond the counted fields' envelope as often as a member at 60 did)
    low = np.where(counted, distances.min(0), np.nan)
    high = np.where(counted, distances.max(0), np.nan)
    # members differ over areas, the fields' noise at places: each anchor takes the median of its nearest anchors'
    _, nearest = NearestNeighbours(where).query(where, min(SMOOTHING_ANCHORS, len(where)))
    return MemberSpread(where, np.median(raw[nearest.reshape(len(where), -1)], axis=1), low, high, own)


def seen_distances(scans, anchors, side, lengthscale):
    """For each scan (its ``field``, ``points``, ``normals``), the first-order distance of each anchor to its field's
    mean surface and whether the scan saw the anchor's place on its own member: the anchor carried onto that surface
    (:func:`_distance_and_foot`) has a point of the scan within ``lengthscale`` on the anchor's side (``side``, the
    anchors' normals). Returns ((s, a) float64, (s, a) bool)."""
    from scipy.spatial import cKDTree

    distances = np.zeros((len(scans), len(anchors)))
    saw = np.zeros((len(scans), len(anchors)), dtype=bool)
    for j, scan in enumerate(scans):
        distances[j], landed = _distance_and_foot(scan.field, anchors)
        points = np.asarray(scan.points, dtype=np.float64)
        normals = np.asarray(scan.normals, dtype=np.float64)
        k = min(SIDE_CANDIDATES, len(points))
        dist, idx = cKDTree(points).query(landed, k)
        dist, idx = dist.reshape(len(anchors), k), idx.reshape(len(anchors), k)
        same_side = np.einsum("akj,aj->ak", normals[idx], side) > 0
        saw[j] = ((dist < lengthscale) & same_side).any(1)
    return distances, saw


def _first_order(field, points):
    """The first-order distance (m,) of (m, 3) points to ``field``'s mean surface, E f / max(|grad E f|,
    ``GRADIENT_FLOOR``) as :func:`inspection.reference.field_quantity` has it, and the unit gradient (m, 3) along
    which it is measured, from one pass of the mean net."""
    mean, gradient = field.mean_and_gradient(points)
    gradient = np.asarray(gradient, dtype=np.float64)
    norm = np.linalg.norm(gradient, axis=1)
    return (np.asarray(mean, dtype=np.float64) / np.maximum(norm, GRADIENT_FLOOR),
            gradient / np.maximum(norm, 1e-12)[:, None])


def _distance_and_foot(field, points, steps=FOOT_STEPS):
    """The first-order distance (m,) of (m, 3) points to ``field``'s mean surface (:func:`_first_order`) and where
    they land on it (m, 3): ``steps`` Newton steps along its gradient."""
    first = None
    foot = np.asarray(points, dtype=np.float64).copy()
    for _ in range(steps):
        distance, direction = _first_order(field, foot)
        first = distance if first is None else first
        foot -= distance[:, None] * direction
    return first, foot


def carried_surface(reference, spread, field, points):
    """The good surface carried to the member that ``field`` projects (module docstring), as a
    :class:`LocalReference` whose :meth:`~LocalReference.surface` the good points' term asks, and each of its
    surface points' remaining variance; None when nothing near ``points`` moves (no member spread there).

    Parameters
    ----------
    reference : LocalReference
        The good scans' reference (its distinct surface points and normals, its stats).
    spread : MemberSpread
    field : stochastic field
        The scan's projected field (``mean_and_gradient``, ``lengthscale``).
    points : (m, 3) array
        The scan's points (model frame).

    Returns
    -------
    (LocalReference, (n, 3) float64, (n,) float64) or None
        Over the carried good points within ``CARRY_REACH_LENGTHSCALES`` kernel lengthscales of the scan (the
        others are never their planes' neighbours): the reference, the points, and the variance w s_ref^2 each adds
        to a plane through it.
    """
    from scipy.spatial import cKDTree

    lengthscale = getattr(field, "lengthscale", None)
    if spread is None or not spread.differs or not lengthscale:
        return None
    index, normals = reference.distinct_surface()
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    reach = CARRY_REACH_LENGTHSCALES * lengthscale + spread.extent
    box = np.flatnonzero(((index.data >= points.min(0) - reach) & (index.data <= points.max(0) + reach)).all(1))
    gap, _ = cKDTree(points).query(index.data[box], 1, distance_upper_bound=reach)
    near = box[np.isfinite(gap) & (gap > reference.self_distance())]  # a scanned point is not evidence for itself
    if len(near) <= reference.k:
        return None
    good = index.data[near].copy()
    tau2 = spread.at(good)
    moving = np.flatnonzero(tau2 > 0)
    if len(moving) == 0:
        return None
    scan_distance, direction = _first_order(field, good[moving])
    own_mean, own_std = reference.stats(good[moving])
    weight = tau2[moving] / (tau2[moving] + np.maximum(own_std**2, 1e-20))
    good[moving] -= (weight * (scan_distance - own_mean))[:, None] * direction
    extra = np.zeros(len(good))
    extra[moving] = weight * own_std**2
    carried = LocalReference(good, np.zeros(len(good)), reference.k, surface_points=good,
                             surface_normals=None if normals is None else normals[near],
                             grazing_scale=reference.grazing_scale, term_variances=reference.term_variances)
    return carried, good, extra


def carried_surface_scores(reference, spread, field, points, noise, grazing=None, normals=None):
    """The good points' term (:meth:`LocalReference.surface_scores`, with its ``supported``) of (m, 3) points
    against the good surface carried to the scan's member, or None when nothing near the scan moves (the
    reference's own term stands). Only the points within ``AFFECTED_LENGTHSCALES`` kernel lengthscales of an
    anchor where the members differ are scored against the carried surface; the others' good neighbours do not
    move, and keep the reference's own term (its cost is what a part of one shape pays)."""
    from datasets.neighbours import NearestNeighbours

    lengthscale = getattr(field, "lengthscale", None)
    if spread is None or not spread.differs or not lengthscale:
        return None
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    grazing = None if grazing is None else np.asarray(grazing, dtype=np.float64).reshape(-1)
    normals = None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    gap, _ = spread.moving_index().query(points, 1,
                                         distance_upper_bound=AFFECTED_LENGTHSCALES * lengthscale + spread.extent)
    affected = np.flatnonzero(np.isfinite(gap))
    carried = None if len(affected) == 0 else carried_surface(reference, spread, field, points[affected])
    if carried is None:
        return None
    scores, supported = reference.surface_scores(points, noise, grazing, normals, with_support=True)
    surface, good, extra = carried
    some = points[affected]
    offset, plane_spread, supported[affected] = surface.surface(
        some, None if normals is None else normals[affected], with_support=True)
    _, nearest = NearestNeighbours(good).query(some, 1)
    variance = total_variance(plane_spread + extra[nearest.reshape(-1)], 0.0, float(noise) ** 2,
                              None if grazing is None else grazing[affected], 0.0, reference.grazing_scale)
    scores[affected] = np.abs(offset) / np.sqrt(variance)
    return scores, supported
