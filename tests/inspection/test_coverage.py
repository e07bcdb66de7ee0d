"""inspection.coverage and coverage_views (issue 48): which points lie on surface the good scans covered, the verdict
a scan whose evidence lies elsewhere gets, and the views that would cover it.

The part is the analytic sphere (tests/inspection/spheres.py): good scans see its upper half only, so its lower half
is a face no good scan saw."""
import numpy as np
import pytest

from datasets import Scan
from inspection import Inspector
from inspection.coverage import (COVERAGE_LENGTHSCALES, NOT_COVERED, Coverage, across_gaps, coverage_radius, coverage_verdict,
                                 covered_points)
from inspection.coverage_views import plan_views, seen_from, sphere_directions
from inspection.reference import LocalReference
from tests.inspection.spheres import ScaledSphereField, ScaledSphereModel, SphereField, sphere_scan

def half_sphere(n=1500, seed=0, dent=0.0, lower=False, name="scan"):
    """A one-view scan of the upper (or ``lower``) half sphere with its outward normals, as a Scan."""
    points, directions = sphere_scan(n=n, seed=seed, dent=dent)
    if lower:
        centre = np.array([0.1, -0.2, 0.05])
        points = (points - centre) * np.array([1, 1, -1]) + centre
        directions = directions * np.array([1, 1, -1])
    return Scan(name=name, points=points.astype(np.float32), normals=directions.astype(np.float32))


def plane_reference(spacing=0.02, half=0.5):
    """A reference over a square of the plane z = 0 (normals +z), side 2 x ``half``."""
    g = np.arange(-half, half + 1e-9, spacing)
    x, y = np.meshgrid(g, g)
    pts = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    return LocalReference(pts, np.zeros(len(pts)), surface_points=pts, surface_normals=normals)


def test_the_gap_across_the_surface_is_the_distance_beside_the_good_points_not_above_them():
    ref = plane_reference()
    up = np.tile([0.0, 0.0, 1.0], (4, 1))
    queries = np.array([[0.001, 0.001, 0.03],  # above good surface (a bump's top): nothing beside it
                        [0.001, 0.001, -0.04],  # below it (a dent's floor)
                        [0.6, 0.0, 0.0],  # 0.1 beyond the square's edge, in its plane
                        [0.5, 0.8, 0.0]])  # 0.3 beyond another edge
    gaps = across_gaps(ref, queries, up)
    np.testing.assert_allclose(gaps[:2], np.hypot(0.001, 0.001), atol=1e-9)  # the grid point at the origin
    np.testing.assert_allclose(gaps[2:], [0.1, 0.3], atol=1e-9)
    # the other side of the surface: no good point faces the way these do
    assert np.isinf(across_gaps(ref, queries[:2], -up[:2])).all()
    # without the points' normals the nearest good point's normal stands in
    np.testing.assert_allclose(across_gaps(ref, queries[:1]), np.hypot(0.001, 0.001), atol=1e-9)
    covered = covered_points(ref, queries, up, radius=0.05)
    assert covered.tolist() == [True, True, False, False]
    assert covered_points(ref, queries, up, radius=None).all()


def test_the_coverage_radius_is_lengthscales_of_the_field_or_nothing():
    assert coverage_radius(ScaledSphereField(), 0.5) == pytest.approx(0.05)
    assert coverage_radius(SphereField(), 0.5) is None  # no lengthscale: coverage does not apply
    assert coverage_radius(ScaledSphereField(), 0) is None


@pytest.mark.parametrize("verdict, covered_share, score, score_all, counted_all, expected", [
    ("defective", 0.9, 6.0, 7.0, False, "defective"),  # evidence on covered surface stands
    ("defective", 0.0, 6.0, 6.0, True, "uncertain"),  # too little covered to score: whatever the score
    ("good", 0.3, 1.0, 1.0, False, "uncertain"),  # most of it uncovered
    ("good", 0.9, 1.0, 9.0, False, "uncertain"),  # the evidence lies on uncovered surface
    ("good", 0.9, 1.0, 2.0, False, "good"),  # below the threshold either way
    ("uncertain", 0.9, 4.5, 4.9, False, "uncertain"),  # the threshold's own uncertainty, coverage says nothing
])
def test_coverage_turns_a_verdict_uncertain_only_where_the_evidence_is_not_covered(
        verdict, covered_share, score, score_all, counted_all, expected):
    covered = np.arange(100) < round(100 * covered_share)
    got, why = coverage_verdict(verdict, "score ...", Coverage(covered, 0.05, score_all, counted_all), 5.0, score)
    assert got == expected
    assert (NOT_COVERED in why) == (expected == "uncertain" and verdict != "uncertain")
    assert why.endswith("score ...")  # the threshold's own words are kept
    assert coverage_verdict(verdict, "w", None, 5.0, score) == (verdict, "w")


