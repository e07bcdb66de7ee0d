"""Whether a scanned member lies outside the family the model was trained on: beyond every trained member's surface
over much of the surface where the members differ.

Why: in a product family (a bracket bent to several angles, a housing with its holes in different places) the good
surface is carried to the scanned member (:mod:`inspection.member_surface`), which follows a member between the
trained ones. A member beyond them (bent further than any trained member) is carried only as far as the trained
members reach, and its good scans read as defects. Such a scan says nothing about defects: its verdict is
``uncertain - outside the trained family``, never ``defective`` (issue 52, item 3).

How. At calibration (:func:`inspection.member_surface.fit_member_spread`) each anchor of the good surface keeps the
trained members' envelope: the least and the greatest first-order distance of the anchor to a good scan's own field,
over every reference scan's field (``MemberSpread.low``, ``high``: each code decodes a whole member, and a member
between two trained ones is often seen at an anchor by scans of one side only), and the reference's own spread s_ref
there. At scoring (:func:`family_range`), the scan's own projected field gives the same distance d at the anchors
where the members differ (tau^2 > 0) and that the scan saw (:func:`inspection.member_surface.seen_distances`, the
criterion the calibration counts a field by). An anchor lies *beyond* when d is outside [low - m, high + m], with the
margin m = ``OUTSIDE_MARGIN`` s_ref; the scan lies outside the trained family when at least ``OUTSIDE_SHARE`` of at
least ``MIN_SEEN_ANCHORS`` such anchors lie beyond. A member between the trained ones lies inside the envelope; a
defect moves the field over a patch of it, a member beyond the range over much of what moves with it.
"""
from dataclasses import dataclass

import numpy as np

# an anchor lies beyond the trained members when the scan's field distance there is outside their envelope by more
# than this many of the reference's own spreads s_ref, and a scan is outside the trained family when at least this
# share of the anchors it saw where the members differ lie beyond them. Chosen on fandisk bent 24-48 degrees either
# way (seed 0): at 3 s_ref, the untrained member at 0 degrees inside the range had at most 0.038 of its anchors
# beyond (good scans) and 0.049 (defective ones, 4 of each type), the held-back scans 0.007; the member at 60
# degrees, beyond it, 0.034-0.225 (14 of 16 good scans at 0.06 or more). A member 6 degrees beyond a family bent
# 6-12 degrees either way lies 0-0.099 beyond, most of it below: it is told only where it lies far beyond
# (docs/results_archive.md, "Families that bend: beyond the range")
OUTSIDE_MARGIN = 3.0
OUTSIDE_SHARE = 0.06
# and it saw at least this many of them (fewer: the family's range is not judged, as for a part of one shape)
MIN_SEEN_ANCHORS = 30
OUTSIDE_FAMILY = "outside the trained family"


@dataclass
class FamilyRange:
    """Where a scanned member lies against the trained family.

    Attributes
    ----------
    seen : int
        The anchors where the members differ that the scan saw.
    beyond : int
        Of those, the anchors where the scan's field lies beyond every trained member's (by the margin).
    """

    seen: int
    beyond: int

    @property
    def share(self):
        """The share of the seen anchors that lie beyond, 0..1 (0 with none seen)."""
        return self.beyond / self.seen if self.seen else 0.0

    @property
    def outside(self):
        """Whether the scan's member lies outside the trained family (module docstring)."""
        return self.seen >= MIN_SEEN_ANCHORS and self.share >= OUTSIDE_SHARE


def family_range(reference, field, points, normals):
    """The :class:`FamilyRange` of a scan, or None where the family's range is not judged: no member spread, members
    that do not differ (``MemberSpread.differs``), an envelope not measured (a calibration of version 5), a field
    without a kernel lengthscale, or a scan without normals.

    Parameters
    ----------
    reference : inspection.reference.LocalReference or None
        Its ``member_spread`` and its distinct surface's normals (the anchors' sides).
    field : stochastic field
        The scan's projected field (``mean_and_gradient``, ``lengthscale``; model frame).
    points, normals : (m, 3) arrays
        The scan's points and unit outward normals (model frame).
    """
    from .member_surface import seen_distances

    spread = getattr(reference, "member_spread", None)
    lengthscale = getattr(field, "lengthscale", None)
    if (spread is None or not spread.differs or not spread.has_envelope or normals is None or not lengthscale
            or len(points) == 0 or reference.distinct_surface()[1] is None):
        return None
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    moving = np.flatnonzero((spread.between > 0) & np.isfinite(spread.low))
    reach = 2.0 * lengthscale + spread.extent  # anchors farther from every scanned point cannot have been seen
    box = moving[((spread.anchors[moving] >= points.min(0) - reach)
                  & (spread.anchors[moving] <= points.max(0) + reach)).all(1)]
    if len(box) == 0:
        return FamilyRange(0, 0)
    anchors = spread.anchors[box].astype(np.float64)
    scan = _Scan(field, points, np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    distance, saw = (a[0] for a in seen_distances([scan], anchors, spread.anchor_sides(reference)[box], lengthscale))
    margin = OUTSIDE_MARGIN * spread.own[box].astype(np.float64)
    beyond = (distance < spread.low[box] - margin) | (distance > spread.high[box] + margin)
    return FamilyRange(int(saw.sum()), int((saw & beyond).sum()))


@dataclass
class _Scan:
    """The scan as :func:`inspection.member_surface.seen_distances` reads one."""

    field: object
    points: np.ndarray
    normals: np.ndarray


def family_verdict(verdict, reason, found):
    """A scan's verdict and reason with what its :class:`FamilyRange` ``found`` says: a scan whose member lies
    outside the trained family and whose verdict is not ``'good'`` is ``'uncertain'``, never ``'defective'``: its
    good points were carried only as far as the trained members reach, so a good part reads as a defective one, and
    a defect cannot be told from the member's own shape. A ``'good'`` verdict stands (its whole surface reads as a
    good part's); ``found`` None or not outside: unchanged. Returns (verdict, reason)."""
    if found is None or not found.outside or verdict in ("error", "good"):
        return verdict, reason
    return "uncertain", (f"{OUTSIDE_FAMILY}: {100 * found.share:.0f} % of the surface it shows where the trained "
                         f"members differ lies beyond every one of them, so its score cannot tell a defect from the "
                         f"member's own shape; train on members like it (their good scans among the training scans) "
                         f"to judge it; {reason}")
