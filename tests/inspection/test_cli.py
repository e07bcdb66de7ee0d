"""inspection command line: calibrate / score outputs (CSV, JSON, PNG, PLY), the stored calibration, bad inputs."""
import csv
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # effective only if torch is not loaded yet; see inspection.__main__

from datasets import Frame, Scan, ScanCollection, read_cloud
from inspection.__main__ import main
from inspection.calibration import read_calibration
from inspection.report import CSV_COLUMNS

from .tiny import FRAME, half_sphere as _scan, tiny_field_model

@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A tiny collection (6 train, 3 good + 2 dented test scans) and an (untrained, tiny) field model file."""
    scans = [_scan(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    scans += [_scan(f"test/good/{i:03d}", "test", "good", seed=10 + i) for i in range(3)]
    scans += [_scan(f"test/dent/{i:03d}", "test", "defective", "dent", seed=20 + i, dent=0.1) for i in range(2)]
    return tiny_field_model(tmp_path_factory.mktemp("insp"), scans)


def test_help_is_fast():
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "inspection", "score", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--align" in r.stdout
    assert time.perf_counter() - t0 < 5


def test_calibrate_then_score(workdir, tmp_path, capsys):
    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    rc = main(["calibrate", "--model", str(model), "--data", str(workdir / "tree.h5"), "--alpha", "0.3", "--quiet"])
    assert rc == 0
    cal = read_calibration(model)
    held = sorted(n for n, r in zip(cal.names, cal.roles) if r == "held-back")
    crossed = sorted(n for n, r in zip(cal.names, cal.roles) if r == "cross-fitted")
    assert held == [f"train/good/{i:03d}" for i in range(3, 6)]  # the held-back scans
    assert crossed == [f"train/good/{i:03d}" for i in range(3)]  # and the training scans, cross-fitted
    assert len(cal.scores) == 6 and cal.aggregate == "top1" and cal.alpha == 0.3
    from autodecoder.field.stochastic_field import StochasticField

    StochasticField.load(model)  # the model file still loads as before

    out = tmp_path / "results"
    rc = main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(out),
               "--maps", "all", "--quiet"])
    assert rc == 0
    with open(out / "scores.csv", newline="") as f:
        rows = list(csv.DictReader(f))
        assert tuple(csv.reader(open(out / "scores.csv")).__next__()) == CSV_COLUMNS
    assert len(rows) == 5 and {r["split"] for r in rows} == {"test"}
    assert {r["label"] for r in rows} == {"good", "defective"}
    summary = json.loads((out / "summary.json").read_text())
    lo, hi = summary["decision"]["far_interval"]  # the threshold's own uncertainty, as a false-alarm rate
    for r in rows:
        p = float(r["p_value"])
        # n = 6 calibration scans; 'uncertain' exactly where the p-value lies within the threshold's interval
        expected = "uncertain" if lo <= p <= hi else ("defective" if p <= 0.3 else "good")
        assert 1 / 7 - 1e-6 <= p <= 1 and r["verdict"] == expected
    assert summary["n_uncertain"] == sum(r["verdict"] == "uncertain" for r in rows) > 0
    # what each labelled scan was told, counted by its label
    assert summary["metrics"]["verdicts"] == {
        lab: {v: sum(r["label"] == lab and r["verdict"] == v for r in rows) for v in ("good", "uncertain", "defective")}
        for lab in ("good", "defective")}
    two = tmp_path / "two"
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(two), "--maps",
                 "none", "--two-class", "--quiet"]) == 0
    with open(two / "scores.csv", newline="") as f:
        binary = {r["name"]: r["verdict"] for r in csv.DictReader(f)}
    assert binary == {r["name"]: "defective" if float(r["p_value"]) <= 0.3 else "good" for r in rows}
    assert summary["n_scans"] == 5 and summary["counts"]["defective"] == 2
    m = summary["metrics"]
    for key in ("auroc", "aupr", "precision", "recall", "f1", "confusion_matrix", "point_auroc"):
        assert key in m
    assert set(m["auroc_per_defect"]) == {"dent"}
    for png in ("roc.png", "scores.png", "maps/legend.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ply = out / "maps" / "test__dent__000.ply"
    pts, normals = read_cloud(ply)
    assert pts.shape == (300, 3) and normals is not None
    # what the map and the point AUROC show is the Inspector's anomaly map (each point's patch residual)
    import open3d as o3d
    from sklearn.metrics import roc_auc_score

    from inspection import Inspector, load_model_handle
    from inspection.maps import colours

    handle = load_model_handle(model)
    insp = Inspector.from_calibration(handle.model, handle.calibration)
    with ScanCollection(workdir / "tree.h5") as c:
        tests = c.read_many(c.select(split="test"))
    amaps = {s.name: insp.anomaly_map(s) for s in tests}
    written = np.asarray(o3d.io.read_point_cloud(str(ply)).colors)
    np.testing.assert_array_equal(np.round(written * 255).astype(np.uint8), colours(amaps["test/dent/000"]))
    labelled = [s for s in tests if s.point_labels is not None]
    assert m["point_auroc"] == pytest.approx(roc_auc_score(np.concatenate([s.point_labels for s in labelled]),
                                                           np.concatenate([amaps[s.name] for s in labelled])))
    assert "flagged" in capsys.readouterr().out
    # scoring again into the same results folder replaces its files
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(out),
                 "--maps", "none", "--quiet"]) == 0
    assert not list((out / "maps").glob("*.ply"))


def _error(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("error: ") and len(err.splitlines()) == 1, err
    return err


def test_score_calibrates_an_uncalibrated_model_on_its_held_back_scans(workdir, tmp_path, capsys):
    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    out = tmp_path / "r"
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(out),
                 "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "is not calibrated: calibrating on its 3 held-back good scans" in said
    cal = read_calibration(model)  # stored, as `calibrate` would have
    assert sorted(cal.names) == [f"train/good/{i:03d}" for i in range(6)] and cal.alpha == 0.02
    summary = json.loads((out / "summary.json").read_text())
    decision = summary["decision"]
    assert decision["n"] == 6 and decision["basis"] == "log-normal" and decision["alpha"] == 0.02
    assert summary["threshold"] == pytest.approx(decision["value"]) and "49" in decision["note"]
    # the threshold in plain words first (its rate, its interval, what set it), the statistics after
    plain = said.index(f"threshold {summary['threshold']:.4g}: a good scan is flagged 2 % of the time on average")
    assert "it rests on 3 held-back scans, fewer than the 49" in said[plain:].splitlines()[0]
    assert said[plain:].splitlines()[1].startswith("statistics: basis log-normal on 6 calibration scores")
    variances = cal.extra["reference"]["term_variances"]  # the joint score's terms, weighed by the good scans
    assert summary["point_score"] == "joint" and summary["term_variances"] == pytest.approx(variances)
    assert f"the field's {variances[0] ** 0.5:.2f}, the good points' {variances[1] ** 0.5:.2f}" in said


def test_uncalibrated_model_on_other_data_is_an_error(workdir, tmp_path, capsys):
    other = tmp_path / "other.h5"
    ScanCollection.create(other, [_scan("test/good/000", "test", "good")], frame=FRAME)
    err = _error(["score", "--model", str(workdir / "model.pt"), "--data", str(other), "--out", str(tmp_path / "r")],
                 capsys)
    assert "not calibrated" in err and "model.pt" in err and "calibrate" in err


def test_the_per_scan_job_is_what_score_runs(workdir, tmp_path):
    """inspection.job, shared by score, watch and the benchmarks: an uncalibrated model's calibrated_inspector
    without its training collection is one error naming the command; given it, the model calibrates itself (stored
    in the file), and inspect_scan gives each scan the row score wrote; error_row is the row of a scan not scored."""
    from inspection import calibrated_inspector, error_row, inspect_scan, load_model_handle
    from inspection.errors import InspectionError
    from inspection.run import score

    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    with pytest.raises(InspectionError, match=r"not calibrated, and no data was given; run `python -m inspection "
                                              r"calibrate --model .*model.pt --data GOOD_SCANS` first"):
        calibrated_inspector(load_model_handle(model))
    said = []
    insp = calibrated_inspector(load_model_handle(model), workdir / "tree.h5", echo=said.append)
    assert "is not calibrated: calibrating on its 3 held-back good scans" in said[0]
    assert read_calibration(model).names == list(insp.calibration_names_)  # stored, as `calibrate` stores it
    score(model, workdir / "tree.h5", tmp_path / "r", maps="none", progress=False, echo=lambda line: None)
    with open(tmp_path / "r" / "scores.csv", newline="") as f:
        written = list(csv.DictReader(f))
    again = calibrated_inspector(load_model_handle(model))  # calibrated now: from the stored calibration
    with ScanCollection(workdir / "tree.h5") as c:
        tests = c.read_many(c.select(split="test"))
    for i, scan in enumerate(tests):
        row = inspect_scan(again, scan, i)["row"]
        assert written[i]["name"] == row["name"] and written[i]["verdict"] == row["verdict"]
        assert float(written[i]["score"]) == pytest.approx(row["score"], rel=1e-8)  # as the CSV rounds it
    assert error_row("x.ply", "x.ply: empty") == {"name": "x.ply", "split": "", "label": "unknown", "defect": "",
                                                  "score": None, "p_value": None, "verdict": "error",
                                                  "reason": "x.ply: empty"}
    with pytest.raises(ValueError, match="maps_dir"):
        inspect_scan(again, tests[0], 0, maps="all")


def test_bad_inputs(workdir, tmp_path, capsys):
    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    assert main(["calibrate", "--model", str(model), "--data", str(workdir / "tree.h5"), "--quiet"]) == 0
    capsys.readouterr()
    # a collection in another frame
    other = tmp_path / "other.h5"
    ScanCollection.create(other, [_scan("test/good/000", "test", "good")], frame=Frame(np.zeros(3), 1.0))
    err = _error(["score", "--model", str(model), "--data", str(other), "--out", str(tmp_path / "r1")], capsys)
    assert "other.h5" in err and "frame" in err
    # missing model, missing data, unknown file type
    assert "nope.pt" in _error(["score", "--model", str(tmp_path / "nope.pt"), "--data", str(other), "--out",
                                str(tmp_path / "r2")], capsys)
    assert "nope.h5" in _error(["score", "--model", str(model), "--data", str(tmp_path / "nope.h5"), "--out",
                                str(tmp_path / "r3")], capsys)
    weird = tmp_path / "scan.foo"
    weird.write_text("1 2 3\n")
    assert "scan.foo" in _error(["score", "--model", str(model), "--data", str(weird), "--out",
                                 str(tmp_path / "r4")], capsys)
    # an empty scan file, in a folder of scanner files
    folder = tmp_path / "scans"
    folder.mkdir()
    (folder / "part.xyz").write_text("")
    assert "part.xyz" in _error(["score", "--model", str(model), "--data", str(folder), "--out",
                                 str(tmp_path / "r5")], capsys)
    # a model file that is not a model
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    assert "junk.pt" in _error(["calibrate", "--model", str(junk), "--data", str(workdir / "tree.h5")], capsys)
    # refusing to write into a folder that is not a results folder
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    assert "busy" in _error(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out",
                             str(busy)], capsys)


def test_scanner_file_in_model_frame(workdir, tmp_path, capsys):
    """One cloud file in file units is moved into the model's frame and scored (label unknown)."""
    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    assert main(["calibrate", "--model", str(model), "--data", str(workdir / "tree.h5"), "--quiet"]) == 0
    s = _scan("x", "test", "good", seed=5)
    cloud = tmp_path / "part.npy"
    np.save(cloud, np.c_[FRAME.to_file(s.points), s.normals])
    out = tmp_path / "r"
    assert main(["score", "--model", str(model), "--data", str(cloud), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "scores.csv")))
    assert [(r["name"], r["label"]) for r in rows] == [("part", "unknown")]


