"""The latent model with grid nets (``representation="grid"``): training, projection, checkpoints, old checkpoints.

References: the spheres' known radii, the uncached projection path (the grids interpolated at every step), a
model rebuilt from its file, and a SIREN checkpoint rewritten in the version-1 format.
"""
import numpy as np
import pytest
import torch

from autodecoder.latent.model import LATENT_VERSION, load_model
from autodecoder.latent.options import LatentOptions
from autodecoder.latent.train import train_latent

from .spheres import RADII, sphere_scan, sphere_scans, zero_crossing_radius

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# small grids and batches: the file runs in well under a minute on 2 cores
GRID = dict(representation="grid", latent_dim=2, mean_samples=256, screen_samples=128, pair_clusters=8, batch=2,
            lr=3e-3, code_lr=1e-2, grid_mean={"finest": 16, "levels": 2, "channels": 4, "hidden": 32,
                                               "shared_cells": 24},
            grid_cov={"finest": 4, "levels": 2, "channels": 4, "hidden": 16, "features": 8})



@pytest.fixture(scope="module")
def trained(tmp_path_factory, one_torch_thread):
    out = tmp_path_factory.mktemp("grid_latent") / "model.pt"
    model = train_latent(sphere_scans(), out, epochs=100, seed=0, quiet=True, **GRID)
    return model, out


def test_grid_training_fits_each_scan_with_its_code(trained):
    model, _ = trained
    assert model.representation == "grid" and "grid" in repr(model)
    assert model.info["shared_solve"]["converged"] and model.info["shared_solve"]["points"] == 2000
    history = model.info["history"]
    assert np.mean([h["loss"] for h in history[-5:]]) < 0.5 * np.mean([h["loss"] for h in history[:5]])
    radii = [zero_crossing_radius(model.training_field(f"train/{i:03d}")) for i in range(len(RADII))]
    assert np.abs(np.array(radii) - RADII).max() < 0.02, radii
    # the variance is smallest on the scan's own surface
    field = model.training_field("train/001")
    d = np.random.default_rng(1).normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert np.median(field.variance(0.2 * d)) < np.median(field.variance(0.45 * d))


def test_grid_projection_recovers_an_unseen_radius_and_matches_the_uncached_path(trained, monkeypatch):
    import autodecoder.latent.projection as projection

    model, _ = trained
    scan = sphere_scan("new", 0.25, seed=9)
    fit = model.project(scan.points, scan.normals, seed=0, steps=80)
    assert abs(zero_crossing_radius(fit.field) - 0.25) < 0.03
    # the cached features (grids interpolated once per scan) give exactly the codes of the per-step interpolation
    scans = [scan, sphere_scan("other", 0.32, seed=10)]
    cached = model.project_many(scans, seed=0, steps=20)
    monkeypatch.setattr(projection, "_uses_cache", lambda net: False)
    plain = model.project_many(scans, seed=0, steps=20)
    for a, b in zip(cached, plain):
        assert torch.allclose(a.code, b.code, atol=1e-6) and abs(a.loss - b.loss) <= 1e-6 * b.loss
    assert abs(zero_crossing_radius(cached[1].field) - 0.32) < 0.03


def test_grid_checkpoint_and_field_round_trip(trained, tmp_path):
    from autodecoder.field.stochastic_field import StochasticField

    model, out = trained
    state = torch.load(out, weights_only=True)
    assert state["version"] == LATENT_VERSION == 2 and state["config"]["representation"] == "grid"
    assert state["config"]["grid_mean"]["shared_cells"] == 24  # the full settings: rebuilt without the defaults
    loaded = load_model(out)
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(0)) - 0.5
    a, b = model.training_field("train/002"), loaded.training_field("train/002")
    assert np.array_equal(a.mean(x.numpy()), b.mean(x.numpy()))
    assert np.array_equal(a.variance(x.numpy()), b.variance(x.numpy()))
    b.save(tmp_path / "field.pt")
    again = StochasticField.load(tmp_path / "field.pt")
    assert np.array_equal(again.mean(x.numpy()), a.mean(x.numpy()))


