"""`score --jobs N`: scoring in N processes gives exactly the rows, order, maps and summary of one process."""
import json
import os

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # effective only if torch is not loaded yet; see inspection.__main__

from inspection.__main__ import main

from .tiny import half_sphere as _scan, tiny_field_model

@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A collection (6 good train scans; 9 test scans, 3 of them dented) and an untrained tiny field model
    calibrated on its good scans."""
    scans = [_scan(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(6)]
    scans += [_scan(f"test/good/{i:03d}", "test", "good", seed=10 + i) for i in range(6)]
    scans += [_scan(f"test/dent/{i:03d}", "test", "defective", "dent", seed=20 + i, dent=0.1) for i in range(3)]
    root = tiny_field_model(tmp_path_factory.mktemp("jobs"), scans)
    assert main(["calibrate", "--model", str(root / "model.pt"), "--data", str(root / "tree.h5"), "--alpha", "0.3",
                 "--quiet"]) == 0
    return root


def test_jobs_2_equals_jobs_1_exactly(workdir):
    outs = {}
    for jobs in (1, 2):
        out = workdir / f"out{jobs}"
        assert main(["score", "--model", str(workdir / "model.pt"), "--data", str(workdir / "tree.h5"), "--out",
                     str(out), "--maps", "all", "--jobs", str(jobs), "--quiet"]) == 0
        outs[jobs] = out
    csv1, csv2 = ((outs[j] / "scores.csv").read_text() for j in (1, 2))
    assert csv1 == csv2  # every score to 9 digits, every verdict, in the same (input) order
    names = [line.split(",")[0] for line in csv1.splitlines()[1:]]
    assert names == [f"test/good/{i:03d}" for i in range(6)] + [f"test/dent/{i:03d}" for i in range(3)]
    s1, s2 = (json.loads((outs[j] / "summary.json").read_text()) for j in (1, 2))
    for s in (s1, s2):
        s.pop("seconds_per_scan")  # a timing, not a result
    assert s1 == s2  # metrics, point-level AUROC included
    maps1 = sorted(p.name for p in (outs[1] / "maps").glob("*.ply"))
    assert len(maps1) == 9 and maps1 == sorted(p.name for p in (outs[2] / "maps").glob("*.ply"))
    for name in maps1:
        assert (outs[1] / "maps" / name).read_bytes() == (outs[2] / "maps" / name).read_bytes()


def test_jobs_must_be_a_positive_whole_number(workdir, tmp_path, capsys):
    for bad in ("0", "-3", "two"):
        with pytest.raises(SystemExit) as exc:
            main(["score", "--model", str(workdir / "model.pt"), "--data", str(workdir / "tree.h5"), "--out",
                  str(tmp_path / "o"), "--jobs", bad])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "--jobs" in err and len(err.strip().splitlines()) == 1
