"""Fold models (autodecoder.latent.folds): the split, training them into the checkpoint, and the guarantee that a fold
model never scores a scan it trained on."""
import pytest
import torch

from datasets.collection import ScanCollection
from tests.latent.spheres import sphere_scan

TINY = dict(latent_dim=2, width=16, depth=1, features=8, mean_samples=128, screen_samples=64, pair_clusters=4,
            batch=4, epochs=3)


def test_assign_folds_deals_every_scan_once_and_every_part_evenly():
    from autodecoder.latent.folds import assign_folds

    names = [f"a/{i}" for i in range(7)] + [f"b/{i}" for i in range(5)]
    parts = ["a"] * 7 + ["b"] * 5
    folds = assign_folds(names, parts, k=3, seed=4)
    assert len(folds) == 3
    flat = [n for f in folds for n in f]
    assert sorted(flat) == sorted(names)  # each name exactly once
    for part, total in (("a", 7), ("b", 5)):
        counts = [sum(n.startswith(part) for n in f) for f in folds]
        assert max(counts) - min(counts) <= 1 and sum(counts) == total
    assert folds == assign_folds(names, parts, k=3, seed=4)  # seeded
    assert folds != assign_folds(names, parts, k=3, seed=5)
    for fold in folds:  # in the training order
        assert fold == sorted(fold, key=names.index)


def test_assign_folds_refuses_what_cannot_be_split():
    from autodecoder.latent.folds import assign_folds

    with pytest.raises(ValueError, match="k must be >= 2"):
        assign_folds(["a", "b"], k=1)
    with pytest.raises(ValueError, match="3 training scans of part 'x' cannot be split into 4 folds"):
        assign_folds(["a", "b", "c", "d", "e"], ["x", "x", "x", "y", "y"], k=4)


@pytest.fixture(scope="module")
def folded_model(tmp_path_factory, one_torch_thread):
    from autodecoder.latent.folds import train_collection_with_folds as train_collection

    tmp = tmp_path_factory.mktemp("folds")
    scans = [sphere_scan(f"train/{i:03d}", 0.2 + 0.02 * (i % 3), n=200, seed=i) for i in range(7)]
    data = ScanCollection.create(tmp / "c.h5", scans)
    path = tmp / "model.pt"
    model = train_collection(data, path, calibration_fraction=0.3, quiet=True, calibration_folds=2, fold_jobs=2,
                             **TINY)
    return data, path, model


def test_fold_models_never_train_on_the_scans_they_score(folded_model):
    from autodecoder.latent.folds import FOLD_RULE, FOLDS_KEY
    from autodecoder.latent.model import load_model, read_checkpoint

    data, path, model = folded_model
    assert len(model.train_names) == 5 and len(model.calibration_names) == 2
    folds = load_model(path).calibration_folds  # recorded in the model file
    assert len(folds) == 2 and len(read_checkpoint(path)[FOLDS_KEY]) == 2
    scored = [n for f in folds for n in f.scored_names]
    assert sorted(scored) == sorted(model.train_names)  # every training scan scored once
    for fold in folds:
        assert not set(fold.scored_names) & set(fold.model.train_names)
        # the training scans outside its fold and the held-back scans (scored by the main model alone)
        assert sorted(fold.model.train_names) == sorted(set(model.train_names) - set(fold.scored_names)
                                                        | set(model.calibration_names))
        assert fold.rule == FOLD_RULE
        # the main model's settings: same kernel, same epochs, same nets
        for key in ("lengthscale", "epochs", "width", "depth", "latent_dim"):
            assert fold.model.config[key] == model.config[key]
        assert "resume" not in fold.model.state  # no optimiser state: a fold model is used, not trained on


def test_fold_models_trained_in_processes_equal_those_trained_here(folded_model, tmp_path):
    """Worker processes (fold_jobs=2) and this process (jobs=1) train the same fold models, bit for bit."""
    from autodecoder.latent.folds import train_folds
    from autodecoder.latent.model import read_checkpoint

    data, path, _ = folded_model
    state = read_checkpoint(path)
    here = train_folds(state, data, k=2, jobs=1)
    for mine, theirs in zip(here, state["calibration_folds"]):
        assert mine["scored_names"] == theirs["scored_names"]
        for key in ("mean_state", "cov_state"):
            for name, value in mine["checkpoint"][key].items():
                torch.testing.assert_close(value, theirs["checkpoint"][key][name], rtol=0, atol=0)
        torch.testing.assert_close(mine["checkpoint"]["codes"], theirs["checkpoint"]["codes"], rtol=0, atol=0)


