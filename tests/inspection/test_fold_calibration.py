"""Calibration with fold models (issue 27): every training scan is scored by the fold model that never trained on
it, against that fold model's own reference, and those scores set the threshold's level with the held-back ones."""
import numpy as np
import pytest

from datasets import ScanCollection
from tests.inspection.tiny import half_sphere

TINY = dict(latent_dim=2, width=16, depth=1, features=8, mean_samples=128, screen_samples=64, pair_clusters=4,
            batch=4, epochs=3)


@pytest.fixture(scope="module")
def folded(tmp_path_factory, one_torch_thread):
    from autodecoder.latent.folds import train_collection_with_folds as train_collection

    tmp = tmp_path_factory.mktemp("foldcal")
    scans = [half_sphere(f"train/{i:03d}", seed=i, n=200) for i in range(9)]
    data = ScanCollection.create(tmp / "c.h5", scans)
    model = train_collection(data, tmp / "model.pt", calibration_fraction=0.34, quiet=True, calibration_folds=3,
                             fold_jobs=1, **TINY)
    return data, model


def test_each_training_scan_is_scored_by_the_fold_model_that_never_saw_it(folded, monkeypatch):
    import inspection.scoring as scoring
    from inspection import Inspector

    data, model = folded
    seen = []
    real = scoring.gather_evidence

    def recording(m, scan, *args, **kwargs):
        seen.append((m, scan.name, kwargs.get("exclude_own_code", False)))
        return real(m, scan, *args, **kwargs)

    monkeypatch.setattr(scoring, "gather_evidence", recording)
    with ScanCollection(data) as c:
        insp = Inspector(model, projection={"steps": 5, "starts": 1}).fit(c)
    folds = model.calibration_folds
    roles = dict(zip(insp.calibration_names_, insp.calibration_roles_))
    assert sorted(n for n, r in roles.items() if r == "held-back") == sorted(model.calibration_names)
    assert sorted(n for n, r in roles.items() if r == "fold") == sorted(model.train_names)
    assert "fold models that never saw them" in insp.calibration_source_
    assert insp.decision_threshold_.n == len(model.train_names) + len(model.calibration_names)
    assert "out-of-sample scores (3 held-back, 6 by fold models)" in insp.decision_threshold_.note
    for m, name, exclude in seen:
        trained = set(m.train_names)
        if name in trained:  # a model projects a scan it trained on only for its reference, never from its own code
            assert exclude
    for fold in folds:
        # each fold model projected every training scan of the main model: those it scores, and the others for its
        # reference; the held-back scans it trained on are the main model's to score
        projected = {name for m, name, _ in seen if m is fold.model}
        assert projected == set(model.train_names)
        assert set(model.calibration_names) <= set(fold.model.train_names)
    # the main model never scored a training scan for the calibration: only for its reference (exclude_own_code)
    assert all(exclude for m, name, exclude in seen if m is model and name in model.train_names)


def test_without_fold_models_the_training_scans_are_cross_fitted(folded, tmp_path):
    from autodecoder.latent.folds import FOLDS_KEY
    from autodecoder.latent.model import LatentModel
    from inspection import Inspector

    data, model = folded
    state = {k: v for k, v in model.state.items() if k != FOLDS_KEY}
    bare = LatentModel(state, "bare")
    with ScanCollection(data) as c:
        insp = Inspector(bare, projection={"steps": 5, "starts": 1}).fit(c)
    assert insp.calibration_roles_.count("cross-fitted") == len(model.train_names)
    assert "cross-fitted" in insp.calibration_source_
    assert np.isfinite(insp.threshold_)


def test_a_fold_scored_scan_is_compared_with_a_reference_without_its_points(folded):
    from inspection.calibrating import fold_evidence
    from inspection.config import InspectionConfig
    from inspection.selection import select_scans

    data, model = folded
    with ScanCollection(data) as c:
        goods = c.read_many(c.select(label="good"))
    config = InspectionConfig(projection={"steps": 5, "starts": 1}).validated()
    settings = config.decided(model, True, False)  # no sensor origins here: no rays
    selection = select_scans(model, goods)
    evidence, references = fold_evidence(model, selection, settings)
    assert sorted(e.name for e in evidence) == sorted(model.train_names)
    by_name = {s.name: s for s in goods}
    for e, reference in zip(evidence, references):
        own = {tuple(p) for p in np.asarray(by_name[e.name].points, dtype=np.float32)}
        assert not own & {tuple(p) for p in reference.surface_points}  # its own points left out of the surface
        others = {tuple(p) for s in goods if s.name in model.train_names and s.name != e.name
                  for p in np.asarray(s.points, dtype=np.float32)}
        assert {tuple(p) for p in reference.surface_points} <= others  # every other training scan's