def test_grid_resume_gives_the_same_run(tmp_path):
    scans = sphere_scans()[:2]
    kw = dict(seed=3, quiet=True, **GRID)
    full = train_latent(scans, tmp_path / "full.pt", epochs=4, **kw)
    train_latent(scans, tmp_path / "part.pt", epochs=4, stop_after=2, **kw)
    resumed = train_latent(scans, tmp_path / "part.pt", resume=torch.load(tmp_path / "part.pt", weights_only=True),
                           **kw)
    assert resumed.epoch == 4 and torch.equal(full.codes, resumed.codes)
    for p, q in zip(full.mean_net.parameters(), resumed.mean_net.parameters()):
        assert torch.equal(p, q)


def test_version_1_siren_checkpoints_still_load(tmp_path):
    siren = train_latent(sphere_scans()[:2], tmp_path / "siren.pt", epochs=2, seed=0, quiet=True, latent_dim=2,
                         width=16, depth=2, features=8, mean_samples=128, screen_samples=64, pair_clusters=4)
    state = torch.load(tmp_path / "siren.pt", weights_only=True)
    state["version"] = 1  # as written before the grid representation: no 'representation' in the config
    for key in ("representation", "grid_mean", "grid_cov", "grid_lr", "shared_lr", "shared_points"):
        state["config"].pop(key)
    torch.save(state, tmp_path / "v1.pt")
    old = load_model(tmp_path / "v1.pt")
    assert old.representation == "siren" and type(old.mean_net) is type(siren.mean_net)
    x = np.random.default_rng(0).uniform(-0.4, 0.4, size=(30, 3))
    assert np.array_equal(old.training_field("train/000").mean(x), siren.training_field("train/000").mean(x))


def test_unknown_representation_is_refused():
    with pytest.raises(ValueError, match="representation.*'voxels'"):
        LatentOptions(representation="voxels")
    with pytest.raises(ValueError, match="grid_lr"):
        LatentOptions(grid_lr=0)


def test_command_line_passes_the_representation_and_the_samples():
    import train_latent

    args = train_latent.build_parser().parse_args(["--data", "c.h5", "--out", "m.pt", "--representation", "grid"])
    assert train_latent.options_from_args(args)["representation"] == "grid"
    args = train_latent.build_parser().parse_args(["--data", "c.h5", "--out", "m.pt"])
    assert "representation" not in train_latent.options_from_args(args)  # the library's default
    assert "mean_samples" not in train_latent.options_from_args(args)
    args = train_latent.build_parser().parse_args(["--data", "c.h5", "--out", "m.pt", "--samples", "1024"])
    options = train_latent.options_from_args(args)
    assert (options["mean_samples"], options["screen_samples"]) == (1024, 512)


def test_grid_default_epochs_follow_the_grid_budget():
    import math

    from autodecoder.latent.options import (GRID_DEFAULT_STEPS, GRID_MAX_DEFAULT_EPOCHS, GRID_MIN_DEFAULT_EPOCHS,
                                            default_epochs)

    assert default_epochs(26, 8, representation="grid") == math.ceil(GRID_DEFAULT_STEPS / 4)  # 4 steps an epoch
    assert default_epochs(52, 8, n_parts=2, representation="grid") == math.ceil(2 * GRID_DEFAULT_STEPS / 7)
    assert default_epochs(10_000, 8, representation="grid") == GRID_MIN_DEFAULT_EPOCHS
    assert default_epochs(1, 8, representation="grid") == min(GRID_MAX_DEFAULT_EPOCHS, GRID_DEFAULT_STEPS)
    assert default_epochs(26, 8) != default_epochs(26, 8, representation="grid")
    with pytest.raises(ValueError, match="representation"):
        default_epochs(26, 8, representation="voxels")


