"""The good surface carried to the scanned member of a family whose members differ (inspection.member_surface), on
tilted planes z = a x whose signed distance is known in closed form: members differ by their slope a, most far from
the hinge line x = 0."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from inspection.calibration import CALIBRATION_VERSION, migrate
from inspection.evidence import ScanEvidence
from inspection.member_spread import MEMBER_SHARE, MemberSpread
from inspection.member_surface import MEMBER_SPREAD_FLOOR, SMOOTHING_ANCHORS, carried_surface, fit_member_spread
from inspection.reference import LocalReference, field_quantity
from inspection.scores import reference_terms
from tests.inspection.planes import NOISE, Tilted, member_scan


def _evidence(slope, seed, dent=None):
    points, normals = member_scan(slope, seed, dent=dent)
    field = Tilted(slope)
    return ScanEvidence(f"a{slope}_{seed}", points, field, value=field_quantity(field, points),
                        variance=np.zeros(len(points)), normals=normals)


def _reference(slopes, scans_each=3):
    goods = [_evidence(a, 10 * i + j) for i, a in enumerate(slopes) for j in range(scans_each)]
    reference = LocalReference(np.concatenate([g.points for g in goods]), np.concatenate([g.value for g in goods]),
                               surface_normals=np.concatenate([g.normals for g in goods]),
                               surface_points=np.concatenate([g.points for g in goods]))
    reference.member_spread = fit_member_spread(reference, goods)
    return reference, goods


def test_member_spread_is_the_members_variance_beyond_the_floor():
    """Members of slopes -0.01 to 0.01 all lie within a lengthscale of each other over the square: at an anchor,
    every scan's field counts, and the members' variance is the closed form's sample variance of the signed
    distances to the members' planes, less the floor times the reference's own spread."""
    slopes = (-0.01, -0.005, 0.005, 0.01)
    reference, _ = _reference(slopes)
    spread = reference.member_spread
    a = spread.anchors.astype(np.float64)
    exact = np.array([(a[:, 2] - s * a[:, 0]) / np.hypot(s, 1.0) for s in slopes for _ in range(3)])
    _, own = reference.stats(a)
    raw = np.maximum(exact.var(0, ddof=1) - MEMBER_SPREAD_FLOOR * own**2, 0.0)
    expected = np.median(raw[cKDTree(a).query(a, SMOOTHING_ANCHORS)[1]], axis=1)  # each anchor's neighbourhood's
    inside = np.abs(a[:, :2]).max(1) < 0.9  # away from the square's border, where fewer scans reach an anchor
    assert np.allclose(spread.between[inside], expected[inside], rtol=0.05, atol=1e-7)
    far, hinge = inside & (np.abs(a[:, 0]) > 0.6), inside & (np.abs(a[:, 0]) < 0.05)
    assert spread.between[far].min() > 5e-6 and spread.between[hinge].max() < 1e-7


def test_one_shape_moves_nothing():
    """Scans of one member: no spread beyond the floor anywhere, nothing carried, the term as before."""
    reference, goods = _reference((0.0, 0.0, 0.0))
    assert reference.member_spread is not None and not reference.member_spread.differs
    scan = _evidence(0.0, 99)
    assert carried_surface(reference, reference.member_spread, scan.field, scan.points) is None
    plain = LocalReference.from_dict({**reference.as_dict(), "member_spread": None})
    got = reference_terms(reference, scan.points, scan.value, scan.variance, NOISE, normals=scan.normals,
                          field=scan.field)
    want = reference_terms(plain, scan.points, scan.value, scan.variance, NOISE, normals=scan.normals)
    assert np.array_equal(got[1], want[1])


def test_members_that_differ_over_a_small_share_move_nothing():
    """Members differing over less than ``MEMBER_SHARE`` of the anchors (partial views of one part do, at a few %)
    are a part of one shape: the term is the good points' as they lie, and calibrate's summary says nothing."""
    from inspection.job import _member_note

    reference, _ = _reference((0.0, 0.04, 0.0, 0.04))
    spread = reference.member_spread
    assert spread.differs and spread.share > MEMBER_SHARE
    note = _member_note(SimpleNamespace(reference_=reference))
    assert len(note) == 1 and f"{100 * spread.share:.0f} % of their surface" in note[0]
    keep = np.argsort(-spread.between)[:int(0.9 * MEMBER_SHARE * len(spread.between))]
    few = np.zeros_like(spread.between)
    few[keep] = spread.between[keep]
    reference.member_spread = MemberSpread(spread.anchors, few)
    assert not reference.member_spread.differs and _member_note(SimpleNamespace(reference_=reference)) == []
    scan = _evidence(0.07, 78)
    got = reference_terms(reference, scan.points, scan.value, scan.variance, NOISE, normals=scan.normals,
                          field=scan.field)
    want = reference_terms(reference, scan.points, scan.value, scan.variance, NOISE, normals=scan.normals)
    assert np.array_equal(got[1], want[1])


def test_a_member_off_the_trained_ones_scores_like_a_trained_one_and_a_dent_on_it_still_shows():
    """Members of slopes 0 and 0.04: a good scan of slope 0.07, whose points lie up to 0.03 (30 noise) off the
    nearest trained member, reads as far off as a defect against the good points as they lie, and like a trained
    member's scan against the good points carried to it; a dent of 0.01 on it still stands out."""
    reference, _ = _reference((0.0, 0.04, 0.0, 0.04))
    trained = _evidence(0.04, 77)
    new = _evidence(0.07, 78)

    def good_points_term(scan, carried=True):
        return reference_terms(reference, scan.points, scan.value, scan.variance, NOISE, normals=scan.normals,
                               field=scan.field if carried else None)[1]

    arm = np.abs(new.points[:, 0] - 0.8) < 0.15
    assert np.median(good_points_term(new, carried=False)[arm]) > 10
    assert np.median(good_points_term(new)[arm]) < 2 * max(np.median(good_points_term(trained)[arm]), 0.5)
    dented = _evidence(0.07, 78, dent=0.01)
    pit = np.hypot(dented.points[:, 0] - 0.7, dented.points[:, 1]) < 0.1
    assert np.median(good_points_term(dented)[pit]) > 5