def test_a_left_out_training_scan_marks_only_the_surface_no_other_scan_saw():
    """inspection.calibrating.uncovered_points against brute force: held-back scans on a square set the reach (the 99 %
    quantile of their points' distance to every training scan's points); a training scan that alone saw a flap
    beyond the square, left out, marks exactly its points farther than that from the other scans' points; there the
    joint score is the field's term alone (sqrt((z_d^2 + z_d^2) / 2) = z_d at equal term variances), elsewhere it is as
    before."""
    from types import SimpleNamespace

    from inspection.calibrating import uncovered_points
    from inspection.reference import LocalReference
    from inspection.scores import reference_scores

    rng = np.random.default_rng(2)
    g = np.arange(0.0, 1.0 + 1e-9, 0.05)
    square = np.c_[np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), np.zeros(len(g) ** 2)]
    flap = square[square[:, 0] <= 0.5] + [1.05, 0.0, 0.0]  # x in [1.05, 1.55]: seen by scan 0 alone ...
    flap[:, 2] = 0.5 * (flap[:, 0] - 1.0)  # ... bent up out of the square's plane
    scans = [np.r_[square[::2], flap], square[1::2], square + [0.0, 0.0, 0.001]]
    points = np.concatenate(scans)
    owners = np.concatenate([np.full(len(p), i) for i, p in enumerate(scans)])
    reference = LocalReference(points, np.zeros(len(points)), owners=owners, surface_points=points,
                               surface_owners=owners)
    held = [SimpleNamespace(points=square + rng.normal(0, 0.01, square.shape), stray=None) for _ in range(3)]
    crossed = [SimpleNamespace(points=p, stray=None) for p in scans]
    masks = uncovered_points(held, reference, crossed, [reference.without(j) for j in range(3)])
    held_d = np.sqrt(((np.concatenate([h.points for h in held])[:, None] - points[None]) ** 2).sum(-1)).min(1)
    reach = np.quantile(held_d, 0.99)
    for j, (p, mask) in enumerate(zip(scans, masks)):
        others = points[owners != j]
        brute = np.sqrt(((p[:, None] - others[None]) ** 2).sum(-1)).min(1) > reach
        np.testing.assert_array_equal(mask, brute)
    assert masks[0].sum() >= len(flap) - 21 and not masks[1].any() and not masks[2].any()
    left_out = reference.without(0)
    p = scans[0]
    value, variance = rng.normal(0, 0.02, len(p)), np.full(len(p), 1e-4)
    plain = reference_scores(left_out, "joint", p, value, variance, 0.01)
    masked = reference_scores(left_out, "joint", p, value, variance, 0.01, uncovered=masks[0])
    field_term = left_out.standardized(p, value, variance, 0.01)
    np.testing.assert_allclose(masked[masks[0]], field_term[masks[0]])
    np.testing.assert_allclose(masked[~masks[0]], plain[~masks[0]])
    assert (plain[masks[0]] > masked[masks[0]]).mean() > 0.9  # the flap read as far off the other scans' surface