def test_latent_model_end_to_end(tmp_path, capsys):
    """A tiny latent model trained on half-spheres: calibrated on its held-back scans, it scores a dented one worse
    than good ones, and the score command writes its outputs."""
    from inspection.training import train_model

    scans = [_scan(f"train/good/{i:03d}", "train", "good", seed=i, n=200) for i in range(6)]
    scans += [_scan(f"test/good/{i:03d}", "test", "good", seed=10 + i, n=200) for i in range(2)]
    scans += [_scan(f"test/dent/{i:03d}", "test", "defective", "dent", seed=20 + i, dent=0.25, n=200)
              for i in range(2)]
    data, model = tmp_path / "tiny.h5", tmp_path / "tiny.pt"
    ScanCollection.create(data, scans, frame=FRAME)
    train_model(data, model, calibration_fraction=0.5, epochs=20, width=32, depth=2, features=16, latent_dim=4,
                mean_samples=256, screen_samples=128, pair_clusters=8, batch=3, lr=3e-3, code_lr=3e-3)
    assert main(["calibrate", "--model", str(model), "--data", str(data), "--alpha", "0.3", "--quiet",
                 "--projection", "steps=15,starts=1,max_candidates=4"]) == 0
    cal = read_calibration(model)
    # 3 training scans: by default each is scored by the fold model that never saw it (leave-one-out)
    assert cal.roles.count("held-back") == 3 and cal.roles.count("fold") == 3
    assert all(n.startswith("train/") for n in cal.names)
    assert cal.config().projection == {"steps": 15, "starts": 1, "max_candidates": 4}
    out = tmp_path / "res"
    assert main(["score", "--model", str(model), "--data", str(data), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "scores.csv")))
    score = {r["name"]: float(r["score"]) for r in rows}
    assert min(score["test/dent/000"], score["test/dent/001"]) > max(score["test/good/000"], score["test/good/001"])
    assert json.loads((out / "summary.json").read_text())["model_kind"] == "latent"