def test_members_far_apart_carry_a_member_half_way_between():
    """The issue's two members bent 0 and 35 degrees apart (slopes 0 and 0.7): far from the hinge their surfaces lie
    many lengthscales apart, so each anchor is counted by the other member's field where it lands on that member's
    surface; a good scan of the member half-way (slope 0.35) then reads like a trained member's, where the good
    points as they lie put it 30 lengthscales off."""
    reference, _ = _reference((0.0, 0.7, 0.0, 0.7))
    far = np.abs(reference.member_spread.anchors[:, 0]) > 0.5
    assert reference.member_spread.between[far].min() > 0.01
    trained, new = _evidence(0.7, 77), _evidence(0.35, 78)
    arm = np.abs(new.points[:, 0] - 0.8) < 0.15
    terms = [reference_terms(reference, s.points, s.value, s.variance, NOISE, normals=s.normals, field=f)[1][arm]
             for s, f in ((new, None), (new, new.field), (trained, trained.field))]
    assert np.median(terms[0]) > 100
    assert np.median(terms[1]) < 2 * max(np.median(terms[2]), 0.5)


def test_member_spread_round_trip_and_bad_input():
    reference, _ = _reference((0.0, 0.04, 0.0, 0.04))
    stored = LocalReference.from_dict(reference.as_dict())
    assert np.array_equal(stored.member_spread.between, reference.member_spread.between)
    assert np.array_equal(stored.member_spread.anchors, reference.member_spread.anchors)
    with pytest.raises(ValueError, match="one variance per anchor"):
        MemberSpread(np.zeros((3, 3)), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        MemberSpread(np.zeros((2, 3)), np.array([0.1, -1.0]))
    for damaged in ("spread", {"anchors": np.zeros((2, 3))}, {"anchors": np.zeros((2, 3)), "between": [np.nan, 0]}):
        with pytest.raises(ValueError, match="member_spread|finite"):
            MemberSpread.from_dict(damaged)


def test_a_version_4_calibration_scores_as_it_was_calibrated():
    """A record written before the member spread reads with none: the good points as they lie."""
    record = {"version": 4, "scores": [1.0], "names": ["a"], "aggregate": "top1", "point_score": "joint",
              "roles": ["held-back"],
              "extra": {"config": {}, "reading": None, "parts": None, "level_rendered": False, "rays": None,
                        "align": None, "regions": None,
                        "reference": {"points": np.zeros((20, 3)), "values": np.zeros(20), "k": 16}}}
    upgraded = migrate(record)
    assert upgraded["version"] == CALIBRATION_VERSION and upgraded["extra"]["reference"]["member_spread"] is None
    assert "member_spread" not in record["extra"]["reference"]  # the record given is not modified
