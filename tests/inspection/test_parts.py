"""Inspection of a model trained on several part types: each part calibrated on its own good scans, with its own
threshold; a scan of a part the model does not know is refused with a message naming the parts it knows."""
import numpy as np
import pytest

from datasets.scan import Scan

TINY = dict(latent_dim=2, width=16, depth=1, features=8, mean_samples=128, screen_samples=64, pair_clusters=4,
            batch=4, epochs=3)


def _sphere(name, radius, part, seed, split="train", label="good", defect=""):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(300, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return Scan(points=(radius * v).astype(np.float32), normals=v.astype(np.float32), name=name, split=split,
                label=label, defect=defect, part_id=part)


@pytest.fixture(scope="module")
def two_part_run(tmp_path_factory, one_torch_thread):
    from autodecoder.latent.folds import train_collection_with_folds as train_collection
    from datasets.collection import ScanCollection

    tmp = tmp_path_factory.mktemp("parts")
    scans = []
    for i, (part, r) in enumerate((("a", 0.15), ("b", 0.3))):
        scans += [_sphere(f"{part}/train/{k:03d}", r, part, 100 * i + k) for k in range(6)]
        scans += [_sphere(f"{part}/test/good", r, part, 100 * i + 50, split="test"),
                  _sphere(f"{part}/test/bad", 1.3 * r, part, 100 * i + 51, split="test", label="defective",
                          defect="dent")]
    data = ScanCollection.create(tmp / "ab.h5", scans)
    model = tmp / "model.pt"
    train_collection(data, model, calibration_fraction=0.34, quiet=True, calibration_folds=2, **TINY)
    from inspection.job import calibrate

    insp, info = calibrate(model, data, progress=False)  # stored in the model file
    return data, model, tmp, insp, info


def test_calibration_and_thresholds_are_per_part(two_part_run):
    from inspection.job import describe_calibration

    insp, info = two_part_run[3:]
    assert sorted(insp.parts_) == ["a", "b"]
    for part, one in insp.parts_.items():  # each part: its own held-back scans, its training scans by fold models
        assert one.calibration_names_ and all(n.startswith(f"{part}/") for n in one.calibration_names_)
        assert one.calibration_roles_.count("held-back") == 2 and one.calibration_roles_.count("fold") == 4
    assert set(info["parts"]) == {"a", "b"}
    lines = describe_calibration(insp, info)
    assert any(line.startswith("part a: threshold") for line in lines)
    assert any(line.startswith("part b: threshold") for line in lines)


def test_scoring_uses_each_parts_threshold_and_stored_calibration(two_part_run):
    from inspection.estimator import Inspector
    from inspection.model_io import load_model_handle
    from inspection.run import score

    data, model, tmp = two_part_run[:3]
    lines = []
    summary = score(model, data, tmp / "results", progress=False, maps="none", echo=lines.append)
    assert "thresholds per part: a " in lines[0]
    assert set(summary["parts"]) == {"a", "b"} and summary["decision"] is None
    handle = load_model_handle(model)
    loaded = Inspector.from_calibration(handle.model, handle.calibration)
    rows = {r["name"]: r for r in _read_csv(tmp / "results" / "scores.csv")}
    for part in ("a", "b"):
        t = loaded.parts_[part].threshold_
        assert summary["parts"][part]["threshold"] == pytest.approx(t)
        for name in (f"{part}/test/good", f"{part}/test/bad"):
            score = float(rows[name]["score"])
            verdict = "defective" if score > t else "good"
            if loaded.parts_[part].decision_threshold_.uncertain([score])[0]:  # within the part's own uncertainty
                verdict = "uncertain"
            assert rows[name]["verdict"] == verdict


def test_a_scan_of_an_unknown_part_is_refused(two_part_run):
    from inspection.estimator import Inspector
    from inspection.model_io import load_model_handle

    handle = load_model_handle(two_part_run[1])
    insp = Inspector.from_calibration(handle.model, handle.calibration)
    for part, match in (("c", r"part_id 'c'.*\['a', 'b'\]"), ("", "no part_id")):
        with pytest.raises(ValueError, match=match):
            insp.inspect(_sphere("x", 0.2, part, 1))
    with pytest.raises(ValueError, match="pass the scans"):
        insp.predict_from_scores([1.0])  # no threshold of its own: each scan against its part's


def test_a_single_part_model_keeps_one_inspector(tmp_path, one_torch_thread):
    from autodecoder.latent.train import train_collection
    from datasets.collection import ScanCollection
    from inspection.estimator import Inspector
    from inspection.job import calibrate

    scans = [_sphere(f"train/{k:03d}", 0.2, "a", k) for k in range(5)]
    data = ScanCollection.create(tmp_path / "a.h5", scans)
    train_collection(data, tmp_path / "m.pt", calibration_fraction=0.4, quiet=True, **TINY)
    insp, info = calibrate(tmp_path / "m.pt", data, progress=False)
    assert type(insp) is Inspector and not insp.parts_ and "threshold" in info and insp.for_scan(scans[0]) is insp


def _read_csv(path):
    import csv

    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_a_two_part_model_scores_with_the_rays_when_every_scan_has_a_sensor_origin(tmp_path, one_torch_thread):
    """The default path of scanners that record where they stood: calibrate turns the rays on (every scan has a
    sensor origin), each part gets its own combination, and score writes the ray columns and summary for the parts
    together (it used to fail on the two-part inspector)."""
    import csv

    from autodecoder.latent.train import train_collection
    from datasets.collection import ScanCollection
    from inspection.job import calibrate
    from inspection.run import score

    scans = []
    for i, (part, r) in enumerate((("a", 0.15), ("b", 0.3))):
        scans += [_sphere(f"{part}/train/{k:03d}", r, part, 100 * i + k) for k in range(6)]
        scans += [_sphere(f"{part}/test/good", r, part, 100 * i + 50, split="test")]
    for k, s in enumerate(scans):  # a sensor 1.5 units away, on a different side for each scan
        v = np.random.default_rng(k).normal(size=3)
        s.sensor_origin = (1.5 * v / np.linalg.norm(v)).astype(np.float32)
    data = ScanCollection.create(tmp_path / "ab.h5", scans)
    model = tmp_path / "model.pt"
    train_collection(data, model, calibration_fraction=0.34, quiet=True, **TINY)
    insp, _ = calibrate(model, data, progress=False)
    assert sorted(insp.parts_) == ["a", "b"] and insp.settings_.rays
    rules = {p: one.combination_.rule for p, one in insp.parts_.items()}
    assert set(rules) == {"a", "b"}
    summary = score(model, data, tmp_path / "results", progress=False, maps="none", echo=lambda line: None)
    assert summary["rays"]["options"]["n_rays"] > 0 and rules["a"] in summary["rays"]["score"]
    assert set(summary["parts"]) == {"a", "b"}
    with open(tmp_path / "results" / "scores.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(float(r["score_rays"]) >= 0 for r in rows)
