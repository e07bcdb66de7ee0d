"""The first hour with a folder of scans, as a user has it (issue 53): a flat folder of good scans without normals,
with a README, a scanner's .conf and a hidden file beside them, imported as training data and trained on (a
tiny model, a few epochs); the training says early that so few good scans make a loose threshold; the Python API's
three-way verdict is the command line's on the same scanner files; the README's example for one scanner file runs
as written; `watch` keeps the page `score` writes."""
import contextlib
import csv
import io
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from datasets import ScanCollection, write_cloud

README = Path(__file__).resolve().parents[2] / "README.md"
# a tiny model trained quickly (as tests/inspection/test_one_pipeline.py's): the command line's own options
TINY = ["--epochs", "20", "--latent-dim", "4", "--width", "32", "--depth", "2", "--batch", "4", "--samples", "256",
        "--lr", "3e-3", "--code-lr", "3e-3", "--calibration-fraction", "0.4", "--seed", "0"]


def _view(seed, dent=0.0, n=250):
    """A noisy half-sphere (radius 30 mm) seen from +z, in millimetres and off the origin, without normals; dented
    at its pole by ``dent`` mm."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 30.0 - dent * np.exp(-np.sum((d - [0, 0, 1]) ** 2, axis=1) / 0.05)
    return d * r[:, None] + rng.normal(0.0, 0.06, (n, 3)) + np.array([120.0, -40.0, 15.0])


def _folder(root, views):
    """A scanner's folder: ``views`` {stem: points} as PLY files without normals, and what else such folders hold."""
    root.mkdir(parents=True)
    for stem, points in views.items():
        write_cloud(root / f"{stem}.ply", points)
    (root / "README").write_text("Range data. The .conf file aligns the views.\n")
    (root / "scanner.conf").write_text("camera 0 0 0 0 0 0 1\n")
    (root / ".hidden").write_text("a desktop's metadata\n")
    return root


