"""Which points of a scan lie on surface the good scans covered, and what a scan's verdict may say where they did not.

A model trained on few good scans (8 from a few directions) has never seen parts of the surface that new scans show.
There its field is an extrapolation and the good scans' own surface is absent, so a good scan's points read as far
from good surface as a defect's (good test scans scored up to 4x their calibration with 8 training scans:
docs/results.md, "Eight good scans"). The paper's stochastic field knows this (its variance grows where training
saw little); the good scans' points say it more sharply: a point is **covered** when a good scan's point lies within
``COVERAGE_LENGTHSCALES`` kernel lengthscales of it *across* the surface (in the point's tangent plane) on the same
side (their normals agree). Across, not straight: a bump, a dent or a blob sits above or below good surface, whose
points lie beneath it along its normal, so a defect on seen surface stays covered; a face no good scan saw has its
nearest good points beside it, at the border of what they saw.

A scan's score counts its covered points (:func:`inspection.scoring.score_evidence`); :func:`coverage_verdict`
turns a scan whose evidence lies on uncovered surface, or most of whose surface is uncovered, into ``'uncertain'``
with the reason, never into ``'good'`` or ``'defective'``.
"""
from dataclasses import dataclass

import numpy as np

# a point is covered when a good point on its side lies within this many kernel lengthscales of it across the
# surface; 0.5 (about 2.5-3 point spacings of the good scans' union with 8 training scans) ranked best on two parts
# with 8 training scans, and 0.25 and 1-1.5 worse (docs/results.md, "Eight good scans")
COVERAGE_LENGTHSCALES = 0.5
# coverage='auto' scores over covered points when the held-back good scans have at least this share of their points
# uncovered: on 2 parts x 3 seeds with 4, 8 and 16 training scans, the held-back scans' share was 0-0.4 % where
# coverage cost AUROC (fandisk with 16 scans: a missing patch exposes surface good parts never show) and 1.9-48 %
# where it gained or held it (docs/results.md, fewscans)
COVERAGE_MIN_SHARE = 0.01
# a scan with less than this share of its points on covered surface is 'uncertain' whatever its score
MIN_COVERED_SHARE = 0.5
# a scan with fewer covered points than this (or than 1 % of its points) is scored over every point, and 'uncertain'
MIN_COVERED_POINTS = 10
COVERAGE_NEIGHBOURS = 48  # good surface points examined per point (the nearest, in 3D)
NOT_COVERED = "not covered by good scans"


@dataclass
class Coverage:
    """Where a scored scan lies on surface the good scans covered.

    Attributes
    ----------
    covered : (m,) bool
        Per point of the scan (its own order): covered by the good scans (module docstring).
    radius : float
        The coverage radius used, model-frame units.
    score_all : float
        The scan's score over every point, covered or not (rays weighed in as for ``score``): what it would be
        without coverage.
    counted_all : bool
        Too few points were covered to score (``MIN_COVERED_POINTS``): the scan's score counts every point, and its
        verdict is 'uncertain' whatever it is.
    """

    covered: np.ndarray
    radius: float
    score_all: float
    counted_all: bool = False

    @property
    def uncovered_share(self):
        """The share of the scan's points not covered (0..1)."""
        return float(np.mean(~self.covered)) if len(self.covered) else 0.0


def coverage_radius(field, lengthscales=COVERAGE_LENGTHSCALES):
    """The coverage radius (model-frame units): ``lengthscales`` x the field's kernel lengthscale (``'auto'``:
    ``COVERAGE_LENGTHSCALES``), or None when the field has none (a callable; coverage then does not apply) or
    ``lengthscales`` is 0."""
    if lengthscales == "auto":
        lengthscales = COVERAGE_LENGTHSCALES
    lengthscale = getattr(field, "lengthscale", None)
    if not lengthscales or lengthscale is None or not np.isfinite(lengthscale) or lengthscale <= 0:
        return None
    return float(lengthscales) * float(lengthscale)


