"""Registration of a real range scan placed by hand: a known 5 degree / 2 % motion of a real view of the Stanford
bunny is undone to within a fraction of the view's point spacing. Uses ../shared/realscans (skipped, with the reason,
when that shared data is absent)."""
import json
from pathlib import Path

import numpy as np
import pytest

REALSCANS = Path(__file__).resolve().parents[3] / "shared" / "realscans" / "bunny"


@pytest.mark.skipif(not REALSCANS.is_dir(), reason=f"needs the real Stanford range scans (shared data, not in the "
                                                     f"repository) at {REALSCANS}")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_real_view_moved_by_hand_is_registered_back(seed):
    from scipy.spatial.transform import Rotation

    from datasets import read_cloud
    from inspection.align import Aligner

    full, _ = read_cloud(REALSCANS / "bun045.ply")
    full = np.asarray(full, dtype=np.float64)
    diagonal = float(np.linalg.norm(np.ptp(full, axis=0)))
    rng = np.random.default_rng(seed)
    scan = full[rng.choice(len(full), 4000, replace=False)]  # a fresh subset: no point lies exactly on a target one
    axis = rng.normal(size=3)
    rotation = Rotation.from_rotvec(np.radians(5.0) * axis / np.linalg.norm(axis)).as_matrix()
    shift = rng.normal(size=3)
    shift *= 0.02 * diagonal / np.linalg.norm(shift)
    centre = scan.mean(0)
    placed = (scan - centre) @ rotation.T + centre + shift  # 5 degrees about the view's centre, 2 % of its size
    aligner = Aligner(full, seed=0)
    moved_back, _, transform = aligner.align(placed)
    error = np.linalg.norm(moved_back - scan, axis=1)
    assert np.median(error) < 0.1 * aligner.spacing and error.max() < 0.5 * aligner.spacing
    # the transform found is the inverse of the one applied
    undo = Rotation.from_matrix(transform[:3, :3] @ rotation).magnitude()
    assert np.degrees(undo) < 0.1


# ---------------------------------------------------------------------------------------------------------------
# Alignment as a setting of the calibration: calibration scans are registered exactly as new scans are.
# Core tests: their own small data (no ../shared).

def _corner(name, split, seed, rotation_deg=0.0, n=600):
    """The three faces of a cube's corner (half side 0.25) that a sensor on the (1, 1, 1) diagonal sees: a view that
    pins all six degrees of freedom of a registration. Turned by ``rotation_deg`` about a seeded axis through the
    cube's centre and shifted by 1 % of its size when ``rotation_deg`` is not 0."""
    from scipy.spatial.transform import Rotation

    from datasets import Scan

    rng = np.random.default_rng(seed)
    face = rng.integers(0, 3, n)
    p = rng.uniform(-0.25, 0.25, (n, 3))
    p[np.arange(n), face] = 0.25
    normals = np.eye(3)[face]
    p += rng.normal(0, 0.001, (n, 3))
    if rotation_deg:
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(np.radians(rotation_deg) * axis / np.linalg.norm(axis))
        shift = rng.normal(size=3)
        p, normals = turn.apply(p) + 0.01 * 0.87 * shift / np.linalg.norm(shift), turn.apply(normals)
    return Scan(name=name, points=p.astype(np.float32), normals=normals.astype(np.float32), split=split,
                label="good", point_labels=None if split == "train" else np.zeros(n, np.uint8))


@pytest.fixture(scope="module")
def placed_by_hand(tmp_path_factory):
    """A collection of cube corners: 4 training scans in place, 3 held-back and 2 test scans turned by 4 degrees and
    shifted by 1 % of the size (parts placed by hand), with the tiny untrained field model of
    tests/inspection/tiny.py."""
    from tests.inspection.tiny import tiny_field_model

    scans = ([_corner(f"train/good/{i:03d}", "train", i) for i in range(4)]
             + [_corner(f"validation/good/{i:03d}", "validation", 10 + i, 4.0) for i in range(3)]
             + [_corner(f"test/good/{i:03d}", "test", 20 + i, 4.0) for i in range(2)])
    return tiny_field_model(tmp_path_factory.mktemp("placed"), scans, n_train=4, n_heldback=3), scans