def _run(main, argv):
    """A command line's (exit status, stdout, stderr), in-process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main([str(a) for a in argv])
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def first_hour(tmp_path_factory, one_torch_thread):
    """8 good views imported from a flat folder as training data, a tiny model trained on them (3 held back) and
    calibrated by the command line; a folder of 3 new good and 2 dented views to score."""
    from datasets.__main__ import main as data_main
    from inspection.__main__ import main as inspect_main
    from train_latent import main as train_main

    tmp = tmp_path_factory.mktemp("first_hour")
    good = _folder(tmp / "good_scans", {f"good{i}": _view(i) for i in range(8)})
    new = _folder(tmp / "new_scans", {**{f"new{i}": _view(20 + i) for i in range(3)},
                                       **{f"dented{i}": _view(30 + i, dent=4.0) for i in range(2)}})
    imported = _run(data_main, ["import", good, "--split", "train", "--label", "good", "--out", tmp / "good.h5"])
    trained = _run(train_main, ["--data", tmp / "good.h5", "--out", tmp / "model.pt", *TINY])
    calibrated = _run(inspect_main, ["calibrate", "--model", tmp / "model.pt", "--data", tmp / "good.h5", "--quiet"])
    return {"tmp": tmp, "good": good, "new": new, "imported": imported, "trained": trained, "calibrated": calibrated}


def test_a_flat_folder_is_imported_as_training_data_and_trained_on(first_hour):
    import autodecoder

    status, out, _ = first_hour["imported"]
    assert status == 0
    assert "skipped 3 files that are not point clouds: .hidden, README, scanner.conf" in out.splitlines()
    with ScanCollection(first_hour["tmp"] / "good.h5") as c:
        assert sorted(c.names) == [f"good{i}" for i in range(8)]
        assert {(m["split"], m["label"]) for m in c.metadata()} == {("train", "good")}
    status, out, err = first_hour["trained"]
    assert status == 0, err
    model = autodecoder.load_model(first_hour["tmp"] / "model.pt")
    assert sorted(model.train_names + model.calibration_names) == [f"good{i}" for i in range(8)]
    assert len(model.calibration_names) == 3  # round(0.4 x 8) held back to calibrate
    # the time reported is the whole run's, the epochs' share beside it
    wrote = next(line for line in out.splitlines() if line.startswith("wrote "))
    total, epochs = map(float, re.search(r"; ([\d.]+) s in all \(the training epochs ([\d.]+) s\)", wrote).groups())
    assert 0 < epochs <= total
    assert first_hour["calibrated"][0] == 0, first_hour["calibrated"][2]


def test_a_few_scan_training_says_so_before_the_work(first_hour):
    from inspection.threshold import DEFAULT_ALPHA, format_rate, lognormal_far_interval

    out = first_hour["trained"][1].splitlines()
    note = next(i for i, line in enumerate(out) if line.startswith("note: few good scans for the threshold"))
    assert note < next(i for i, line in enumerate(out) if line.startswith("wrote "))
    line = out[note]
    assert "of the 8 good scans 5 train the model and 3 are held back" in line
    # few scans: by default a fold model per training scan scores it out of sample, so all 8 set the level
    assert "and 5 fold models score the 5 training scans as new" in line
    lo, hi = lognormal_far_interval(8, DEFAULT_ALPHA, df=7)
    assert f"between {format_rate(lo)} and {format_rate(hi)}" in line
    assert "41 more good scans scored by fold models would make it exact" in line
    # and the progress of the steps before the epochs (the pose decision, reading the scans, their targets)
    err = first_hour["trained"][2]
    assert "pose: placed by hand?" in err and "GP targets" in err and "training" in err


def test_training_on_scans_imported_without_a_split_says_how_to_get_them_there(first_hour, tmp_path):
    from datasets.__main__ import main as data_main
    from train_latent import main as train_main

    status, out, _ = _run(data_main, ["import", first_hour["good"], "--out", tmp_path / "test.h5"])
    assert status == 0 and "`--split train --label good`" in out  # said at the import already
    status, out, err = _run(train_main, ["--data", tmp_path / "test.h5", "--out", tmp_path / "m.pt", "--quiet"])
    assert status == 2 and out == "" and len(err.splitlines()) == 1
    assert "no good scans in split 'train' (it holds 8 scans: 8 in split 'test' labelled 'unknown')" in err
    assert "nsspr-data import FOLDER --split train --label good" in err


def _cli_rows(results):
    with open(results / "scores.csv", newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def scored(first_hour):
    """`nsspr-inspect score` of the folder of new scanner files (a README, a .conf and a hidden file beside them)."""
    from inspection.__main__ import main as inspect_main

    results = first_hour["tmp"] / "results"
    status, out, err = _run(inspect_main, ["score", "--model", first_hour["tmp"] / "model.pt", "--data",
                                           first_hour["new"], "--out", results, "--quiet"])
    assert status == 0, err
    return results, out


def test_score_on_a_folder_skips_what_is_not_a_cloud_and_counts_by_verdict(scored):
    results, out = scored
    assert "skipped 3 files that are not point clouds: .hidden, README, scanner.conf" in out
    rows = _cli_rows(results)
    assert sorted(rows) == ["dented0", "dented1", "new0", "new1", "new2"]
    counts = {v: sum(r["verdict"] == v for r in rows.values()) for v in ("defective", "uncertain", "good")}
    assert f"5 scans: {counts['defective']} defective (flagged), {counts['uncertain']} uncertain (rescan), " \
           f"{counts['good']} good" in out
    assert "precision" not in out and "recall" not in out  # no labels: nothing to measure them against


@pytest.fixture(scope="module")
def watched(first_hour, tmp_path_factory):
    """`watch --once --report-every 2` on a copy of the new scans' folder with a broken file added; returns the
    results folder, the lines it said, and the number of rows of each page it wrote."""
    import inspection.html_report
    from inspection.watch import watch

    tmp = tmp_path_factory.mktemp("watched")
    drop = tmp / "drop"
    shutil.copytree(first_hour["new"], drop)
    (drop / "broken.ply").write_bytes(b"not a ply file")  # an error verdict is a row of the page too
    written = []  # rows per rewrite of the page
    real = inspection.html_report.write_html_report

    def counting(path, rows, *args, **kwargs):
        written.append(len(rows))
        return real(path, rows, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(inspection.html_report, "write_html_report", counting)
        said = []
        watch(first_hour["tmp"] / "model.pt", drop, tmp / "out", once=True, settle=0, echo=said.append,
              report_every=2)
        # started again with nothing new, a watcher leaves the page as it is
        watch(first_hour["tmp"] / "model.pt", drop, tmp / "out", once=True, settle=0, echo=None)
    return drop, tmp / "out", said, written


def _journal(out):
    from inspection.watch import JOURNAL, read_journal

    return {Path(e["file"]).stem: e for e in read_journal(out / JOURNAL)}


def test_the_api_verdict_is_the_command_lines(first_hour, scored, watched):
    import autodecoder
    from inspection import Inspector, read_calibration
    from inspection.loading import load_scans

    rows = _cli_rows(scored[0])
    model = autodecoder.load_model(first_hour["tmp"] / "model.pt")
    insp = Inspector.from_calibration(model, read_calibration(first_hour["tmp"] / "model.pt"))
    scans, _ = load_scans(first_hour["new"], model.frame)
    verdicts, reasons = insp.predict_verdict(scans, return_reasons=True)
    assert {s.name: str(v) for s, v in zip(scans, verdicts)} == {n: r["verdict"] for n, r in rows.items()}
    # the verdict in words, as `watch` journals it and report.html shows it
    journal = _journal(watched[1])
    assert {s.name: r for s, r in zip(scans, reasons)} == {s.name: journal[s.name]["why"] for s in scans}
    # the dented scans score above the new good ones, and the verdicts are not all one
    scores = {n: float(r["score"]) for n, r in rows.items()}
    assert min(scores["dented0"], scores["dented1"]) > max(scores[f"new{i}"] for i in range(3))
    assert len(set(verdicts)) >= 2
    # predict is the two-class view: -1 exactly where the score lies above the threshold (the 'flagged' column)
    flagged = insp.predict(scans) == -1
    assert [rows[s.name]["flagged"] == "true" for s in scans] == flagged.tolist()
    two = insp.predict_verdict(scans, uncertain=False)
    assert two.tolist() == ["defective" if f else "good" for f in flagged]


def _readme_file_example():
    """The README's example for one scanner file (the code block that calls ``load_scans``)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    found = [b for b in blocks if "load_scans(" in b]
    assert len(found) == 1, "the README should hold exactly one example that reads a scanner file"
    return found[0]