def test_rays_auto_stays_off_when_some_scans_of_the_collection_have_no_sensor_origin(tmp_path):
    # a public layout's collection: rendered template views carry origins, its test scans none; rays calibrated on
    # the views could not score the test scans, so rays='auto' must not turn them on
    from inspection.calibrating import _good_scans

    rng = np.random.default_rng(0)

    def scan(name, split, origin):
        p = rng.normal(size=(50, 3)).astype(np.float32)
        n = p / np.linalg.norm(p, axis=1, keepdims=True)
        return Scan(name=name, points=p, normals=n, split=split, label="good", sensor_origin=origin)

    views = [scan(f"train/t/view_{i}", "train", np.array([0, 0, 5.0])) for i in range(2)]
    ScanCollection.create(tmp_path / "all.h5", views + [scan("test/a", "test", np.array([5.0, 0, 0]))])
    ScanCollection.create(tmp_path / "public.h5", views + [scan("test/a", "test", None)])
    with ScanCollection(tmp_path / "all.h5") as c:
        assert _good_scans(c, object())[2]
    with ScanCollection(tmp_path / "public.h5") as c:
        scans, training, origins = _good_scans(c, object())
        assert not origins and not training and len(scans) == 3  # no fingerprint to match: not the training data
    assert _good_scans(views, object())[2]  # scans given: decided by the scans themselves