@pytest.fixture(scope="module")
def fitted():
    """A 'joint' inspector of the scaled sphere: good scans of the upper half only."""
    good = [half_sphere(seed=s, name=f"good{s}") for s in range(6)]
    held = [half_sphere(seed=s, name=f"held{s}") for s in range(20, 26)]
    return Inspector(ScaledSphereModel(), point_score="joint", alpha=0.05, coverage=0.5).fit(held,
                                                                                              reference_scans=good)


def test_coverage_auto_is_on_where_new_good_scans_show_uncovered_surface():
    """coverage='auto': off when the held-back scans lie on surface the training scans covered (every point counts,
    as before coverage), on when they show at least COVERAGE_MIN_SHARE of uncovered surface (the calibration says
    so in its source)."""
    good = [half_sphere(seed=s, name=f"good{s}") for s in range(6)]
    covered_held = [half_sphere(seed=s, name=f"held{s}") for s in range(20, 24)]
    off = Inspector(ScaledSphereModel(), point_score="joint", alpha=0.05).fit(covered_held, reference_scans=good)
    assert off.settings_.coverage == 0.0 and off.inspect(covered_held[0]).coverage is None
    wider = [Scan(name=f"wide{i}", points=np.vstack([s.points, low.points[:100]]),
                  normals=np.vstack([s.normals, low.normals[:100]]))
             for i, (s, low) in enumerate(zip(covered_held, [half_sphere(seed=30 + i, lower=True) for i in range(4)]))]
    on = Inspector(ScaledSphereModel(), point_score="joint", alpha=0.05).fit(wider, reference_scans=good)
    assert on.settings_.coverage == COVERAGE_LENGTHSCALES and on.inspect(wider[0]).coverage is not None
    assert "scored over covered surface" in on.calibration_source_


def test_a_face_no_good_scan_saw_is_uncertain_not_covered_and_a_dent_on_a_covered_face_is_defective(fitted):
    unseen = half_sphere(seed=50, lower=True, name="unseen face")
    dented = half_sphere(seed=51, dent=0.05, name="dent")
    good = half_sphere(seed=52, name="good")
    results = [fitted.inspect(s) for s in (unseen, dented, good)]
    assert results[0].coverage.uncovered_share > 0.5 and results[1].coverage.uncovered_share < 0.05
    verdicts, reasons = fitted.verdicts_from_results(results, [unseen, dented, good])
    assert verdicts == ["uncertain", "defective", "good"]
    assert reasons[0].startswith(NOT_COVERED)
    assert fitted.predict_verdict([unseen, dented, good]).tolist() == verdicts  # the API says the same


def test_the_score_counts_the_covered_points_only(fitted):
    """A good upper scan with a strip of the lower half added: the strip is uncovered, so the score is that of the
    upper points alone (the same as the scan without the strip, up to the aggregate's share of points)."""
    upper = half_sphere(seed=60, name="upper")
    lower = half_sphere(n=200, seed=61, lower=True)
    strip = lower.points[:, 2] < 0.05 - 0.4  # well below the equator
    both = Scan(name="both", points=np.vstack([upper.points, lower.points[strip]]),
                normals=np.vstack([upper.normals, lower.normals[strip]]))
    result = fitted.inspect(both)
    assert not result.coverage.covered[len(upper.points):].any()
    counted = result.point_scores[result.coverage.covered]
    k = int(np.ceil(0.01 * len(counted)))
    assert result.score == pytest.approx(np.sort(counted)[-k:].mean())
    assert result.components["points_all"] >= result.score