def test_a_fold_that_trained_on_a_scan_it_scores_is_refused(folded_model, tmp_path):
    from autodecoder.latent.model import load_model, read_checkpoint, save_checkpoint

    _, path, _ = folded_model
    state = read_checkpoint(path)
    fold = state["calibration_folds"][0]
    fold["scored_names"] = fold["scored_names"] + [fold["checkpoint"]["train_names"][0]]
    save_checkpoint(state, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=r"bad\.pt: calibration fold 1: trained on 1 of the scans it scores"):
        load_model(tmp_path / "bad.pt").calibration_folds
    state = read_checkpoint(path)
    state["calibration_folds"][1]["scored_names"] = ["not/a/training/scan"]
    save_checkpoint(state, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="scores 'not/a/training/scan', which is not one of the model's training"):
        load_model(tmp_path / "foreign.pt").calibration_folds
    state = read_checkpoint(path)
    state["calibration_folds"][0]["checkpoint"]["train_names"][0] = "some/other/scan"
    save_checkpoint(state, tmp_path / "stranger.pt")
    with pytest.raises(ValueError, match="trained on 'some/other/scan', which is neither a training nor a held-back"):
        load_model(tmp_path / "stranger.pt").calibration_folds


def test_folds_of_another_collection_are_refused(folded_model, tmp_path):
    from autodecoder.latent.folds import add_folds

    _, path, _ = folded_model
    other = ScanCollection.create(tmp_path / "other.h5", [sphere_scan(f"x/{i}", 0.3, n=100, seed=i) for i in range(4)])
    copy = tmp_path / "m.pt"
    copy.write_bytes(path.read_bytes())
    with pytest.raises(ValueError, match=r"other\.h5: not the collection the model was trained on"):
        add_folds(copy, other, 2)
    assert copy.read_bytes() == path.read_bytes()  # untouched


def test_training_refuses_folds_it_cannot_make_before_training(tmp_path):
    from autodecoder.latent.options import TrainingInputError
    from autodecoder.latent.folds import train_collection_with_folds as train_collection

    data = ScanCollection.create(tmp_path / "c.h5", [sphere_scan(f"t/{i}", 0.2, n=100, seed=i) for i in range(3)])
    with pytest.raises(TrainingInputError, match=r"c\.h5: calibration folds: 2 training scans cannot be split "
                                                 r"into 3 folds"):
        train_collection(data, tmp_path / "m.pt", calibration_fraction=0.34, quiet=True, calibration_folds=3, **TINY)
    assert not (tmp_path / "m.pt").exists()


def test_by_default_few_training_scans_get_one_fold_model_each_and_more_get_none(tmp_path):
    """The default (no number asked for): leave-one-out fold models with 2 to FEW_SCANS training scans of each part,
    none with more; asked for 0, none either way."""
    from autodecoder.latent.folds import DEFAULT_FOLDS, FEW_SCANS, FOLDS_KEY, default_folds
    from autodecoder.latent.model import read_checkpoint
    from autodecoder.latent.folds import train_collection_with_folds as train_collection

    assert DEFAULT_FOLDS == 0 and FEW_SCANS == 8
    assert [default_folds(n) for n in (1, 2, 8, 9, 32)] == [0, 2, 8, 0, 0]
    assert default_folds([3, 5]) == 3 and default_folds([3, 9]) == 0  # every part few, else none
    data = ScanCollection.create(tmp_path / "c.h5", [sphere_scan(f"t/{i}", 0.2, n=100, seed=i) for i in range(4)])
    model = train_collection(data, tmp_path / "m.pt", calibration_fraction=0.25, quiet=True, fold_jobs=1, **TINY)
    folds = model.calibration_folds  # 3 training scans: each scored by a model that never saw it
    assert len(folds) == 3 and sorted(n for f in folds for n in f.scored_names) == sorted(model.train_names)
    none = train_collection(data, tmp_path / "n.pt", calibration_fraction=0.25, quiet=True, calibration_folds=0,
                            **TINY)
    assert none.calibration_folds == [] and FOLDS_KEY not in read_checkpoint(tmp_path / "n.pt")


def test_a_failing_fold_process_is_one_clear_error(tmp_path):
    from autodecoder.latent.folds import _train_in_processes
    from autodecoder.latent.options import LatentOptions

    with pytest.raises(RuntimeError, match=r"calibration fold 1: its training process failed: .*missing\.h5"):
        _train_in_processes(tmp_path / "missing.h5", [["a"], ["b"]], LatentOptions(**TINY), None, 2, None)
