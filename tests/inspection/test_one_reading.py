"""One reading of a scan file (issue 47, item 4): the same file gives the same points, normals and score whether it is
imported into a collection first or scored from a folder (``score --data FOLDER``, ``watch``), for each layout's
rule of orientation: no sensor origin with templates (Real3D-AD), a sensor-origin sidecar (a tree with ground truth,
stray points dropped), no origin in a flat folder (a random subset of points).

The data are made here and tiny (a bowl of a few hundred points a cloud; half-spheres); the model is an untrained
tiny field saved with each collection's frame, which scores deterministically.
"""
import csv
import json
import os
import shutil

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # only if torch is not loaded yet; see inspection.__main__

from datasets import ScanCollection, write_cloud
from datasets.importer import ScanSource, import_tree, load_source
from datasets.layouts import orient_by_surface, orient_like_templates
from datasets.normals import estimate_normals, orient_consistently
from datasets.importer import read_scan
from datasets.reading import SIGNS_FROM_SURFACE, SIGNS_KEY, Reading
from inspection.errors import InspectionError
from inspection.loading import load_scans, read_file, signed_for_scoring

OUTER, INNER, RIM = 12.0, 10.0, 4.0  # mm: a bowl, a spherical shell cut at z = RIM, open upward (concave inside)


