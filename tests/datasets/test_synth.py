"""Tests of datasets.parts, datasets.synth and the synth command: the built-in part, mesh loading, collections."""
import numpy as np
import pytest
import trimesh

from datasets.frame import Frame
from datasets.parts import builtin_part, load_part
from datasets.synth import synthesise

SMALL = dict(n_train=2, n_validation=1, n_test_good=2, n_test_defective=1, n_points=800, progress=False)
CLI_SMALL = ["--mesh", "builtin", "--train", "2", "--test-good", "1", "--test-defective", "1", "--points", "800",
             "--quiet"]


@pytest.fixture(scope="module")
def bracket():
    return builtin_part()


@pytest.fixture(scope="module")
def part():
    """A small watertight part with flat faces and an edge-rich outline (fast to scan)."""
    return trimesh.creation.box(extents=(3.0, 2.0, 1.0))


def test_builtin_part_is_a_deterministic_watertight_solid(bracket):
    assert bracket.is_watertight and bracket.is_winding_consistent and bracket.volume > 0
    assert bracket.body_count == 1
    assert bracket.euler_number == 2 - 2 * 5  # four bolt holes and the bore
    again = builtin_part()
    np.testing.assert_array_equal(again.vertices, bracket.vertices)
    np.testing.assert_array_equal(again.faces, bracket.faces)


def test_load_part_reads_meshes_and_builtin(tmp_path, part):
    path = tmp_path / "part.stl"
    part.export(path)
    loaded = load_part(path)
    assert loaded.is_watertight and loaded.volume == pytest.approx(part.volume)
    assert len(load_part("builtin").faces) > 0


@pytest.mark.parametrize("case", ["empty", "point_cloud", "extension", "missing", "garbage"])
def test_load_part_rejects_non_meshes_naming_the_file(tmp_path, case):
    if case == "empty":
        path = tmp_path / "empty.obj"
        path.write_text("")
    elif case == "point_cloud":
        path = tmp_path / "cloud.ply"
        trimesh.PointCloud(np.random.default_rng(0).random((20, 3))).export(path)
    elif case == "extension":
        path = tmp_path / "part.xyz"
        path.write_text("0 0 0\n")
    elif case == "garbage":
        path = tmp_path / "garbage.stl"
        path.write_text("not a mesh at all")
    else:
        path = tmp_path / "nowhere.obj"
    with pytest.raises(ValueError) as error:
        load_part(path)
    assert str(path) in str(error.value)


def test_synthesise_layout_labels_and_frame(part):
    scans, frame = synthesise(part, seed=1, part_id="box", **SMALL)
    names = [s.name for s in scans]
    assert names == ["train/good/000", "train/good/001", "validation/good/000", "test/good/000", "test/good/001",
                     "test/dent/000", "test/bump/000", "test/missing/000", "test/foreign/000"]
    assert frame == Frame.fit(part.vertices)
    for scan in scans:
        assert scan.points.shape == (800, 3) and scan.points.dtype == np.float32 and scan.part_id == "box"
        assert scan.sensor_origin is not None
        assert np.all(np.abs(scan.points) < 0.5 + 0.05)  # unit cube, plus noise and defects sticking out
        assert np.all(np.sum(scan.normals * (scan.sensor_origin - scan.points), axis=1) > 0)
        if scan.split == "test":
            assert scan.point_labels is not None
            if scan.label == "good":
                assert scan.point_labels.sum() == 0 and scan.defect == ""
            else:
                assert scan.defect == scan.name.split("/")[1] and scan.point_labels.sum() >= 24
        else:
            assert scan.point_labels is None and scan.label == "good"
    # noise relative to the part: 0.002 x diagonal in mesh units, on the good scans' distance to the part
    good = scans[0]
    distance = trimesh.proximity.closest_point(part, frame.to_file(good.points))[1]
    assert 0.5 < np.sqrt(np.mean(distance ** 2)) / (0.002 * np.linalg.norm(part.extents)) < 1.2


def test_synthesise_is_deterministic_and_seeded(part):
    a, _ = synthesise(part, seed=3, **SMALL)
    b, _ = synthesise(part, seed=3, **SMALL)
    c, _ = synthesise(part, seed=4, **SMALL)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.normals, y.normals)
    assert not np.array_equal(a[0].points, c[0].points)


def test_synthesise_rejects_unknown_defects(part):
    with pytest.raises(ValueError, match="scratch"):
        synthesise(part, defects=("dent", "scratch"), **SMALL)