def test_calibration_scans_are_registered_as_new_scans_are(placed_by_hand, one_torch_thread):
    from datasets import ScanCollection
    from inspection import Inspector
    from inspection.model_io import load_model_handle

    root, scans = placed_by_hand
    model = load_model_handle(root / "model.pt").model
    with ScanCollection(root / "tree.h5") as c:
        aligned = Inspector(model, align=True).fit(c)
        unmoved = Inspector(model).fit(c)
        held = c.read_many(c.select(split="validation"))
    assert aligned.aligner_ is not None and unmoved.aligner_ is None
    names = list(aligned.calibration_names_)
    for i, scan in enumerate(held):
        # a held-back scan's calibration score is the score it gets as a new scan: registered the same way (the
        # index seeds what is drawn per scan, as in calibration)
        result = aligned.inspect(scan, index=i)
        assert result.transform is not None and not np.allclose(result.transform, np.eye(4))
        assert aligned.calibration_scores_[names.index(scan.name)] == pytest.approx(result.score, rel=1e-9)
    # registration moves these scans: without it the calibration scores differ
    k = [names.index(s.name) for s in held]
    assert not np.allclose(aligned.calibration_scores_[k], unmoved.calibration_scores_[k], rtol=1e-3)


def test_a_training_scan_is_not_registered_onto_itself(placed_by_hand):
    from inspection.align import Aligner

    _, scans = placed_by_hand
    train = [s for s in scans if s.split == "train"]
    aligner = Aligner.from_scans(train)
    assert set(aligner.owners) == {s.name for s in train}
    for scan in train:
        without = aligner.without(scan.name)
        assert scan.name not in set(without.owners) and len(without.owners) == (aligner.owners != scan.name).sum()
    assert aligner.without("test/good/000") is aligner


def test_the_stored_alignment_moves_scans_as_the_calibration_did(placed_by_hand, one_torch_thread):
    from datasets import ScanCollection
    from inspection import Inspector
    from inspection.model_io import load_model_handle

    root, scans = placed_by_hand
    model = load_model_handle(root / "model.pt").model
    with ScanCollection(root / "tree.h5") as c:
        fitted = Inspector(model, align=True).fit(c)
    restored = Inspector.from_calibration(model, fitted.calibration())
    test = [s for s in scans if s.split == "test"]
    for scan in test:
        a, b = fitted.inspect(scan), restored.inspect(scan)
        np.testing.assert_allclose(a.transform, b.transform, atol=1e-6)
        assert a.score == pytest.approx(b.score, rel=1e-6)


def test_score_align_needs_a_calibration_with_it(placed_by_hand, tmp_path, one_torch_thread):
    import json
    import shutil

    from inspection.errors import InspectionError
    from inspection.job import calibrate
    from inspection.run import score

    root, _ = placed_by_hand
    # uncalibrated: score --align calibrates with alignment, and the calibration then aligns by itself
    model = tmp_path / "model.pt"
    shutil.copyfile(root / "model.pt", model)
    summary = score(model, root / "tree.h5", tmp_path / "out", align=True, progress=False, maps="none",
                    echo=lambda line: None)
    assert summary["aligned"] is True
    again = score(model, root / "tree.h5", tmp_path / "out2", progress=False, maps="none", echo=lambda line: None)
    assert again["aligned"] is True
    assert json.loads((tmp_path / "out2" / "summary.json").read_text())["aligned"] is True
    # calibrated without it: --align is refused with the command that fixes it
    plain = tmp_path / "plain.pt"
    shutil.copyfile(root / "model.pt", plain)
    calibrate(plain, root / "tree.h5", progress=False)
    with pytest.raises(InspectionError, match=r"calibrated without it.*calibrate --model .*--align"):
        score(plain, root / "tree.h5", tmp_path / "out3", align=True, progress=False, echo=lambda line: None)


