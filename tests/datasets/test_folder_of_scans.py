"""A folder as a scanner or a colleague leaves it is data: `nsspr-data import` skips what is not a point cloud (a
README, a scanner's alignment .conf, hidden files, a mesh) and names it in one line, never touching the user's
files; `--split train --label good` makes a flat folder of good scans a training collection."""
import hashlib

import numpy as np
import pytest

from datasets import ScanCollection, write_cloud
from datasets.__main__ import main
from datasets.importer import import_tree, list_folder, skipped_line


def _view(seed, n=200):
    """A noisy half-sphere of radius 20 mm seen from +z, in millimetres, without normals (as scanners write)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return 20.0 * d + rng.normal(0.0, 0.05, (n, 3)) + np.array([100.0, 50.0, 0.0])


def _scanner_folder(root, n=4):
    """What a scanner's folder holds: clouds, one with its sensor-origin sidecar, and files that are not clouds."""
    root.mkdir(parents=True)
    for i in range(n):
        write_cloud(root / f"view{i}.ply", _view(i))
    (root / "view0.json").write_text('{"sensor_origin": [100, 50, 300]}')  # a cloud's sidecar: used, not skipped
    (root / "README").write_text("Range data, Cyberware 3030MS\n")
    (root / "bun.conf").write_text("camera 0 0 0 0 0 0 1\nbmesh view0.ply 0 0 0 0 0 0 1\n")
    (root / ".DS_Store").write_bytes(b"\x00\x01")
    (root / "part.stl").write_text("solid part\nendsolid part\n")
    return root


def _digests(root):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()}


def test_import_skips_what_is_not_a_cloud_names_it_in_one_line_and_leaves_the_folder_alone(tmp_path, capsys):
    root = _scanner_folder(tmp_path / "scans")
    before = _digests(root)
    assert main(["import", str(root), "--out", str(tmp_path / "c.h5")]) == 0
    out = capsys.readouterr().out
    skipped = [line for line in out.splitlines() if line.startswith("skipped")]
    assert skipped == ["skipped 4 files that are not point clouds: .DS_Store, README, bun.conf, part.stl"]
    with ScanCollection(tmp_path / "c.h5") as c:
        assert sorted(c.names) == [f"view{i}" for i in range(4)]
        assert {(m["split"], m["label"]) for m in c.metadata()} == {("test", "unknown")}
        assert c[c.index_of("view0")].sensor_origin is not None  # the sidecar was read
    # a flat folder left in split 'test': the import says how it becomes training data
    assert "--split train --label good" in out
    assert _digests(root) == before  # the user's files: not one byte changed, nothing added


def test_a_flat_folder_of_good_scans_becomes_a_training_collection(tmp_path, capsys):
    root = _scanner_folder(tmp_path / "scans")
    assert main(["import", str(root), "--split", "train", "--label", "good", "--out", str(tmp_path / "g.h5")]) == 0
    assert "--split train --label good" not in capsys.readouterr().out  # nothing more to say
    with ScanCollection(tmp_path / "g.h5") as c:
        assert {(m["split"], m["label"]) for m in c.metadata()} == {("train", "good")} and len(c) == 4
        assert c.provenance["frame_fitted_on"] == "train"
    # a split alone: labelled as the files directly in a tree's split folder are (good, or unknown in test)
    summary = import_tree(root, tmp_path / "v.h5", progress=False, split="validation")
    assert list(summary["groups"]) == [("validation", "good", "")]
    summary = import_tree(root, tmp_path / "d.h5", progress=False, split="test", label="defective")
    assert list(summary["groups"]) == [("test", "defective", "")]


def test_a_tree_names_its_skipped_files_and_refuses_a_split_and_label(tmp_path, capsys):
    root = tmp_path / "tree"
    for split, cls, k in (("train", "good", 0), ("train", "good", 1), ("test", "good", 2), ("test", "dent", 3)):
        write_cloud(root / split / cls / f"s{k}.ply", _view(k))
    (root / "train" / "good" / "scanner.conf").write_text("bmesh s0.ply 0 0 0 0 0 0 1\n")
    (root / "test" / "dent" / ".notes").write_text("hidden")
    (root / "README.md").write_text("a dataset's own README at the root: not part of any split")
    listing = list_folder(root)
    assert sorted(s.name for s in listing.sources) == ["test/dent/s3", "test/good/s2", "train/good/s0", "train/good/s1"]
    line = skipped_line(listing.skipped, root)
    assert line == "skipped 2 files that are not point clouds: test/dent/.notes, train/good/scanner.conf"
    assert main(["import", str(root), "--out", str(tmp_path / "t.h5")]) == 0
    assert line in capsys.readouterr().out
    # the tree's folders say the splits and labels: giving them as well is one clear error
    assert main(["import", str(root), "--split", "train", "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(root) in err and "tree" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


def test_a_folder_with_no_cloud_is_one_error_that_counts_what_it_skipped(tmp_path, capsys):
    root = tmp_path / "notes"
    root.mkdir()
    (root / "README").write_text("no scans here")
    (root / "a.conf").write_text("")
    with pytest.raises(ValueError, match=r"no point-cloud files found .*skipped 2 other files"):
        list_folder(root)
    assert main(["import", str(root), "--out", str(tmp_path / "c.h5")]) == 2
    assert "no point-cloud files found" in capsys.readouterr().err