def test_a_scan_whose_face_of_a_thin_wall_no_good_scan_saw_takes_the_field_term_there():
    """A wall 0.02 thick: scan 0 alone saw its top face, scans 1 and 2 its bottom face. Left out, scan 0's points
    have only the bottom face's points near them, normals opposite, a wall's thickness away (nearer than the
    held-back scans' reach, so the distance rule of uncovered_points keeps them): the good points' plane would come from
    the other face, so the joint score's good-points term is the field's term there
    (inspection.scores.reference_terms); scans 1 and 2, left out, still have the other's points on their side and
    keep the good points' term. A new scan of the top face against a reference of bottom-face scans alone is judged
    the same way; without normals no side can be told and the good points' term stays."""
    from types import SimpleNamespace

    from inspection.calibrating import uncovered_points
    from inspection.calibration import migrate
    from inspection.reference import LocalReference
    from inspection.scores import reference_terms

    rng = np.random.default_rng(4)
    g = np.arange(0.0, 1.0 + 1e-9, 0.04)
    plane = np.c_[np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), np.zeros(len(g) ** 2)]
    top, bottom = plane + [0.0, 0.0, 0.01], plane - [0.0, 0.0, 0.01]
    up = np.tile([0.0, 0.0, 1.0], (len(plane), 1))
    scans = [(top, up), (bottom[::2], -up[::2]), (bottom[1::2], -up[1::2])]
    points = np.concatenate([p for p, _ in scans])
    normals = np.concatenate([n for _, n in scans])
    owners = np.concatenate([np.full(len(p), i) for i, (p, _) in enumerate(scans)])
    reference = LocalReference(points, np.zeros(len(points)), owners=owners, surface_points=points,
                               surface_owners=owners, surface_normals=normals)
    # held-back scans of the bottom face, noisy enough that the reach (99 % of their distances) exceeds the wall
    held = [SimpleNamespace(points=bottom + rng.normal(0, 0.03, bottom.shape), stray=None) for _ in range(2)]
    reach = np.quantile(np.concatenate([reference.surface_distance(h.points) for h in held]), 0.99)
    assert reach > 0.03
    crossed = [SimpleNamespace(points=p, normals=n, stray=None) for p, n in scans]
    # the distance rule marks none of them: the wall is thinner than the reach
    assert not any(m.any() for m in uncovered_points(held, reference, crossed, [reference.without(j) for j in range(3)]))

    def terms(ref, p, n):
        value, variance = rng.normal(0, 0.004, len(p)), np.full(len(p), 1e-6)
        return reference_terms(ref, p, value, variance, 0.002, normals=n)

    z_d, z_s = terms(reference.without(0), top, up)
    np.testing.assert_array_equal(z_s, z_d)  # no good point on its side: the field's term
    plane_term = reference.without(0).surface_scores(top, 0.002)  # the plane through the other face, no sides
    assert np.median(plane_term) > 3 > np.median(z_d)  # a wall's thickness off: as far as a defect
    for j in (1, 2):
        p, n = scans[j]
        z_d, z_s = terms(reference.without(j), p, n)
        np.testing.assert_allclose(z_s, reference.without(j).surface_scores(p, 0.002, normals=n))
        assert not np.array_equal(z_s, z_d)
    bottom_only = LocalReference(points[owners > 0], np.zeros(int((owners > 0).sum())),
                                 surface_points=points[owners > 0], surface_normals=normals[owners > 0])
    new_top = top + rng.normal(0, 0.002, top.shape)
    z_d, z_s = terms(bottom_only, new_top, up)
    np.testing.assert_array_equal(z_s, z_d)
    z_d, z_s = terms(bottom_only, new_top, None)
    np.testing.assert_allclose(z_s, bottom_only.surface_scores(new_top, 0.002))
    # stored and restored, the rule goes with the reference; a reference stored before it keeps the good points'
    # term on the unseen face, as it was calibrated
    restored = LocalReference.from_dict(bottom_only.as_dict())
    assert restored.field_on_unseen_faces
    z_d, z_s = terms(restored, new_top, up)
    np.testing.assert_array_equal(z_s, z_d)
    record = bottom_only.as_dict()
    del record["field_on_unseen_faces"]  # a version-1 calibration record's reference, upgraded as it is read
    older = LocalReference.from_dict(migrate({"version": 1, "scores": [1.0], "names": ["a"], "aggregate": "top1",
                                              "point_score": "joint", "extra": {"reference": record}})
                                     ["extra"]["reference"])
    assert not older.field_on_unseen_faces
    z_d, z_s = terms(older, new_top, up)
    np.testing.assert_allclose(z_s, older.surface_scores(new_top, 0.002, normals=up))
    assert np.median(z_s) > 3 > np.median(z_d)
    old_with_owners = LocalReference(points, np.zeros(len(points)), owners=owners, surface_points=points,
                                     surface_owners=owners, surface_normals=normals, field_on_unseen_faces=False)
    assert reference.without(0).field_on_unseen_faces and not old_with_owners.without(0).field_on_unseen_faces