def test_grid_optimiser_groups_give_each_kind_of_parameter_its_rate():
    from autodecoder.field.networks import build_networks
    from autodecoder.latent.loop import _NetPair, _net_optimiser

    options = LatentOptions(**{k: v for k, v in GRID.items() if k not in ("grid_mean", "grid_cov")})
    config = {"representation": "grid", "latent_dim": 2, "box_lo": [-0.5] * 3, "box_hi": [0.5] * 3,
              "grid_mean": GRID["grid_mean"], "grid_cov": GRID["grid_cov"]}
    mean_net, cov_net = build_networks(config)
    opt = _net_optimiser(_NetPair(mean_net, cov_net, 100.0, 1.0), options)
    rates = {id(p): g["peak_lr"] for g in opt.param_groups for p in g["params"]}
    params = list(mean_net.parameters()) + list(cov_net.parameters())
    assert len(rates) == len(params)  # every parameter once
    assert rates[id(mean_net.shared.values)] == options.shared_lr
    assert rates[id(mean_net.encoder.levels[0].values)] == rates[id(cov_net.encoder.levels[-1].values)] == options.grid_lr
    assert rates[id(mean_net.decoder.layers[0].weight)] == rates[id(cov_net.decoder.code_in.weight)] == options.lr


def test_grid_covariance_reads_projected_codes_clamped_to_the_training_codes_box(trained, tmp_path):
    model, out = trained
    lo, hi = model.codes.min(0).values, model.codes.max(0).values
    assert torch.equal(model.cov_net.code_lo, lo) and torch.equal(model.cov_net.code_hi, hi)
    far = hi + 5.0 * (hi - lo) + 1.0  # beyond the box on every coordinate
    clipped = torch.from_numpy(np.clip(far.numpy(), lo.numpy(), hi.numpy()))  # independent of torch's clamp
    x = (torch.rand(40, 3, generator=torch.Generator().manual_seed(3)) - 0.5).numpy()
    a, b = model.field(far), model.field(clipped)
    assert np.array_equal(a.variance(x), b.variance(x))  # the covariance reads the clipped code
    assert not np.allclose(a.mean(x), b.mean(x))  # the mean is not clamped
    # inside the box nothing changes: a training code's variance is that of the unclamped net
    inside = model.codes[1]
    with torch.no_grad():
        free = model.cov_net.variance(torch.from_numpy(x).float(), inside)
        model.cov_net.set_code_range()
        try:
            assert torch.equal(model.cov_net.variance(torch.from_numpy(x).float(), inside), free)
            unclamped = model.cov_net.variance(torch.from_numpy(x).float(), far)
        finally:
            model.cov_net.set_code_range(lo, hi)
    assert not np.allclose(unclamped.numpy(), a.variance(x))  # the clamp did something for the far code
    # the range is not in the state dict (checkpoints keep their keys); the loaded model sets it from its codes
    assert not any(k.startswith("code_") for k in model.cov_net.state_dict())
    assert torch.equal(load_model(out).cov_net.code_hi, hi)
    # a projected field written to its own file keeps the clamp
    a.save(tmp_path / "far.pt")
    from autodecoder.field.stochastic_field import StochasticField

    again = StochasticField.load(tmp_path / "far.pt")
    assert torch.equal(again.cov_net.code_lo, lo) and np.array_equal(again.variance(x), a.variance(x))


def test_grid_code_range_refuses_bad_bounds(trained):
    net = trained[0].cov_net
    with pytest.raises(ValueError, match="both"):
        net.set_code_range(torch.zeros(2), None)
    with pytest.raises(ValueError, match="lo <= hi"):
        net.set_code_range(torch.ones(2), torch.zeros(2))
    with pytest.raises(ValueError, match="lo <= hi"):
        net.set_code_range(torch.zeros(3), torch.ones(3))