def test_the_readmes_scanner_file_example_runs_and_says_what_score_says(first_hour, scored, watched, tmp_path,
                                                                         monkeypatch, capsys):
    shutil.copy(first_hour["tmp"] / "model.pt", tmp_path / "model.pt")
    shutil.copy(first_hour["new"] / "dented0.ply", tmp_path / "scan.ply")  # a scanner file without normals
    monkeypatch.chdir(tmp_path)
    exec(compile(_readme_file_example(), str(README), "exec"), {})
    printed = capsys.readouterr().out.strip()
    verdict, why = _cli_rows(scored[0])["dented0"]["verdict"], _journal(watched[1])["dented0"]["why"]
    assert printed == f"{verdict} - {why}"


class _Page(HTMLParser):
    """The visible text of a page (scripts and styles left out)."""

    def __init__(self):
        super().__init__()
        self.text, self._skip = [], False

    def handle_starttag(self, tag, attrs):
        self._skip = tag in ("script", "style")

    def handle_endtag(self, tag):
        self._skip = False

    def handle_data(self, data):
        if not self._skip:
            self.text.append(data)


def test_watch_keeps_the_report_page_refreshed_and_naming_every_scored_file(watched):
    from inspection.watch import REPORT

    _, out, said, written = watched
    assert said[0] == "skipped 3 files that are not point clouds: .hidden, README, scanner.conf"
    entries = _journal(out).values()
    assert len(entries) == 6 and written == [2, 4, 6]  # every 2 scans, and the last ones when it stopped; not again
    page = _Page()
    page.feed((out / REPORT).read_text(encoding="utf-8"))
    page.close()
    visible = " ".join(page.text)
    assert all(e["file"] in visible for e in entries) and "error" in visible
    assert all(e["why"] in visible for e in entries if e["verdict"] != "error")  # each verdict in words
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]  # written atomically: no leftovers
