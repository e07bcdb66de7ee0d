"""Several part types in one latent model: the training budget follows the part types, the held-back scans are drawn
per part, and a scan of known part starts its projection from that part's training codes only."""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from datasets.scan import Scan

TINY = dict(latent_dim=2, width=16, depth=1, features=8, mean_samples=128, screen_samples=64, pair_clusters=4,
            batch=2)


def _sphere(name, radius, part, n=300, seed=0, split="train", label="good"):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return Scan(points=(radius * v).astype(np.float32), normals=v.astype(np.float32), name=name, split=split,
                label=label, part_id=part)


def _two_part_scans(per_part=4):
    return [_sphere(f"{p}/train/{k:03d}", r + 0.02 * k, p, seed=10 * i + k)
            for i, (p, r) in enumerate((("a", 0.15), ("b", 0.3))) for k in range(per_part)]


def test_default_epochs_give_each_part_type_the_single_part_budget():
    from autodecoder.latent.options import DEFAULT_EPOCHS, MAX_DEFAULT_STEPS, MIN_DEFAULT_EPOCHS, default_epochs

    for n in (3, 26, 100, 10_000):  # one part type: the single-part rule unchanged
        assert default_epochs(n, 8, n_parts=1) == default_epochs(n, 8)
    # k parts of n scans each: every code as many updates as in its part alone
    for n in (26, 64, 200, 400, 4000, 40_000):
        for k in (2, 3):
            assert default_epochs(k * n, 8, n_parts=k) == default_epochs(n, 8)
    assert default_epochs(52, 8, n_parts=2) == DEFAULT_EPOCHS  # two parts of 26: 450 epochs of 7 steps
    # the step cap is per part type: 2,000 scans of two parts get the epochs of 1,000 scans of one
    assert default_epochs(2000, 8, n_parts=2) == MAX_DEFAULT_STEPS // 125 < DEFAULT_EPOCHS
    assert default_epochs(200_000, 8, n_parts=2) == MIN_DEFAULT_EPOCHS
    assert default_epochs(800, 8, world=2, n_parts=2) == default_epochs(400, 8, world=2)  # 400 scans a process
    with pytest.raises(ValueError, match="n_parts"):
        default_epochs(10, 8, n_parts=0)


def test_count_parts():
    from autodecoder.latent.options import count_parts

    assert count_parts(["a", "b", "a"]) == 2
    assert count_parts(["", "", ""]) == 1 and count_parts([]) == 1
    assert count_parts(["a", ""]) == 2


def test_held_back_scans_are_drawn_per_part_as_in_each_part_alone(tmp_path):
    from autodecoder.latent.collection_split import split_training_scans
    from datasets.collection import ScanCollection

    a = [_sphere(f"a/{k:03d}", 0.2, "a", n=20, seed=k) for k in range(10)]
    b = [_sphere(f"b/{k:03d}", 0.3, "b", n=20, seed=k) for k in range(15)]
    ScanCollection.create(tmp_path / "ab.h5", a + b)
    ScanCollection.create(tmp_path / "a.h5", a)
    ScanCollection.create(tmp_path / "b.h5", b)
    with ScanCollection(tmp_path / "ab.h5") as c:
        train, held = split_training_scans(c, calibration_fraction=0.2, seed=3)
        names = c.names
    expect_held, expect_train = [], []
    for part in ("a", "b"):
        with ScanCollection(tmp_path / f"{part}.h5") as c:
            t, h = split_training_scans(c, calibration_fraction=0.2, seed=3)
            expect_held += h
            expect_train += [c.names[i] for i in t]
    assert sorted(held) == sorted(expect_held) and len(held) == 2 + 3
    assert sorted(names[i] for i in train) == sorted(expect_train)


@pytest.fixture(scope="module")
def two_part_model(one_torch_thread):
    from autodecoder.latent.train import train_latent

    return train_latent(_two_part_scans(), options=None, epochs=3, seed=0, quiet=True, **TINY)


def test_training_records_part_ids_and_budgets_by_part(one_torch_thread):
    from autodecoder.latent.options import default_epochs
    from autodecoder.latent.train import train_latent

    model = train_latent(_two_part_scans(), quiet=True, stop_after=1, **TINY)
    assert model.train_part_ids == ["a"] * 4 + ["b"] * 4
    assert model.config["epochs"] == default_epochs(8, TINY["batch"], n_parts=2) and model.epoch == 1


def test_part_codes_restrict_the_candidate_starts(two_part_model):
    from autodecoder.latent.projection import _candidates, part_codes

    index, mean = part_codes(two_part_model, "b")
    assert index.tolist() == [4, 5, 6, 7]
    torch.testing.assert_close(mean, two_part_model.codes[4:].mean(0))
    cand, cand_index = _candidates(two_part_model, 64, exclude=(5,), part_id="b")
    assert cand_index.tolist() == [-1, 4, 6, 7]
    torch.testing.assert_close(cand[0], mean)
    every, _ = part_codes(two_part_model, None)
    assert every.tolist() == list(range(8))
    with pytest.raises(ValueError, match=r"part_id 'c'.*\['a', 'b'\]"):
        part_codes(two_part_model, "c")


def test_a_model_without_part_ids_ignores_the_part_id():
    from autodecoder.latent.projection import part_codes

    model = SimpleNamespace(codes=torch.zeros(3, 2), code_mean=torch.ones(2), train_part_ids=["", "", ""])
    index, mean = part_codes(model, "anything")
    assert index.tolist() == [0, 1, 2] and torch.equal(mean, model.code_mean)


def test_projection_starts_from_the_scans_part(two_part_model):
    scans = [_sphere("a/test", 0.17, "a", seed=99), _sphere("b/test", 0.31, "b", seed=98),
             _sphere("a/test2", 0.16, "a", seed=97)]
    out = two_part_model.project_many(scans, steps=5, starts=2, explore=2)
    assert out[0].start in (-1, 0, 1, 2, 3) and out[2].start in (-1, 0, 1, 2, 3)
    assert out[1].start in (-1, 4, 5, 6, 7)
    forced = two_part_model.project_many(scans[:1], steps=5, starts=2, explore=2, part_id="b")
    assert forced[0].start in (-1, 4, 5, 6, 7)  # the option wins over the scan's own part id
    alone = two_part_model.project_many([scans[0], scans[2]], steps=5, starts=2, explore=2)
    for got, want in zip(alone, (out[0], out[2])):  # part a's scans: one batch, as if projected without part b's
        torch.testing.assert_close(got.code, want.code)
    with pytest.raises(ValueError, match="part_id 'z'"):
        two_part_model.project_many([_sphere("z/test", 0.2, "z")], steps=2)
    with pytest.raises(ValueError, match="part_id 'z'"):
        two_part_model.project(scans[0].points, scans[0].normals, steps=2, part_id="z")
