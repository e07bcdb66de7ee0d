"""A scanned member outside the trained family (inspection.family_range, issue 52 item 3), on the hinged plates
(tests/inspection/planes.py): a family of two members whose arm is bent 0 and 40 degrees about the hinge line x = 0,
their flat half alike. A member between them (20 degrees) scores like a trained member; one beyond them (60 degrees)
is 'uncertain - outside the trained family', never 'defective'; a dent on a member inside the range still is
'defective'."""
import numpy as np
import pytest

from datasets import Scan
from inspection import Inspector
from inspection.family_range import (MIN_SEEN_ANCHORS, OUTSIDE_FAMILY, OUTSIDE_SHARE, FamilyRange, family_range,
                                     family_verdict)
from inspection.member_spread import MemberSpread
from tests.inspection.planes import HingedModel, member_scan

TRAINED = (0.0, 40.0)


def member(degrees, seed, dent=None, name=None, dent_at=(0.7, 0.0)):
    points, normals = member_scan(np.tan(np.radians(degrees)), seed, n=4000, dent=dent, dent_at=dent_at, hinged=True)
    return Scan(name=name or f"bend{degrees:g}_{seed}", points=points.astype(np.float32),
                normals=normals.astype(np.float32))


@pytest.fixture(scope="module")
def fitted():
    """A 'joint' inspector of the two-member family: 4 training scans of each member as the good surface, 4 new
    scans of each held back for the threshold."""
    good = [member(d, 10 * i + j) for i, d in enumerate(TRAINED) for j in range(4)]
    held = [member(d, 100 + 10 * i + j) for i, d in enumerate(TRAINED) for j in range(4)]
    return Inspector(HingedModel(), point_score="joint", alpha=0.05).fit(held, reference_scans=good)


def test_a_member_between_the_trained_ones_scores_like_them_and_one_beyond_is_uncertain(fitted):
    spread = fitted.reference_.member_spread
    assert spread.differs and spread.has_envelope
    trained, between, beyond = member(40.0, 301), member(20.0, 302), member(60.0, 303)
    dented = member(20.0, 304, dent=0.03)
    scans = [trained, between, beyond, dented]
    results = [fitted.inspect(s) for s in scans]
    found = [r.family for r in results]
    assert all(f is not None and f.seen >= MIN_SEEN_ANCHORS for f in found)
    assert [f.outside for f in found] == [False, False, True, False]
    assert found[0].share < 0.05 and found[1].share < 0.05 and found[2].share > 0.8
    # the member half-way scores like a trained member's scan, not like a defect
    assert results[1].score < max(2 * results[0].score, fitted.threshold_)
    verdicts, reasons = fitted.verdicts_from_results(results, scans)
    assert verdicts == ["good", "good", "uncertain", "defective"]
    assert reasons[2].startswith(OUTSIDE_FAMILY)
    assert fitted.predict_verdict(scans).tolist() == verdicts  # the API says the same


def test_outside_the_family_a_scan_that_reads_as_good_stays_good_and_any_other_is_uncertain(fitted):
    """A member just beyond the range (44 degrees) lies outside, but its whole surface reads as a good part's:
    'good' stands. On the member beyond (60 degrees) a dent, on its flat half or on its arm, cannot be told from
    the member's own shape: 'uncertain', with the reason."""
    near = member(44.0, 311)
    flat = member(60.0, 312, dent=0.03, dent_at=(-0.5, 0.3))
    arm = member(60.0, 313, dent=0.03)
    results = [fitted.inspect(s) for s in (near, flat, arm)]
    assert all(r.family.outside for r in results)
    verdicts, reasons = fitted.verdicts_from_results(results, [near, flat, arm])
    assert verdicts == ["good", "uncertain", "uncertain"]
    assert all(why.startswith(OUTSIDE_FAMILY) for why in reasons[1:])
    assert fitted.verdicts_from_results(results, [near, flat, arm], uncertain=False)[0] == ["good", "defective",
                                                                                             "defective"]


def test_the_member_beyond_would_be_called_defective_without_the_family_range(fitted):
    """The reason the range is judged: carried only as far as the trained members reach, the 60-degree member's
    good scan scores above the threshold."""
    assert fitted.inspect(member(60.0, 305)).score > fitted.threshold_


def test_the_envelope_is_the_trained_members_closed_form_range(fitted):
    """At an anchor on the arms where both members' scans saw it, the envelope is the least and greatest signed
    distance to the two members' arms (closed form)."""
    spread = fitted.reference_.member_spread
    a = spread.anchors.astype(np.float64)
    slopes = np.tan(np.radians(TRAINED))
    exact = np.array([(a[:, 2] - s * a[:, 0]) / np.hypot(s, 1.0) for s in slopes])
    measured = np.isfinite(spread.low) & (np.abs(a[:, 1]) < 0.9) & (a[:, 0] > 0.2)
    assert measured.sum() > 1000
    np.testing.assert_allclose(spread.low[measured], exact.min(0)[measured], atol=5e-3)
    np.testing.assert_allclose(spread.high[measured], exact.max(0)[measured], atol=5e-3)


def test_no_verdict_changes_without_a_family_or_an_envelope(fitted):
    spread = fitted.reference_.member_spread
    old = MemberSpread(spread.anchors, spread.between)  # a version 5 calibration's: no envelope
    reference = fitted.reference_
    scan = member(60.0, 306)
    try:
        reference.member_spread = old
        assert family_range(reference, HingedModel().project(scan.points).field, scan.points, scan.normals) is None
        reference.member_spread = MemberSpread(spread.anchors, np.zeros_like(spread.between), spread.low,
                                               spread.high, spread.own)  # members that do not differ
        assert family_range(reference, HingedModel().project(scan.points).field, scan.points, scan.normals) is None
    finally:
        reference.member_spread = spread
    assert family_verdict("defective", "w", None) == ("defective", "w")
    few = FamilyRange(MIN_SEEN_ANCHORS - 1, MIN_SEEN_ANCHORS - 1)
    assert family_verdict("defective", "w", few) == ("defective", "w")
    assert family_verdict("good", "w", FamilyRange(100, 90)) == ("good", "w")
    patch = FamilyRange(1000, int(OUTSIDE_SHARE * 1000) - 1)  # a patch beyond, as a defect moves the field
    assert not patch.outside and family_verdict("defective", "w", patch) == ("defective", "w")
    for verdict in ("defective", "uncertain"):
        told, why = family_verdict(verdict, "w", FamilyRange(100, 90))
        assert told == "uncertain" and why.startswith(OUTSIDE_FAMILY) and "90 %" in why and why.endswith("; w")


def test_the_envelope_round_trips_and_bad_envelopes_are_one_clear_error(fitted):
    spread = fitted.reference_.member_spread
    back = MemberSpread.from_dict(spread.as_dict())
    for key in ("low", "high", "own"):
        np.testing.assert_array_equal(getattr(back, key), getattr(spread, key))
    n = len(spread.anchors)
    with pytest.raises(ValueError, match="together"):
        MemberSpread(spread.anchors, spread.between, spread.low)
    with pytest.raises(ValueError, match="one low, high and own per anchor"):
        MemberSpread(spread.anchors, spread.between, spread.low[:-1], spread.high[:-1], spread.own[:-1])
    with pytest.raises(ValueError, match="high >= low"):
        MemberSpread(spread.anchors[:2], spread.between[:2], [0.0, 1.0], [-1.0, 2.0], [0.1, 0.1])
    assert n == len(back.anchors)