def test_cli_writes_byte_identical_collections(tmp_path):
    from datasets.__main__ import main
    from datasets.collection import ScanCollection

    for name in ("a.h5", "b.h5"):
        assert main(["synth", *CLI_SMALL, "--out", str(tmp_path / name)]) == 0
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()
    collection = ScanCollection(tmp_path / "a.h5")
    assert len(collection) == 2 + 1 + 4
    assert len(collection.select(label="defective")) == 4
    collection.close()


def test_cli_tree_format(tmp_path):
    from datasets.__main__ import main
    from datasets.cloud_io import read_cloud

    out = tmp_path / "tree"
    assert main(["synth", *CLI_SMALL, "--out", str(out), "--format", "tree", "--defects", "dent,foreign"]) == 0
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.*")) == [
        "ground_truth/dent/000.deviation.txt", "ground_truth/dent/000.txt", "ground_truth/foreign/000.deviation.txt",
        "ground_truth/foreign/000.txt", "synth.json", "test/dent/000.ply",
        "test/foreign/000.ply", "test/good/000.ply", "train/good/000.ply", "train/good/001.ply"]
    truth = np.loadtxt(out / "ground_truth" / "dent" / "000.txt")
    assert len(truth) == 800 and set(np.unique(truth)) == {0.0, 1.0}
    cloud = read_cloud(out / "test" / "dent" / "000.ply")
    points = cloud[0] if isinstance(cloud, tuple) else cloud.points
    assert len(points) == 800
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left behind


def test_cli_errors_name_the_problem(tmp_path, capsys):
    from datasets.__main__ import main

    existing = tmp_path / "taken.h5"
    existing.write_bytes(b"")
    assert main(["synth", *CLI_SMALL, "--out", str(existing)]) == 2
    assert str(existing) in capsys.readouterr().err
    assert main(["synth", *CLI_SMALL, "--out", str(tmp_path / "x.h5"), "--defects", "dent,scratch"]) == 2
    assert "scratch" in capsys.readouterr().err
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.zeros((5, 3)) + np.arange(5)[:, None]).export(cloud)
    assert main(["synth", "--mesh", str(cloud), "--out", str(tmp_path / "y.h5")]) == 2
    assert str(cloud) in capsys.readouterr().err


@pytest.mark.shared_meshes
def test_fandisk_defects_are_visible(shared_meshes):
    mesh = load_part(shared_meshes / "fandisk.obj")
    scans, frame = synthesise(mesh, n_train=0, n_test_good=0, n_test_defective=1, n_points=4000, seed=0,
                              progress=False)
    for scan in scans:
        labels = scan.point_labels.astype(bool)
        assert labels.mean() >= 0.015
        distance = trimesh.proximity.closest_point(mesh, frame.to_file(scan.points))[1] * frame.scale
        # collection units: the defect is measurably off the part, the rest within noise (0.002 x diagonal)
        noise = 0.002 * np.linalg.norm(np.ptp(mesh.vertices, axis=0)) * frame.scale
        assert np.median(distance[labels]) > 2 * noise and np.quantile(distance[labels], 0.9) > 4 * noise
        assert np.quantile(distance[~labels], 0.99) < 4 * noise


def test_written_origins_leave_the_scans_as_they_are(part):
    """Sidecar origins written as a user writes them (a stand-off off by a factor, an axis off by degrees) change
    the recorded origin of every scan and nothing else; a line scanner's scans are a scan collection like any."""
    exact, _ = synthesise(part, seed=2, **SMALL)
    written, _ = synthesise(part, seed=2, origin_standoff=(0.5, 3.0), origin_tilt_deg=5.0, **SMALL)
    for x, y in zip(exact, written):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.point_labels if x.point_labels is not None else 0,
                                      y.point_labels if y.point_labels is not None else 0)
        assert not np.allclose(x.sensor_origin, y.sensor_origin)
    lines, _ = synthesise(part, seed=2, sensor="line", **SMALL)
    assert [s.name for s in lines] == [s.name for s in exact]
    assert all(s.point_labels.sum() >= 24 for s in lines if s.label == "defective")
    with pytest.raises(ValueError, match="origin_standoff"):
        synthesise(part, seed=2, origin_standoff=(2.0, 1.0), **SMALL)
    with pytest.raises(ValueError, match="sensor"):
        synthesise(part, seed=2, sensor="fisheye", **SMALL)