def test_option_mistakes_are_one_line_before_any_work(workdir, tmp_path, capsys):
    """Bad option values fail with one line and exit 2 before a model or scan is read (the model file is untouched)."""
    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    before = model.read_bytes()
    data = str(workdir / "tree.h5")
    for argv, expected in (
            (["--projection", "foo=1"], "unknown option(s) ['foo']"),
            (["--projection", "steps=-3"], "steps must be >= 0"),
            (["--projection", "steps"], "--projection: expected KEY=VALUE"),
            (["--alpha", "1.5"], "alpha must be in"),
            (["--aggregate", "worst"], "aggregate must be"),
            (["--noise", "-1"], "noise must be"),
            (["--ray-options", "bogus=1"], "unknown ray option"),
            (["--ray-options", "band=0"], "band must be > 0"),
            (["--ray-options", "n_rays=5", "--no-rays"], "--ray-options needs --rays")):
        err = _error(["calibrate", "--model", str(model), "--data", data, "--quiet", *argv], capsys)
        assert expected in err, (argv, err)
    assert model.read_bytes() == before
    # an unwritable results folder: one line naming it
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert main(["calibrate", "--model", str(model), "--data", data, "--quiet"]) == 0
    capsys.readouterr()
    err = _error(["score", "--model", str(model), "--data", data, "--out", str(blocker / "results"), "--quiet"],
                 capsys)
    assert "a_file" in err