# ---- data ------------------------------------------------------------------------------------------------------------
def bowl(n, rng):
    """About ``n`` points on the bowl (outer and inner shell, the rim's annulus) and their outward normals."""
    def shell(m, r):
        d = rng.normal(size=(4 * m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[d[:, 2] * r <= RIM][:m]
        return d * r, d

    k_out, k_in, k_rim = int(0.5 * n), int(0.4 * n), n - int(0.5 * n) - int(0.4 * n)
    p_out, n_out = shell(k_out, OUTER)
    p_in, n_in = shell(k_in, INNER)
    r = np.sqrt(rng.uniform(INNER ** 2 - RIM ** 2, OUTER ** 2 - RIM ** 2, k_rim))
    t = rng.uniform(0.0, 2 * np.pi, k_rim)
    p_rim = np.column_stack([r * np.cos(t), r * np.sin(t), np.full(k_rim, RIM)])
    n_rim = np.tile([0.0, 0.0, 1.0], (k_rim, 1))
    return np.vstack([p_out, p_in, p_rim]), np.vstack([n_out, -n_in, n_rim])


def view_into_the_bowl(n, rng, noise=0.03):
    """A partial scan from above, looking into the bowl (what it returns: the inner floor, the rim, the outer band);
    its true outward normals. Away from its own centroid is the wrong side for most of it."""
    p, nrm = bowl(n, rng)
    seen = nrm[:, 2] > 0.5  # (the outer band near the rim is grazing: not returned)
    inner = np.isclose(np.linalg.norm(p, axis=1), INNER)
    seen &= ~inner | (np.linalg.norm(p[:, :2], axis=1) < 9.0)  # under the rim: hidden
    return p[seen] + rng.normal(0.0, noise, (int(seen.sum()), 3)), nrm[seen]


def write_pcd(path, points):
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", f"WIDTH {len(points)}",
              "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(points)}", "DATA ascii"]
    path.write_text("\n".join(header) + "\n" + "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in points) + "\n")


def tiny_model(collection, out):
    """An untrained tiny field (seeded) saved with ``collection``'s frame and fingerprint; its train split is the
    model's training scans, its validation split (else its first test scans) held back."""
    import torch

    from autodecoder.field.networks import build_networks
    from autodecoder.field.stochastic_field import StochasticField
    from datasets import Frame
    from inspection.model_io import save_reference_field

    with ScanCollection(collection) as c:
        frame, fingerprint, meta = c.frame, c.fingerprint(), c.metadata()
    train = [m["name"] for m in meta if m["split"] == "train"]
    held = [m["name"] for m in meta if m["split"] == "validation"]
    config = {"width": 16, "depth": 1, "latent_dim": 0, "covariance": "feature", "features": 8, "omega0": 5.0,
              "lengthscale": 0.05, "box_lo": [-0.6] * 3, "box_hi": [0.6] * 3}
    torch.manual_seed(0)
    mean_net, cov_net = build_networks(config)
    field = StochasticField(mean_net, cov_net, Frame.identity(), config, noise=0.01)
    save_reference_field(field, out, frame=frame, fingerprint=fingerprint, train_names=train, heldback_names=held)
    return out


def calibrated(collection, model_path):
    """(Inspector fitted on ``collection``, its calibration written into ``model_path``, the model's frame)."""
    from inspection.calibration import write_calibration
    from inspection.estimator import Inspector
    from inspection.model_io import load_model_handle

    handle = load_model_handle(model_path)
    with ScanCollection(collection) as c:
        insp = Inspector(handle.model, alpha=0.3).fit(c)
    write_calibration(model_path, insp.calibration())
    return insp, handle.frame


def quiet(line):
    """An echo that says nothing."""


def scores_csv(out):
    with open(out / "scores.csv", newline="") as f:
        return {row["name"].split("/")[-1]: float(row["score"]) for row in csv.DictReader(f)}


def assert_same_scan(a, b, insp):
    """Points and, as scored, normals equal (float32 storage: tight tolerance), and the same score."""
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-6)
    na, nb = signed_for_scoring(a, insp.reference_).normals, signed_for_scoring(b, insp.reference_).normals
    np.testing.assert_allclose(na, nb, rtol=0, atol=1e-6)
    assert insp.inspect(a).score == pytest.approx(insp.inspect(b).score, rel=1e-9, abs=1e-12)


# ---- Real3D-AD: no sensor origin, 4 templates -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def real3d(tmp_path_factory, one_torch_thread):
    """A Real3D-AD class folder (4 bowl templates, 2 good views into the bowl), imported with an automatic voxel,
    a tiny model calibrated on it, and the test files copied into a flat folder."""
    tmp = tmp_path_factory.mktemp("real3d")
    root, rng = tmp / "bowl", np.random.default_rng(0)
    for k in range(4):
        write_pcd(root / "train" / f"{k + 1}_template.pcd", bowl(1400, rng)[0])
    truth = {}
    for stem in ("1_good", "2_good"):
        points, normals = view_into_the_bowl(1400, rng)
        write_pcd(root / "test" / f"{stem}.pcd", points)
        truth[stem] = (points, normals)
    summary = import_tree(root, tmp / "bowl.h5", views=3, validation_views=2, max_points=300, progress=False)
    assert summary["voxel"] is not None and summary["oriented_by_templates"] == 2
    folder = tmp / "line"
    folder.mkdir()
    for stem in truth:
        shutil.copy(root / "test" / f"{stem}.pcd", folder)
    model = tiny_model(tmp / "bowl.h5", tmp / "model.pt")
    insp, frame = calibrated(tmp / "bowl.h5", model)
    return {"tmp": tmp, "root": root, "folder": folder, "truth": truth, "model": model, "insp": insp, "frame": frame}


def test_the_reading_is_recorded_at_import_and_carried_by_the_calibration(real3d):
    with ScanCollection(real3d["tmp"] / "bowl.h5") as c:
        reading = Reading.from_dict(c.provenance["reading"])
        voxel = c.provenance["voxel"]
    assert reading == Reading(voxel=voxel, file_normals="ignored", normals="after downsampling",
                              signs=SIGNS_FROM_SURFACE)
    from inspection.calibration import read_calibration
    from inspection.estimator import Inspector

    assert real3d["insp"].reading_ == reading.as_dict()
    restored = Inspector.from_calibration(real3d["insp"].model, read_calibration(real3d["model"]))
    assert restored.reading_ == reading.as_dict()


def test_a_real3d_scan_is_the_same_imported_and_read_from_a_folder(real3d):
    insp, frame = real3d["insp"], real3d["frame"]
    imported = {s.name.split("/")[-1]: s for s in load_scans(real3d["tmp"] / "bowl.h5", frame, split="test")[0]}
    read, _ = load_scans(real3d["folder"], frame, reading=insp.reading_)
    assert sorted(imported) == sorted(s.name for s in read) == ["1_good", "2_good"]
    for scan in read:
        twin = imported[scan.name]
        assert scan.extra[SIGNS_KEY] == twin.extra[SIGNS_KEY] == SIGNS_FROM_SURFACE
        # the bug: the file's normals as estimated disagree with the imported ones (signed by the templates)
        assert np.mean(np.einsum("ij,ij->i", scan.normals, twin.normals) < 0) > 0.3
        assert_same_scan(scan, twin, insp)


def test_scoring_signs_are_as_good_as_the_templates(real3d):
    """The good surface's signs at scoring are right where the templates' were at import (truth: the bowl)."""
    insp, frame = real3d["insp"], real3d["frame"]
    for scan in load_scans(real3d["tmp"] / "bowl.h5", frame, split="test")[0]:
        points = frame.to_file(scan.points.astype(np.float64))
        stem = scan.name.split("/")[-1]
        file_points, file_normals = real3d["truth"][stem]
        from scipy.spatial import cKDTree

        truth = file_normals[cKDTree(file_points).query(points)[1]]
        wrong_imported = np.mean(np.einsum("ij,ij->i", scan.normals, truth) < 0)
        wrong_scored = np.mean(np.einsum("ij,ij->i", signed_for_scoring(scan, insp.reference_).normals, truth) < 0)
        assert wrong_scored <= max(wrong_imported, 0.02)
        estimated = estimate_normals(points)  # the estimator's own signs: the wrong side of most of the bowl
        assert np.mean(np.einsum("ij,ij->i", estimated, truth) < 0) > 0.3


def test_score_and_watch_give_a_folder_file_the_imported_scans_score(real3d, tmp_path):
    from inspection.run import score
    from inspection.watch import watch

    score(real3d["model"], real3d["tmp"] / "bowl.h5", tmp_path / "coll", maps="none", progress=False, echo=quiet)
    score(real3d["model"], real3d["folder"], tmp_path / "folder", maps="none", progress=False, echo=quiet)
    watch(real3d["model"], real3d["folder"], tmp_path / "watch", once=True, settle=0, maps="none", echo=None)
    imported, folder = scores_csv(tmp_path / "coll"), scores_csv(tmp_path / "folder")
    journal = [json.loads(line) for line in (tmp_path / "watch" / "verdicts.jsonl").read_text().splitlines()]
    watched = {e["name"]: e["score"] for e in journal}
    assert sorted(imported) == sorted(folder) == sorted(watched) == ["1_good", "2_good"]
    for stem in imported:
        assert folder[stem] == pytest.approx(imported[stem], rel=1e-6)
        assert watched[stem] == pytest.approx(imported[stem], rel=1e-6)


# ---- a tree with sensor-origin sidecars, ground truth and stray points; a flat folder with a random subset ---------
def half_sphere(rng, n=500, dent=0.0):
    """A half-sphere (radius 20 mm, off the origin) seen from +z, and where its sensor was."""
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 20.0 - dent * (d[:, 2] > 0.9)
    centre = np.array([50.0, -10.0, 5.0])
    return centre + d * r[:, None] + rng.normal(0.0, 0.02, (n, 3)), centre + [0.0, 0.0, 60.0], d[:, 2] > 0.9


def make_tree(root, rng):
    """train/good (5 views with sidecars), test/good (one with a sidecar and a stray point, one without), test/dent
    with ground truth; the test files also copied into a flat folder ``root.parent / 'line'``."""
    for i in range(5):
        points, origin, _ = half_sphere(rng)
        write_cloud(root / "train" / "good" / f"{i:03d}.ply", points)
        (root / "train" / "good" / f"{i:03d}.json").write_text(json.dumps({"sensor_origin": origin.tolist()}))
    points, origin, _ = half_sphere(rng)
    points = np.vstack([points, points[:1] + [0.0, 0.0, 6.0]])  # one stray return above the part
    write_cloud(root / "test" / "good" / "a.ply", points)
    (root / "test" / "good" / "a.json").write_text(json.dumps({"sensor_origin": origin.tolist()}))
    write_cloud(root / "test" / "good" / "b.ply", half_sphere(rng)[0])  # no sidecar: normals estimated
    points, origin, pole = half_sphere(rng, dent=2.0)
    write_cloud(root / "test" / "dent" / "c.ply", points)
    (root / "test" / "dent" / "c.json").write_text(json.dumps({"sensor_origin": origin.tolist()}))
    (root / "ground_truth" / "dent").mkdir(parents=True)
    np.savetxt(root / "ground_truth" / "dent" / "c.txt", pole.astype(int), fmt="%d")
    line = root.parent / "line"
    line.mkdir()
    for p in (root / "test").rglob("*.*"):
        shutil.copy(p, line)
    return line


@pytest.mark.parametrize("options", [{"voxel": 1.5, "drop_strays": True}, {"n_points": 300}],
                         ids=["voxel-strays", "subset"])
def test_a_tree_scan_is_the_same_imported_and_read_from_its_tree_or_a_flat_folder(tmp_path, options,
                                                                                   one_torch_thread):
    line = make_tree(tmp_path / "tree", np.random.default_rng(1))
    import_tree(tmp_path / "tree", tmp_path / "tree.h5", progress=False, **options)
    insp, frame = calibrated(tmp_path / "tree.h5", tiny_model(tmp_path / "tree.h5", tmp_path / "model.pt"))
    assert insp.reading_["strays"] == ("dropped" if options.get("drop_strays") else "kept")
    imported = {s.name.split("/")[-1]: s for s in load_scans(tmp_path / "tree.h5", frame, split="test")[0]}
    from_tree = {s.name.split("/")[-1]: s for s in
                 load_scans(tmp_path / "tree", frame, split="test", reading=insp.reading_)[0]}
    flat = {s.name: s for s in load_scans(line, frame, reading=insp.reading_)[0]}
    assert sorted(imported) == sorted(from_tree) == sorted(flat) == ["a", "b", "c"]
    for stem, twin in imported.items():
        assert SIGNS_KEY not in twin.extra  # a tree's signs are the estimator's, on every path
        for scan in (from_tree[stem], flat[stem]):
            assert (scan.sensor_origin is None) == (twin.sensor_origin is None) == (stem == "b")
            assert_same_scan(scan, twin, insp)
    np.testing.assert_array_equal(from_tree["c"].point_labels, imported["c"].point_labels)
    if options.get("drop_strays"):  # the stray return is gone on every path
        assert len(flat["a"].points) == len(imported["a"].points) < len(load_scans(line, frame)[0][0].points)


def test_a_file_read_without_its_collections_reading_would_differ(tmp_path):
    """What the recorded reading prevents: the same file read with a folder's defaults keeps every point."""
    line = make_tree(tmp_path / "tree", np.random.default_rng(2))
    import_tree(tmp_path / "tree", tmp_path / "tree.h5", voxel=1.5, progress=False)
    with ScanCollection(tmp_path / "tree.h5") as c:
        frame, reading = c.frame, c.provenance["reading"]
        imported = c.read_many(c.select(split="test"))
    by_default = {s.name: s for s in load_scans(line, frame)[0]}
    recorded = {s.name: s for s in load_scans(line, frame, reading=reading)[0]}
    for twin in imported:
        stem = twin.name.split("/")[-1]
        assert len(by_default[stem].points) > len(twin.points) == len(recorded[stem].points)


# ---- the rule ----------------------------------------------------------------------------------------------------
def test_orient_by_surface_depends_on_the_normals_lines_only():
    """Any per-point signs in give the same signs out, with points off the surface (a bump) and without any."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    template, template_normals = bowl(3000, rng)
    surface = (cKDTree(template), template_normals, 0.6)
    points, truth = view_into_the_bowl(1500, rng)
    bump = np.linalg.norm(points - points[0], axis=1) < 2.0
    points = points + 2.5 * bump[:, None] * truth  # off the surface by more than 3 spacings
    raw = estimate_normals(points)
    out, on = orient_by_surface(points, raw, surface)
    assert on
    signs = np.where(rng.random(len(points)) < 0.5, -1.0, 1.0)[:, None]
    np.testing.assert_array_equal(orient_by_surface(points, raw * signs, surface)[0], out)
    np.testing.assert_array_equal(orient_by_surface(points, -raw, surface)[0], out)
    # the templates' rule on the estimator's own signs gives the same (what the import stores)
    np.testing.assert_array_equal(orient_like_templates(points, raw, surface)[0], out)
    assert np.mean(np.einsum("ij,ij->i", out, truth)[~bump] < 0) < 0.02
    # without a surface, or off it: the estimator's consistent signs, whatever came in
    np.testing.assert_array_equal(orient_by_surface(points, raw * signs, None)[0], orient_consistently(points, raw))
    moved, on = orient_by_surface(points + 100.0, raw * signs, surface)
    assert not on
    np.testing.assert_array_equal(moved, orient_consistently(points + 100.0, raw))


def test_old_template_collections_leave_the_signs_to_the_surface_and_records_are_checked():
    old = {"source": "import", "layout": "real3d-ad", "voxel": 0.4, "points": None, "seed": 3}
    assert Reading.from_provenance(old) == Reading(voxel=0.4, seed=3, file_normals="ignored",
                                                   normals="after downsampling", signs=SIGNS_FROM_SURFACE)
    tree = {"source": "import", "voxel": None, "points": 100, "seed": 0, "stray_points": {"dropped": True}}
    assert Reading.from_provenance(tree) == Reading(points=100, strays="dropped")
    assert Reading.from_dict(Reading(voxel=2.0).as_dict()) == Reading(voxel=2.0)
    with pytest.raises(ValueError, match="signs"):
        Reading(signs="surface")  # a file's own normals are never re-signed
    with pytest.raises(ValueError, match="version"):
        Reading.from_dict({"version": 99})
    with pytest.raises(ValueError, match="voxel"):
        Reading(voxel=-1.0)


def test_bad_files_on_the_new_paths_are_errors_that_name_them(tmp_path):
    from datasets import Frame

    frame = Frame(np.zeros(3), 0.1)
    reading = Reading(voxel=50.0, file_normals="ignored", normals="after downsampling", signs=SIGNS_FROM_SURFACE)
    small = tmp_path / "small.xyz"  # a few points that one voxel merges
    np.savetxt(small, np.random.default_rng(0).normal(size=(6, 3)))
    with pytest.raises(InspectionError, match=str(small)) as e:
        read_file(ScanSource(small, "small", "test", "unknown", ""), frame, reading)
    assert "after downsampling" in str(e.value)
    bad = tmp_path / "bad.pcd"
    bad.write_text("not a pcd\n")
    with pytest.raises(InspectionError, match=str(bad)):
        load_scans(tmp_path, frame, reading=reading.as_dict())
    _, info = load_scans(tmp_path, frame, reading=reading, errors="collect")
    assert sorted(name for name, _ in info["failed"]) == ["bad", "small"]
    with pytest.raises(InspectionError, match="reading of scanner files.*version"):
        load_scans(tmp_path, frame, reading={"version": 99})
    sidecar = tmp_path / "side"
    sidecar.mkdir()
    np.savetxt(sidecar / "s.xyz", np.random.default_rng(0).normal(size=(50, 3)))
    (sidecar / "s.json").write_text('{"sensor_origin": [1, 2]}')
    with pytest.raises(ValueError, match="s.json"):
        read_scan(ScanSource(sidecar / "s.xyz", "s", "test", "unknown", ""), reading)
    with pytest.raises(ValueError, match="not both"):
        load_source(ScanSource(sidecar / "s.xyz", "s", "test", "unknown", ""), voxel=1.0, reading=reading)