def test_align_without_training_scans_is_one_clear_error(placed_by_hand, one_torch_thread):
    from inspection import Inspector
    from inspection.model_io import load_model_handle

    root, scans = placed_by_hand
    model = load_model_handle(root / "model.pt").model
    held = [s for s in scans if s.split == "validation"]
    with pytest.raises(ValueError, match="align=True registers every scan onto the model's good training scans"):
        Inspector(model, align=True).fit(held)


def test_registration_recovers_a_hand_placement_and_repeats_exactly():
    """A cube corner (a view that pins the pose) turned by 4 degrees and shifted by 1 % is moved back to within a
    small fraction of its point spacing, and the same call gives the same transform to the bit."""
    from inspection.align import Aligner

    target = _corner("target", "train", 0, n=6000)
    placed = _corner("placed", "test", 1, n=1500)  # a fresh sample of the same corner ...
    truth = placed.points.astype(np.float64)
    moved = _corner("placed", "test", 1, rotation_deg=4.0, n=1500)  # ... turned and shifted (same seed, same draw)
    aligner = Aligner(target.points, target.normals)
    back, _, T = aligner.align(moved.points)
    assert np.median(np.linalg.norm(back - truth, axis=1)) < 0.25 * aligner.spacing
    np.testing.assert_array_equal(T, aligner.transform(moved.points))


def test_a_view_that_does_not_pin_the_pose_stays_where_it_was_placed():
    """A flat patch can slide along its plane at no cost to point-to-plane ICP: the placement prior keeps it in
    place (within 0.1 % of the target's size along the plane) while its offset off the plane is corrected."""
    from inspection.align import Aligner

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-0.5, 0.5, (8000, 2)), np.zeros(8000)]
    patch = np.c_[rng.uniform(-0.1, 0.1, (1500, 2)), np.full(1500, 0.004)] + rng.normal(0, 0.0005, (1500, 3))
    aligner = Aligner(plane, np.tile([0.0, 0.0, 1.0], (8000, 1)))
    T = aligner.transform(patch)
    assert abs(T[2, 3] + 0.004) < 0.001  # pulled onto the plane
    assert np.abs(T[:2, 3]).max() < 1e-3 * aligner.size  # not slid along it
    assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))) < 0.1


def test_pose_spread_tells_a_fixture_from_parts_placed_by_hand():
    """Registering each training scan onto the others lowers its residuals by almost nothing in a fixture (ratio
    within 2 % of 1) and by far more when every scan was placed by hand (4 degrees, 1 %)."""
    from inspection.align import AUTO_RATIO, pose_spread

    fixture = [_corner(f"train/good/{i:03d}", "train", i, n=800) for i in range(6)]
    by_hand = [_corner(f"train/good/{i:03d}", "train", i, rotation_deg=4.0, n=800) for i in range(6)]
    assert abs(pose_spread(fixture) - 1) < 0.02
    assert pose_spread(by_hand) > 1.5 * AUTO_RATIO
    assert pose_spread(by_hand[:2]) == 1.0  # too few to compare


def test_align_auto_registers_only_where_the_poses_spread(tmp_path, one_torch_thread):
    """The default align='auto' registers the scans of parts placed by hand (and says so in one line) and leaves a
    fixture's alone; --no-align is never overridden."""
    from datasets import ScanCollection
    from inspection import Inspector
    from inspection.job import calibrate, describe_calibration
    from inspection.model_io import load_model_handle
    from tests.inspection.tiny import tiny_field_model

    def tree(name, degrees):
        scans = ([_corner(f"train/good/{i:03d}", "train", i, rotation_deg=degrees, n=500) for i in range(6)]
                 + [_corner(f"validation/good/{i:03d}", "validation", 10 + i, rotation_deg=degrees, n=500)
                    for i in range(3)])
        (tmp_path / name).mkdir()
        return tiny_field_model(tmp_path / name, scans, n_train=6, n_heldback=3)

    fixture, by_hand = tree("fixture", 0.0), tree("by_hand", 4.0)
    insp, info = calibrate(by_hand / "model.pt", by_hand / "tree.h5", progress=False)
    assert insp.settings_.align is True and insp.aligner_ is not None
    notes = [line for line in describe_calibration(insp, info) if "poses spread" in line]
    assert len(notes) == 1 and "--no-align" in notes[0]
    insp, info = calibrate(fixture / "model.pt", fixture / "tree.h5", progress=False)
    assert insp.settings_.align is False and insp.aligner_ is None and insp.alignment_note_ == ""
    model = load_model_handle(by_hand / "model.pt").model
    with ScanCollection(by_hand / "tree.h5") as c:
        assert Inspector(model, align=False).fit(c).settings_.align is False