def test_the_proposed_view_covers_the_unseen_face(fitted):
    unseen = half_sphere(seed=70, lower=True)
    radius = coverage_radius(ScaledSphereField(), 0.5)
    plan = plan_views(fitted.reference_, unseen.points, unseen.normals, radius, n_views=2, candidates=64)
    first = plan.views[0]
    centre = np.array([0.1, -0.2, 0.05])
    assert (first.position - centre)[2] < -0.5 * np.linalg.norm(first.position - centre)  # from below
    uncovered = ~plan.covered
    # one view sees a cap of the face (incidence below 75 degrees), the second most of the rest
    assert uncovered.mean() > 0.5 and (plan.first_view[uncovered] == 0).mean() > 0.5
    assert plan.views[0].gain > plan.views[1].gain > 0 and plan.remaining_share < 0.2
    # the first view sees the lower face; a view from straight above sees none of it
    above = centre + np.array([0, 0, 3.0])
    assert not seen_from(above, unseen.points[uncovered], unseen.normals[uncovered], unseen.points[:10]).any()


def test_candidate_directions_cover_the_sphere_evenly():
    d = sphere_directions(500)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.abs(d.mean(0)).max() < 0.01  # balanced
    with pytest.raises(ValueError):
        sphere_directions(0)


def test_bad_targets_are_one_clear_error(fitted):
    with pytest.raises(ValueError, match="finite target points"):
        plan_views(fitted.reference_, np.zeros((0, 3)), np.zeros((0, 3)), 0.05)
    with pytest.raises(ValueError, match="n_views"):
        plan_views(fitted.reference_, np.ones((3, 3)), np.ones((3, 3)), 0.05, n_views=0)


def test_the_coverage_command_writes_the_picture_the_cloud_and_the_plan(tmp_path, capsys):
    """`nsspr-inspect coverage` on a calibrated (tiny) model: coverage.png, coverage.ply and coverage.json, the
    views printed; an uncalibrated model is one clear error naming the command that calibrates it."""
    import json

    from datasets import Scan as _Scan
    from inspection.__main__ import main

    from .tiny import half_sphere as tiny_scan, tiny_field_model

    scans = [tiny_scan(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    scans += [tiny_scan(f"test/good/{i:03d}", "test", "good", seed=10 + i) for i in range(2)]
    lower = [_Scan(name=f"test/good/low{i}", points=s.points * np.array([1, 1, -1], np.float32),
                   normals=s.normals * np.array([1, 1, -1], np.float32), split="test", label="good")
             for i, s in enumerate(scans[6:])]
    work = tiny_field_model(tmp_path, scans + lower)
    model = work / "model.pt"
    assert main(["coverage", "--model", str(model), "--data", str(work / "tree.h5"), "--out",
                 str(tmp_path / "cov"), "--quiet"]) == 2
    assert "not calibrated" in capsys.readouterr().err
    assert main(["calibrate", "--model", str(model), "--data", str(work / "tree.h5"), "--coverage", "nope",
                 "--quiet"]) == 2
    assert "coverage must be 'auto' or a number" in capsys.readouterr().err
    assert main(["calibrate", "--model", str(model), "--data", str(work / "tree.h5"), "--coverage", "0.5",
                 "--quiet"]) == 0
    capsys.readouterr()
    # scored with coverage: each scan's uncovered share and verdict in words; the lower halves no good scan saw
    # are 'uncertain', their maps show where
    assert main(["score", "--model", str(model), "--data", str(work / "tree.h5"), "--out", str(tmp_path / "res"),
                 "--maps", "all", "--quiet"]) == 0
    import csv

    rows = {r["name"]: r for r in csv.DictReader(open(tmp_path / "res" / "scores.csv"))}
    low = rows["test/good/low0"]
    assert float(low["uncovered"]) > 0.5 and low["verdict"] == "uncertain" and "not covered" in low["why"]
    assert float(rows["test/good/000"]["uncovered"]) < 0.5
    assert (tmp_path / "res" / "maps" / "coverage" / "test__good__low0.ply").exists()
    capsys.readouterr()
    assert main(["coverage", "--model", str(model), "--data", str(work / "tree.h5"), "--split", "test", "--n", "2",
                 "--out", str(tmp_path / "cov"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "view 1:" in out and "coverage of" in out
    plan = json.loads((tmp_path / "cov" / "coverage.json").read_text())
    assert 1 <= len(plan["views"]) <= 2 and plan["uncovered_share"] > 0.2  # the lower halves: never seen
    assert (tmp_path / "cov" / "coverage.png").stat().st_size > 0
    from datasets import read_cloud

    assert len(read_cloud(tmp_path / "cov" / "coverage.ply")[0]) == plan["points"]
