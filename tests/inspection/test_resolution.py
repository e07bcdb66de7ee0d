"""Scans denser than the model's training scans (inspection.resolution): a scan at the training density scored as it
is, a dense one on a subset at that density, end to end (its verdict, its dent measured, good dense scans at the
calibration's rate, its map and PLY on every point)."""
import csv

import numpy as np
import pytest

from inspection.resolution import SAMPLE_BELOW, EvidenceSample, evidence_sample, sampled_scan, training_spacing

from .spheres import RobustSphereModel, sphere_scan_with_dent


def test_a_scan_at_the_training_density_is_scored_on_every_point_and_a_dense_one_on_a_subset():
    from autodecoder.field.targets import point_spacing

    model = RobustSphereModel()
    spacing = training_spacing(model)
    assert spacing == pytest.approx(model.lengthscale / 2)  # the spacing the lengthscale was drawn from
    assert training_spacing(object()) is None  # a callable field: every point
    as_trained, _, _ = sphere_scan_with_dent(n=3000, seed=1)  # about the spacing the double's lengthscale says
    assert point_spacing(as_trained) == pytest.approx(spacing, rel=0.15)
    assert evidence_sample(as_trained, spacing) is None
    dense, normals, _ = sphere_scan_with_dent(n=60000, seed=2)
    sample = evidence_sample(dense, spacing)
    assert isinstance(sample, EvidenceSample) and sample.points_in == 60000
    assert len(sample.kept) < SAMPLE_BELOW * 60000 and sample.spacing == spacing
    assert point_spacing(dense[sample.kept]) == pytest.approx(spacing, rel=0.1)  # the training density
    assert np.array_equal(sample.kept, np.unique(sample.kept))
    assert np.array_equal(sample.kept, evidence_sample(dense, spacing).kept)  # seeded
    nearest = np.linalg.norm(dense[:500, None] - dense[sample.kept][None], axis=2).argmin(1)  # brute force
    assert np.array_equal(sample.inverse[:500], nearest)
    values = np.arange(len(sample.kept), dtype=float)
    assert np.array_equal(sample.full(values)[sample.kept], values)
    with pytest.raises(ValueError, match="scored points"):
        sample.full(values[:-1])
    assert evidence_sample(np.repeat(dense[:100], 600, axis=0), spacing) is None  # repeated points: no density
    kept_points, kept_normals = sampled_scan((dense, normals), sample.kept)
    assert np.array_equal(kept_points, dense[sample.kept]) and np.array_equal(kept_normals, normals[sample.kept])


def test_a_dense_scan_is_judged_and_measured_as_one_at_the_training_density():
    from inspection import Inspector

    good = [sphere_scan_with_dent(seed=s)[:2] for s in range(6)]
    held = [sphere_scan_with_dent(seed=50 + s)[:2] for s in range(30)]
    insp = Inspector(RobustSphereModel(), point_score="joint", alpha=0.05, coverage=0).fit(held,
                                                                                           reference_scans=good)
    depth = 0.03  # 10 noise deviations
    points, normals, _ = sphere_scan_with_dent(n=60000, seed=98, depth=depth)
    result = insp.inspect((points, normals))
    assert result.sample is not None and len(result.point_scores) == len(result.sample.kept) < 30000
    assert insp.predict([(points, normals)])[0] == -1
    regions, labels = insp.defect_regions((points, normals))
    assert len(regions) == 1 and regions[0].kind == "dent" and len(labels) == len(result.sample.kept)
    depths = []
    for seed in range(90, 95):  # its depth as measured at the training density: the median over five scans
        found = insp.defect_regions(sphere_scan_with_dent(n=60000, seed=seed, depth=depth)[:2])[0]
        assert len(found) == 1 and found[0].kind == "dent"
        depths.append(abs(found[0].deviation))
    assert abs(np.median(depths) - depth) <= 0.15 * depth
    assert len(insp.anomaly_map((points, normals))) == 60000  # the map on every point
    dense_good = [sphere_scan_with_dent(n=60000, seed=300 + s)[:2] for s in range(8)]
    assert (insp.predict(dense_good) == 1).sum() >= 7  # at the calibration's alpha of 0.05


def test_score_writes_every_point_of_a_dense_scan_and_says_how_many_were_scored(tmp_path):
    from datasets import ScanCollection, read_cloud
    from inspection.__main__ import main

    from .tiny import half_sphere, tiny_field_model

    scans = [half_sphere(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    scans += [half_sphere("test/good/000", "test", "good", seed=10),
              half_sphere("test/good/dense", "test", "good", seed=11, n=20000)]
    root = tiny_field_model(tmp_path, scans)
    assert main(["calibrate", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--alpha", "0.3",
                 "--quiet"]) == 0
    out = tmp_path / "out"
    assert main(["score", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--out", str(out),
                 "--split", "test", "--maps", "all", "--quiet"]) == 0
    rows = {r["name"]: r for r in csv.DictReader(open(out / "scores.csv"))}
    assert rows["test/good/000"]["points_scored"] == "" and rows["test/good/000"]["spacing"] == ""
    dense = rows["test/good/dense"]
    assert 0 < int(dense["points_scored"]) < 10000
    # the training spacing the lengthscale was drawn from; lengths of a fixed field's file are in its model frame's
    # units, as its regions' are (the field carries no file frame: inspection.regions.Units.of)
    assert float(dense["spacing"]) == pytest.approx(0.05 / 2)
    maps = [p for p in (out / "maps").glob("*.ply") if "dense" in p.name]
    with ScanCollection(root / "tree.h5") as c:
        n_dense = len(c[c.names.index("test/good/dense")].points)
    assert maps and all(len(read_cloud(p)[0]) == n_dense for p in maps)


def test_held_back_scans_at_full_resolution_calibrate_as_they_are_scored():
    """Dense held-back scans are thinned as new scans are: the threshold they set is the one scans at the training
    density set (1 % apart here), not that of every point (6 % lower: their top 1 % averages more points)."""
    from inspection import Inspector

    good = [sphere_scan_with_dent(seed=s)[:2] for s in range(6)]
    sparse = Inspector(RobustSphereModel(), point_score="joint", alpha=0.05, coverage=0).fit(
        [sphere_scan_with_dent(seed=50 + s)[:2] for s in range(30)], reference_scans=good)
    dense = Inspector(RobustSphereModel(), point_score="joint", alpha=0.05, coverage=0).fit(
        [sphere_scan_with_dent(n=60000, seed=50 + s)[:2] for s in range(30)], reference_scans=good)
    assert dense.threshold_ == pytest.approx(sparse.threshold_, rel=0.03)