def across_gaps(reference, points, normals=None, neighbours=COVERAGE_NEIGHBOURS):
    """Per point, the distance across the surface to the nearest good point on its side.

    Parameters
    ----------
    reference : inspection.reference.LocalReference
        Its distinct surface points (every good training scan's) and, when stored, their normals.
    points : (m, 3) array
        Model frame.
    normals : (m, 3) array, optional
        The points' normals (any length, either orientation of a point's own is fine when the good scans' normals
        are unknown). None: each point takes the normal of its nearest good point.
    neighbours : int
        The nearest good points examined per point.

    Returns
    -------
    (m,) float64
        The smallest component, in the point's tangent plane, of the offset to a good point among its nearest whose
        normal faces the same side (all of them without normals); inf where none does.
    """
    index, surface_normals = reference.distinct_surface()
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    gaps = np.full(len(points), np.inf)
    if len(points) == 0:
        return gaps
    k = int(min(neighbours, index.n))
    for start in range(0, len(points), 20000):  # bounded memory for a full-resolution scan
        block = slice(start, start + 20000)
        _, idx = index.query(points[block], k)
        idx = idx.reshape(len(points[block]), k)
        offsets = index.data[idx] - points[block][:, None]
        if normals is not None:
            n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)[block]
        elif surface_normals is not None:
            n = surface_normals[idx[:, 0]]
        else:  # the nearest good point's direction stands for the normal: the gap is then 0 across
            n = offsets[:, 0]
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        along = np.einsum("mkj,mj->mk", offsets, n)
        across = np.linalg.norm(offsets - along[..., None] * n[:, None], axis=2)
        if surface_normals is not None and normals is not None:
            across = np.where(np.einsum("mj,mkj->mk", n, surface_normals[idx]) > 0, across, np.inf)
        gaps[block] = across.min(axis=1)
    return gaps


def decide_coverage(lengthscales, reference, held):
    """The coverage setting in force and the held-back scans' uncovered share: ``lengthscales`` as given unless
    ``'auto'``; then ``COVERAGE_LENGTHSCALES`` when the held-back good scans' evidence ``held`` (ScanEvidence, the
    calibration's out-of-sample scans: new good scans) has at least ``COVERAGE_MIN_SHARE`` of its kept points
    uncovered by ``reference``'s good surface, else 0 (every point counts). Returns (float, share or None)."""
    from .evidence import kept_points

    radius = None if reference is None or not held else coverage_radius(held[0].field, COVERAGE_LENGTHSCALES)
    share = None
    if radius is not None:
        kept = [kept_points(g.stray, len(g.points)) for g in held]
        covered = np.concatenate([covered_points(reference, g.points[k], None if g.normals is None else
                                                 g.normals[k], radius) for g, k in zip(held, kept)])
        share = float(np.mean(~covered)) if len(covered) else 0.0
    if lengthscales != "auto":
        return float(lengthscales), share
    return (COVERAGE_LENGTHSCALES if share is not None and share >= COVERAGE_MIN_SHARE else 0.0), share


def covered_points(reference, points, normals, radius):
    """(m,) bool: the points within ``radius`` across the surface of a good point on their side
    (:func:`across_gaps`); every point when ``radius`` is None."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if radius is None:
        return np.ones(len(points), dtype=bool)
    return across_gaps(reference, points, normals) <= radius


def coverage_verdict(verdict, reason, coverage, threshold, score):
    """A scan's verdict and reason (as :meth:`inspection.verdicts.VerdictMixin.reasons_from_scores` gives them from
    its score over covered points) with what coverage says: a ``'defective'`` verdict stands (its evidence lies on
    covered surface); any other becomes ``'uncertain'`` when less than ``MIN_COVERED_SHARE`` of its points are
    covered, or when its score over every point exceeds ``threshold`` while ``score``, over its covered points,
    does not (the evidence lies on surface no good scan saw). A scan too little of which was covered to score (``counted_all``) is ``'uncertain'`` whatever its verdict.
    ``coverage``: a :class:`Coverage` or None (unchanged). Returns (verdict, reason)."""
    if coverage is None or verdict == "error" or verdict == "defective" and not coverage.counted_all:
        return verdict, reason
    share = coverage.uncovered_share
    where = f"{100 * share:.0f} % of its points lie on surface no good scan saw from their side"
    if 1 - share < MIN_COVERED_SHARE or coverage.counted_all:
        why = f"{where}, so its score says little"
    elif coverage.score_all > threshold >= score:
        why = (f"its score over every point, {coverage.score_all:.4g}, is above the threshold, and what puts it "
               f"there lies on that surface ({where})")
    else:
        return verdict, reason
    return "uncertain", (f"{NOT_COVERED}: {why}; good scans from this side would decide (`nsspr-inspect coverage "
                         f"--model MODEL` proposes the views); {reason}")
