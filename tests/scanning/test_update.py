"""Fine-tuning a field on new data (update), its persistence, and the next-view command line in-process."""
import json

import numpy as np
import pytest
import torch

from autodecoder import StochasticField, fit_cloud, update_field
from autodecoder.__main__ import main

TINY = dict(quiet=True, width=32, depth=2, features=16, mean_batch=512, screen_batch=256, pair_clusters=16)


def half_sphere(n, sign, seed):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 0] = sign * np.abs(d[:, 0])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, d.copy()


@pytest.fixture(scope="module")
def fields():
    old_p, old_n = half_sphere(400, +1, 0)
    field = fit_cloud(old_p, old_n, representation="siren", seed=0, steps=150, **TINY)
    field.training_points, field.training_normals = torch.tensor(old_p).float(), torch.tensor(old_n).float()
    new_p, new_n = half_sphere(400, -1, 1)
    updated = update_field(field, new_p, new_n, steps=150, seed=0)
    return field, updated, (old_p, new_p)


def test_update_lowers_the_misfit_on_new_data_and_keeps_the_old_surface(fields):
    field, updated, (old_p, new_p) = fields
    before_new = np.abs(field.mean(new_p)).mean()
    after_new = np.abs(updated.mean(new_p)).mean()
    assert after_new < 0.7 * before_new
    assert np.abs(updated.mean(old_p)).mean() < max(2 * np.abs(field.mean(old_p)).mean(), 0.05)
    assert updated.training_points.shape == (800, 3)
    assert updated.frame == field.frame
    assert updated.info["updates"][-1]["n_new"] == 400
    assert field.training_points.shape == (400, 3)  # the old field is untouched
    assert "updates" not in field.info


def test_training_cloud_round_trips_and_old_files_load(fields, tmp_path):
    _, updated, _ = fields
    updated.save(tmp_path / "f.pt")
    back = StochasticField.load(tmp_path / "f.pt")
    assert torch.equal(back.training_points, updated.training_points)
    state = updated.state()
    del state["training_points"], state["training_normals"]  # a file written before they existed
    assert StochasticField.from_state(state).training_points is None


def with_recorded_option(field, name, recorded):
    """The field as if saved with FitOptions.``name`` = ``recorded``, or before that option existed ('missing')."""
    options = dict(field.info["options"])
    if recorded == "missing":
        del options[name]
    else:
        options[name] = recorded
    return StochasticField.from_state({**field.state(), "info": {**field.info, "options": options}})


@pytest.mark.parametrize("recorded, expected_cov_steps", [(8, 3), ("missing", 20)])
def test_update_keeps_the_fields_covariance_schedule(fields, adam_steps, recorded, expected_cov_steps):
    """update() fine-tunes with the options the field was fitted with; a field saved before covariance_every
    existed (no such key) keeps its covariance step with every mean step."""
    field, _, (_, new_p) = fields
    field = with_recorded_option(field, "covariance_every", recorded)
    update_field(field, new_p[:50], new_p[:50], steps=20, seed=0)
    assert len(adam_steps) - adam_steps.count(adam_steps[0]) == expected_cov_steps


@pytest.mark.parametrize("recorded, averaged", [(0.9, True), ("missing", False)])
def test_update_keeps_the_fields_weight_averaging(fields, monkeypatch, recorded, averaged):
    """A field saved before average_decay existed (no such key) keeps its last iterate when fine-tuned."""
    from autodecoder.field import fit as fit_module

    decays = []
    original = fit_module.MeanAverager.__init__

    def spy(self, net, decay, start):
        decays.append(decay)
        original(self, net, decay, start)

    monkeypatch.setattr(fit_module.MeanAverager, "__init__", spy)
    field, _, (_, new_p) = fields
    field = with_recorded_option(field, "average_decay", recorded)
    update_field(field, new_p[:50], new_p[:50], steps=4, seed=0)
    assert decays == ([0.9] if averaged else [0.0])


def test_update_without_a_training_cloud_says_what_to_pass(fields):
    field, _, _ = fields
    state = field.state()
    state["training_points"] = state["training_normals"] = None
    bare = StochasticField.from_state(state)
    with pytest.raises(ValueError, match="old_points"):
        update_field(bare, *half_sphere(10, -1, 2), steps=1)


def test_next_view_cli(fields, tmp_path, capsys):
    field, _, _ = fields
    field.save(tmp_path / "f.pt")
    out = tmp_path / "views.json"
    # a half sphere fitted with the paper's loss: an open sheet, which the command warns about (and still runs)
    with pytest.warns(UserWarning, match="outside_weight=100"):
        code = main(["next-view", "--field", str(tmp_path / "f.pt"), "--n", "2", "--out", str(out), "--starts",
                     "3", "--steps", "2", "--rays", "2", "--samples", "8"])
    assert code == 0
    views = json.loads(out.read_text())["views"]
    assert 1 <= len(views) <= 2 and {"position", "direction", "look_at", "score"} <= set(views[0])
    assert main(["next-view", "--field", str(tmp_path / "missing.pt")]) == 2
    assert "missing.pt" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["next-view", "--help"])
    assert exc.value.code == 0