def test_a_group_placed_by_hand_is_moved_into_one_pose():
    """register_group: six views of a corner, each placed by hand (4 degrees, 1 %), end in one common pose: registering
    them onto each other again changes (almost) nothing, where before it lowered their residuals by half and more."""
    from inspection.align import pose_spread, register_group

    by_hand = [_corner(f"train/good/{i:03d}", "train", i, rotation_deg=4.0, n=800) for i in range(6)]
    moved = register_group(by_hand)
    assert [m.name for m in moved] == [s.name for s in by_hand]
    assert pose_spread(by_hand) > 1.5 and abs(pose_spread(moved) - 1) < 0.05
    for scan, m in zip(by_hand, moved):  # each copy is its scan under the transform it records
        T = m.extra["align"]
        np.testing.assert_allclose(m.points, scan.points @ T[:3, :3].T + T[:3, 3], atol=1e-5)


def test_a_full_resolution_scan_is_registered_by_a_subset_as_well():
    """Above MAX_SOURCE points a scan is registered by an evenly spread subset: the whole scan still comes back."""
    from inspection.align import MAX_SOURCE, Aligner

    n = 3 * MAX_SOURCE
    target = _corner("target", "train", 0, n=6000)
    truth = _corner("placed", "test", 1, n=n).points.astype(np.float64)
    moved = _corner("placed", "test", 1, rotation_deg=4.0, n=n)
    aligner = Aligner(target.points, target.normals)
    back, _, _ = aligner.align(moved.points)
    assert np.median(np.linalg.norm(back - truth, axis=1)) < 0.25 * aligner.spacing


def test_the_start_with_the_smallest_residual_goes_on(monkeypatch):
    """Registration runs each start through the coarsest level and continues from the one whose residual is then
    the smallest (the first of equals): with the residual of the third start made the smallest, the transform is
    the finer levels' continuation of that start's coarse registration, to the bit; with all equal, the first's."""
    import inspection.align as align

    target = _corner("target", "train", 0, n=6000)
    moved = _corner("placed", "test", 1, rotation_deg=4.0, n=1500).points.astype(np.float64)
    aligner = align.Aligner(target.points, target.normals)
    aligner.transform(moved)  # builds the tree
    centre = moved.mean(0)

    def continued(k):
        R, t = aligner._icp(moved, centre, align._starts()[k], np.zeros(3), aligner.levels[:1], align.START_ITERATIONS)
        R, t = aligner._icp(moved, centre, R, t, aligner.levels[1:])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, centre + t - R @ centre
        return T

    calls = []

    def ranked(points):  # the third start's coarse result scores lowest
        calls.append(len(calls))
        return 0.0 if len(calls) == 3 else 1.0

    monkeypatch.setattr(aligner, "_residual", ranked)
    np.testing.assert_array_equal(aligner.transform(moved), continued(2))
    assert len(calls) == len(align._starts())
    monkeypatch.setattr(aligner, "_residual", lambda points: 1.0)
    np.testing.assert_array_equal(aligner.transform(moved), continued(0))


def test_the_starts_are_the_placement_and_small_turns_about_each_axis():
    from scipy.spatial.transform import Rotation

    from inspection.align import START_DEGREES, _starts

    starts = _starts()
    np.testing.assert_array_equal(starts[0], np.eye(3))
    angles = [np.degrees(Rotation.from_matrix(R).magnitude()) for R in starts[1:]]
    np.testing.assert_allclose(angles, START_DEGREES)
    axes = {tuple(np.round(Rotation.from_matrix(R).as_rotvec() / np.radians(START_DEGREES), 9)) for R in starts[1:]}
    assert axes == {tuple(s * np.eye(3)[i]) for i in range(3) for s in (1.0, -1.0)}