def test_a_damaged_scan_gets_verdict_error_and_the_others_are_scored(workdir, tmp_path, capsys):
    """A point moved in one test scan without updating its stored content hash: that scan is reported (verdict
    'error', the reason naming it and the hash), every other scan is scored, and the exit status is 1."""
    import h5py

    model, data = tmp_path / "model.pt", tmp_path / "tree.h5"
    model.write_bytes((workdir / "model.pt").read_bytes())
    data.write_bytes((workdir / "tree.h5").read_bytes())
    with ScanCollection(data) as c:
        victim = c.index_of("test/good/001")
        offset = int(c._offsets[victim])
    assert main(["calibrate", "--model", str(model), "--data", str(data), "--quiet"]) == 0
    with h5py.File(data, "r+") as f:
        f["points"][offset, 0] += 0.01
    capsys.readouterr()
    out = tmp_path / "res"
    assert main(["score", "--model", str(model), "--data", str(data), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "1 scan(s) could not be scored" in err
    with open(out / "scores.csv", newline="") as f:
        rows = {r["name"]: r for r in csv.DictReader(f)}
    assert len(rows) == 5 and rows["test/good/001"]["verdict"] == "error"
    assert "test/good/001" in rows["test/good/001"]["reason"] and "content_sha256" in rows["test/good/001"]["reason"]
    assert all(r["verdict"] in ("good", "defective", "uncertain") and r["reason"] == "" for n, r in rows.items()
               if n != "test/good/001")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_errors"] == 1 and summary["n_scans"] == 5


def test_calibrating_on_a_damaged_good_scan_names_the_file_once_and_the_scan(workdir, tmp_path, capsys):
    import h5py

    model, data = tmp_path / "model.pt", tmp_path / "tree.h5"
    model.write_bytes((workdir / "model.pt").read_bytes())
    data.write_bytes((workdir / "tree.h5").read_bytes())
    with ScanCollection(data) as c:
        offset = int(c._offsets[c.index_of("train/good/004")])
    with h5py.File(data, "r+") as f:
        f["points"][offset, 1] += 0.01
    err = _error(["calibrate", "--model", str(model), "--data", str(data), "--quiet"], capsys)
    assert err.count(str(data)) == 1 and "train/good/004" in err and "content_sha256" in err


def test_score_writes_the_defect_regions_and_judges_a_tolerance(workdir, tmp_path):
    """defects.csv (one row per region), the regions' count and the tolerance's judgement in scores.csv, a region id
    per point in the maps, the region level in summary.json."""
    from plyfile import PlyData

    from inspection.maps import safe_name
    from inspection.report import DEFECT_COLUMNS

    model = tmp_path / "model.pt"
    model.write_bytes((workdir / "model.pt").read_bytes())
    assert main(["calibrate", "--model", str(model), "--data", str(workdir / "tree.h5"), "--alpha", "0.3",
                 "--quiet"]) == 0
    out = tmp_path / "results"
    features = tmp_path / "features.csv"
    features.write_text("name,x,y,z\nnear,0,0,0\nfar,1000,1000,1000\n")
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(out), "--maps",
                 "all", "--tolerance", "0.001mm", "--features", str(features), "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "scores.csv")))
    defects = list(csv.DictReader(open(out / "defects.csv")))
    assert defects and {d["feature"] for d in defects} == {"near"}
    assert tuple(csv.reader(open(out / "defects.csv")).__next__()) == DEFECT_COLUMNS
    summary = json.loads((out / "summary.json").read_text())
    assert summary["regions"]["level"] > 0 and summary["regions"]["n_regions"] == len(defects)
    for r in rows:
        mine = [d for d in defects if d["name"] == r["name"]]
        assert int(r["regions"]) == len(mine)
        ids = PlyData.read(str(out / "maps" / f"{safe_name(r['name'])}.ply"))["vertex"]["region"]
        assert sorted(set(ids.tolist()) - {-1}) == sorted(int(d["region"]) for d in mine)
        out_of_tolerance = any(abs(float(d["deviation"])) > 0.001 for d in mine)
        assert r["tolerance"] == ("out" if out_of_tolerance else "within")
        if out_of_tolerance:
            assert r["verdict"] == "defective" and r["decided_by"] in ("tolerance", "both")
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(tmp_path / "x"),
                 "--tolerance", "wide"]) != 0  # a tolerance that is not one: one line, before any work
    features.write_text("name,x,y\nnear,0,0\n")
    assert main(["score", "--model", str(model), "--data", str(workdir / "tree.h5"), "--out", str(tmp_path / "y"),
                 "--features", str(features)]) != 0
