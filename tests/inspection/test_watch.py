"""`nsspr-inspect watch`: each landed file scored exactly once (also under kill -9 and restart), no torn journal
lines, half-written files not read, bad files an error line and the watcher goes on, one-line option errors."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # effective only if torch is not loaded yet; see inspection.__main__

from datasets import write_cloud
from inspection.__main__ import main
from inspection.errors import InspectionError
from inspection.watch import JOURNAL, TABLE, Watcher, read_journal, watch

from .tiny import FRAME, half_sphere, tiny_field_model

ROOT = Path(__file__).resolve().parents[2]


def _scan(name, seed, dent=0.0):
    return half_sphere(name, seed=seed, dent=dent)


def _drop(folder, name, seed, dent=0.0):
    """A scanner file in file units (the model's frame undone), written atomically."""
    s = _scan(name, seed, dent)
    return write_cloud(Path(folder) / f"{name}.ply", FRAME.to_file(s.points), s.normals)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """An untrained tiny field model saved with its collection's frame and calibrated on 6 good scans."""
    scans = [_scan(f"train/good/{i:03d}", seed=i) for i in range(6)]
    root = tiny_field_model(tmp_path_factory.mktemp("watch"), scans)
    assert main(["calibrate", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--alpha", "0.3",
                 "--quiet"]) == 0
    return root / "model.pt"


def _lines(out):
    """The journal's lines, each parsed (a torn or unparsable line fails the test)."""
    data = (Path(out) / JOURNAL).read_bytes()
    assert data == b"" or data.endswith(b"\n"), "torn last line"
    return [json.loads(line) for line in data.splitlines()]


def test_once_scores_each_file_and_a_bad_file_is_one_error_line(model, tmp_path):
    drop, out = tmp_path / "drop", tmp_path / "out"
    for i in range(3):
        _drop(drop, f"s{i}", seed=100 + i, dent=0.1 * (i == 0))
    np.save(drop / "nan.npy", np.full((50, 3), np.nan))  # no finite point
    (drop / "garbage.ply").write_bytes(b"ply\nformat nonsense\n")
    (drop / "empty.xyz").write_bytes(b"")
    (drop / "notes.md").write_text("not a cloud: ignored")
    (drop / ".s9.ply.tmp").write_text("a scanner's temporary file: ignored")
    said = []
    w = watch(model, drop, out, once=True, settle=0, echo=said.append)
    lines = _lines(out)
    assert sorted(e["file"] for e in lines) == ["empty.xyz", "garbage.ply", "nan.npy", "s0.ply", "s1.ply", "s2.ply"]
    by = {e["file"]: e for e in lines}
    for bad in ("empty.xyz", "garbage.ply", "nan.npy"):
        assert by[bad]["verdict"] == "error" and bad in by[bad]["reason"] and by[bad]["score"] is None
    for good in ("s0.ply", "s1.ply", "s2.ply"):
        assert by[good]["verdict"] in ("good", "defective", "uncertain") and np.isfinite(by[good]["score"])
        assert (out / by[good]["map"]).is_file()  # --maps all (the default)
    assert by["s0.ply"]["score"] > by["s1.ply"]["score"]  # the dented one
    assert w.counts["error"] == 3 and said[-1].startswith("watch: 6 file(s) scored")
    table = (out / TABLE).read_text().splitlines()
    assert len(table) == 7 and table[0].startswith("name,split,label")
    # the defect regions of each file not told good, named by the file, as its row counts them
    import csv

    regions = list(csv.DictReader(open(out / "defects.csv")))
    for e in lines:
        assert sum(d["name"] == e["file"] for d in regions) == (e.get("regions") or 0)
    # a second run finds everything recorded; a file that changes (a rescan under the same name) is scored again
    assert sum(watch(model, drop, out, once=True, settle=0, echo=None).counts.values()) == 0
    _drop(drop, "s1", seed=7)
    assert watch(model, drop, out, once=True, settle=0, echo=None).counts and len(_lines(out)) == 7


def test_half_written_file_is_not_read(model, tmp_path):
    drop, out = tmp_path / "drop", tmp_path / "out"
    whole = _drop(tmp_path / "elsewhere", "part", seed=3).read_bytes()
    drop.mkdir()
    (drop / "part.ply").write_bytes(whole[: len(whole) // 2])  # the scanner is still writing it
    with Watcher(model, drop, out, settle=30, echo=None) as w:
        assert w.poll() == (0, 1)  # seen, still settling: not read
        assert _lines(out) == []
        with open(drop / "part.ply", "ab") as fh:  # the scanner finishes; the file then sits unchanged
            fh.write(whole[len(whole) // 2:])
        past = time.time() - 60
        os.utime(drop / "part.ply", (past, past))
        assert w.poll() == (1, 0)
    (line,) = _lines(out)
    assert line["file"] == "part.ply" and line["verdict"] != "error" and line["size"] == len(whole)


def test_torn_last_line_is_cut_and_that_file_scored_again(model, tmp_path):
    drop, out = tmp_path / "drop", tmp_path / "out"
    for i in range(2):
        _drop(drop, f"s{i}", seed=i)
    watch(model, drop, out, once=True, settle=0, echo=None)
    data = (out / JOURNAL).read_bytes()
    first = data.index(b"\n") + 1
    (out / JOURNAL).write_bytes(data[: first + 20])  # a crash part-way through the second line
    assert len(read_journal(out / JOURNAL)) == 1 and (out / JOURNAL).read_bytes() == data[:first]
    watch(model, drop, out, once=True, settle=0, echo=None)
    assert sorted(e["file"] for e in _lines(out)) == ["s0.ply", "s1.ply"]


def test_one_watcher_per_results_folder(model, tmp_path):
    (tmp_path / "drop").mkdir()
    with Watcher(model, tmp_path / "drop", tmp_path / "out", echo=None):
        with pytest.raises(InspectionError, match="another watcher"):
            Watcher(model, tmp_path / "drop", tmp_path / "out", echo=None).open()


def test_kill_9_at_random_moments_then_restart_gives_each_file_exactly_one_line(model, tmp_path):
    drop, out = tmp_path / "drop", tmp_path / "out"
    n_files = 12
    for i in range(n_files):
        _drop(drop, f"s{i:02d}", seed=200 + i, dent=0.1 * (i % 4 == 0))
    cmd = [sys.executable, "-m", "inspection", "watch", "--model", str(model), "--data", str(drop), "--out", str(out),
           "--settle", "0", "--interval", "0.05", "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rng = np.random.default_rng(0)
    kills = 0
    for round_ in range(3):
        before = len((out / JOURNAL).read_bytes()) if (out / JOURNAL).exists() else 0
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.time() + 30
        if round_ == 0:  # during start-up (imports, journal, model)
            time.sleep(rng.uniform(0.2, 2.0))
        else:  # while it scores: once the journal has grown, a random moment later
            while time.time() < deadline and proc.poll() is None and \
                    (not (out / JOURNAL).exists() or (out / JOURNAL).stat().st_size <= before):
                time.sleep(0.005)
            time.sleep(rng.uniform(0.0, 0.5))
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            kills += 1
        proc.wait()
        if (out / JOURNAL).exists():
            files = [e["file"] for e in read_journal(out / JOURNAL, repair=False)]
            assert len(files) == len(set(files)), f"round {round_}: a file scored twice"
    assert kills >= 2
    r = subprocess.run(cmd + ["--once"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = _lines(out)
    assert sorted(e["file"] for e in lines) == [f"s{i:02d}.ply" for i in range(n_files)]
    assert all(e["verdict"] != "error" for e in lines)
    assert len((out / TABLE).read_text().splitlines()) == n_files + 1
    assert len(list((out / "maps").glob("*.ply"))) == n_files


def _exit_status(argv):
    """main's return value, or the exit status of the argument parser's one-line error."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("argv, message", [
    (["--settle", "-1"], "--settle"),
    (["--interval", "soon"], "--interval"),
    (["--interval", "0"], "--interval"),
    (["--maps", "some"], "--maps"),
])
def test_bad_options_are_one_line_and_exit_2(model, tmp_path, capsys, argv, message):
    (tmp_path / "drop").mkdir()
    rc = _exit_status(["watch", "--model", str(model), "--data", str(tmp_path / "drop"), "--out",
                       str(tmp_path / "out"), "--once", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1


def test_missing_folder_and_uncalibrated_model_are_one_line(model, tmp_path, capsys):
    assert main(["watch", "--model", str(model), "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o"),
                 "--once"]) == 2
    assert "nope: no such folder" in capsys.readouterr().err
    raw = tmp_path / "raw.pt"
    import torch

    state = torch.load(model, weights_only=False)
    state.pop("calibration")
    torch.save(state, raw)
    (tmp_path / "drop").mkdir()
    assert main(["watch", "--model", str(raw), "--data", str(tmp_path / "drop"), "--out", str(tmp_path / "o"),
                 "--once"]) == 2
    err = capsys.readouterr().err
    assert "not calibrated" in err and len(err.strip().splitlines()) == 1