def test_fit_pose_moves_scans_placed_by_hand_into_one_pose_and_leaves_a_fixture():
    """fit_pose decides by the rule inspection's align='auto' uses (pose_spread above AUTO_RATIO): a fixture's scans
    get no frame, scans placed by hand a rigid one whose target is the group in one pose; pose=True always makes
    one, pose=False never."""
    from autodecoder.latent.family import fit_pose, pose_decision
    from inspection.align import pose_spread

    fixture = [_corner(f"train/good/{i:03d}", "train", i, n=500) for i in range(6)]
    by_hand = [_corner(f"train/good/{i:03d}", "train", i, rotation_deg=4.0, n=500) for i in range(6)]
    frame, spread = fit_pose(fixture)
    assert frame is None and abs(spread - 1) < 0.02 and pose_decision(fixture) == (spread, False)
    frame, spread = fit_pose(by_hand)
    assert spread > 1.5 and pose_decision(by_hand) == (spread, True)
    assert frame.kind == "pose" and frame.aligner.motion == "rigid"
    normalised = [frame.normalise(s) for s in by_hand]  # each training scan onto the others
    assert abs(pose_spread(normalised) - 1) < 0.05
    assert fit_pose(fixture, pose=True)[0].kind == "pose"
    assert fit_pose(by_hand, pose=False) == (None, None)
    with pytest.raises(ValueError, match="pose must be"):
        fit_pose(by_hand, pose="sometimes")


_TINY_TRAINING = dict(quiet=True, epochs=3, seed=0, latent_dim=2, width=16, depth=1, features=8, mean_samples=64,
                      screen_samples=32, pair_clusters=4, batch=3)


def _corner_tree(root, degrees):
    """``root/tree.h5``: 6 training and 3 held-back corners, each turned by ``degrees`` (0: a fixture). Returns
    (root, scans)."""
    from datasets import ScanCollection

    scans = ([_corner(f"train/good/{i:03d}", "train", i, rotation_deg=degrees, n=500) for i in range(6)]
             + [_corner(f"validation/good/{i:03d}", "validation", 10 + i, rotation_deg=degrees, n=500)
                for i in range(3)])
    root.mkdir(parents=True, exist_ok=True)
    ScanCollection.create(root / "tree.h5", scans)
    return root, scans


@pytest.fixture(scope="module")
def trained_in_one_pose(tmp_path_factory, one_torch_thread):
    """A tiny latent model trained (pose='auto', the default) on corners placed by hand: trained in one common pose.
    Returns (folder with tree.h5 and model.pt, the scans, the trained model)."""
    from autodecoder.latent.train import train_collection

    root, scans = _corner_tree(tmp_path_factory.mktemp("by_hand"), 4.0)
    return root, scans, train_collection(root / "tree.h5", root / "model.pt", **_TINY_TRAINING)


def test_training_on_scans_placed_by_hand_moves_them_into_one_pose(trained_in_one_pose, tmp_path, one_torch_thread):
    """train_collection's default pose='auto' trains a model of corners placed by hand in one common pose: stored
    in the checkpoint, every scan normalised onto it, so that inspection's align='auto' then finds nothing left to
    register and says why in one line; a fixture, or pose=False, trains without one."""
    import shutil

    from autodecoder.latent.model import load_model
    from autodecoder.latent.train import train_collection
    from inspection.align import pose_spread
    from inspection.job import calibrate, describe_calibration
    from inspection.run import score

    by_hand, scans, model = trained_in_one_pose
    fixture, _ = _corner_tree(tmp_path / "fixture", 0.0)
    assert model.family is not None and model.family.kind == "pose"
    # where the training's time went (the training suite's stages): both decisions, reading, targets, epochs
    assert set(model.info["decision_seconds"]) == {"family", "pose"}
    assert all(model.info[k] > 0 for k in ("read_seconds", "targets_seconds", "train_seconds"))
    assert all(v > 0 for v in model.info["decision_seconds"].values())
    loaded = load_model(by_hand / "model.pt")
    assert loaded.family.kind == "pose"
    new = _corner("test/good/x", "test", 30, rotation_deg=4.0, n=500)
    np.testing.assert_allclose(loaded.normalise(new).points, model.normalise(new).points)
    assert abs(pose_spread([loaded.normalise(s) for s in scans[:6]]) - 1) < 0.05
    copy = tmp_path / "model.pt"  # calibrated here: the module's model stays as trained
    shutil.copyfile(by_hand / "model.pt", copy)
    insp, info = calibrate(copy, by_hand / "tree.h5", progress=False)
    assert insp.settings_.align is False  # nothing left to register after the common pose
    assert sum("one common pose" in line for line in describe_calibration(insp, info)) == 1
    summary = score(copy, by_hand / "tree.h5", tmp_path / "out", split="validation", maps="none",
                    echo=lambda line: None)
    assert summary["common_frame"] == "pose" and summary["aligned"] is False
    assert train_collection(fixture / "tree.h5", fixture / "model.pt", **_TINY_TRAINING).family is None
    assert train_collection(by_hand / "tree.h5", tmp_path / "off.pt", pose=False, **_TINY_TRAINING).family is None


def _scores_csv(folder):
    import csv

    with open(folder / "scores.csv", newline="") as fh:
        return {r["name"]: (r["score"], r["verdict"]) for r in csv.DictReader(fh)}


def test_score_align_means_registered_and_a_model_that_registers_by_itself_accepts_it(
        trained_in_one_pose, placed_by_hand, tmp_path, capsys, one_torch_thread):
    """`--align` asks that every scan be registered before it is scored. A model trained in one common pose
    registers every scan by itself (its calibration says so, and registers nothing more): `score --align` on it is
    accepted with one line saying --align is not needed, and scores exactly as `score` without it. Only a model whose
    calibration registers nothing refuses it, with the command that calibrates it with registration."""
    import shutil

    from inspection.__main__ import main

    by_hand = trained_in_one_pose[0]
    model = tmp_path / "model.pt"
    shutil.copyfile(by_hand / "model.pt", model)
    tree = str(by_hand / "tree.h5")
    assert main(["calibrate", "--model", str(model), "--data", tree, "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "every scan is registered onto it before it is scored" in said and "--align" not in said
    common = ["score", "--model", str(model), "--data", tree, "--split", "validation", "--maps", "none", "--quiet"]
    assert main(common + ["--out", str(tmp_path / "aligned"), "--align"]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "--align" in line]
    assert notes == [f"note: --align is not needed for {model}: it was trained on scans moved into one common pose, "
                     f"and registers every scan onto that pose before scoring it"]
    assert main(common + ["--out", str(tmp_path / "plain")]) == 0
    assert not [line for line in capsys.readouterr().out.splitlines() if "--align" in line]
    assert _scores_csv(tmp_path / "aligned") == _scores_csv(tmp_path / "plain")  # the same scores and verdicts
    summary = json.loads((tmp_path / "aligned" / "summary.json").read_text())
    assert summary["common_frame"] == "pose" and summary["aligned"] is False  # the calibration's own align

    # a model (a fixed field, no common frame) calibrated without registration: --align is refused, one line
    root, _ = placed_by_hand
    plain = tmp_path / "plain.pt"
    shutil.copyfile(root / "model.pt", plain)
    assert main(["calibrate", "--model", str(plain), "--data", str(root / "tree.h5"), "--no-align", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["score", "--model", str(plain), "--data", str(root / "tree.h5"), "--out", str(tmp_path / "refused"),
                 "--maps", "none", "--align", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: {plain}: --align, but the model was calibrated without it: its threshold was drawn from "
                   f"scans scored where they lay, not registered ones; calibrate it again with `python -m inspection "
                   f"calibrate --model {plain} --data TRAINING_COLLECTION --align` (scoring then registers every scan "
                   f"by itself)")
    assert not (tmp_path / "refused").exists()
