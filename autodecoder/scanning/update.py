"""Fine-tuning a fitted field on newly captured points: warm start from its weights, train on old + new data.

Choices (documented here once):
- A new :class:`StochasticField` is returned; the input field is left intact (its nets are deep-copied).
- The field remembers its training cloud in ``training_points``/``training_normals`` (world frame, float32
  tensors, saved with the field). Fields fitted before this existed (or by a ``fit_cloud`` that does not record
  it) need ``old_points``/``old_normals`` passed explicitly.
- The normalisation (world -> model frame) stays the original field's: the nets' inputs keep their meaning, which
  is what makes the warm start useful. The kernel lengthscale also stays. The integration box is the union of the
  old box and the default box around the union cloud, so new points outside the old box are covered (the nets then
  see inputs a little beyond the unit cube, where a SIREN extrapolates smoothly; a part that grows far beyond its
  first scan should be refitted).
- The GP target pools (see :class:`autodecoder.field.fit.FitOptions`) are sized to what ``steps`` uses (by
  :func:`autodecoder.field.fit.train_single`, as for every run).
- One "epoch" is one pass of the screening batch over the union cloud: steps = epochs * ceil(n / screen_batch),
  unless ``steps`` is given. The learning rate starts at ``lr_fraction`` x the fit's (cosine decay), since the
  weights are already near a solution.
"""
import copy
import math
import time
from dataclasses import asdict

import numpy as np
import torch

from autodecoder.field.fit import FitOptions, train_single
from autodecoder.field.steps import residual_noise
from autodecoder.field.grid_fit import GridFitOptions, fit_grid_cloud
from autodecoder.field.grid_networks import GRID_REPRESENTATION
from autodecoder.field.sampling import Box
from autodecoder.field.stochastic_field import StochasticField
from autodecoder.field.targets import CloudTargets, default_box
from datasets.validation import check_oriented_cloud


def update_field(field, points, normals, epochs=50, steps=None, lr_fraction=0.3, old_points=None, old_normals=None,
                 seed=0, quiet=True, options=None, **option_overrides):
    """Fine-tune ``field`` on the union of its training cloud and a new oriented cloud (world frame).

    Parameters
    ----------
    field : StochasticField
        A single-cloud field (no latent code).
    points, normals : (n, 3) arrays
        Newly captured points and outward normals, in the field's world frame.
    epochs : int
        Passes over the union cloud (see the module docstring); ignored when ``steps`` is given.
    steps : int, optional
        Adam steps.
    lr_fraction : float
        Peak learning rate as a fraction of ``options.lr``.
    old_points, old_normals : (m, 3) arrays, optional
        The previous training cloud, when the field does not carry it.
    seed : int
    quiet : bool
    options : FitOptions, optional
        Defaults to the options the field was fitted with (``field.info['options']``) or ``FitOptions()``.
    **option_overrides
        Any FitOptions field.

    Returns
    -------
    StochasticField, with ``training_points``/``training_normals`` the union and ``info['updates']`` extended.

    A grid field (``fit_cloud``'s default representation) is refitted on the union instead, with its own grid
    settings and options (``options`` / ``option_overrides`` are then :class:`GridFitOptions` fields; ``epochs``,
    ``steps`` and ``lr_fraction`` do not apply): its mean is the exact minimiser of the loss on its grid, solved in
    seconds, so there is nothing to fine-tune from, and the union's box and frame replace the old ones.
    """
    if field.code is not None:
        raise ValueError("update_field fine-tunes single-cloud fields; this field has a latent code")
    points, normals = check_oriented_cloud(points, normals)
    if old_points is None:
        if field.training_points is None:
            raise ValueError("the field does not carry its training cloud: pass old_points and old_normals "
                             "(or set field.training_points / field.training_normals)")
        old_points, old_normals = field.training_points.numpy(), field.training_normals.numpy()
    old_points, old_normals = check_oriented_cloud(old_points, old_normals)
    all_points = np.concatenate([old_points, points]).astype(np.float64)
    all_normals = np.concatenate([old_normals, normals]).astype(np.float64)
    if field.config.get("representation", "siren") == GRID_REPRESENTATION:
        return _refit_grid(field, all_points, all_normals, len(points), seed, quiet, options, option_overrides)
    saved = field.info.get("options")
    # a field saved before covariance_every / average_decay existed took a covariance step with every mean step
    # and kept its last iterate
    base = options or (FitOptions(**{"covariance_every": 1, "average_decay": 0.0, **saved}) if saved
                       else FitOptions())
    options = FitOptions(**{**asdict(base), **option_overrides})
    options.lr = options.lr * lr_fraction
    if steps is None:
        steps = max(1, int(epochs) * math.ceil(len(all_points) / options.screen_batch))
    t0 = time.perf_counter()
    norm = field.frame
    model_points = norm.to_collection(all_points)
    h = float(field.config["lengthscale"])
    new_box = default_box(model_points, h)
    lo = np.minimum(np.asarray(field.config["box_lo"]), new_box.lo)
    hi = np.maximum(np.asarray(field.config["box_hi"]), new_box.hi)
    targets = CloudTargets(model_points, all_normals, h, box=Box(lo, hi))
    mean_net, cov_net = copy.deepcopy(field.mean_net), copy.deepcopy(field.cov_net)
    torch.manual_seed(seed)
    history = train_single(mean_net, cov_net, targets, options, np.random.default_rng(seed), quiet=quiet,
                           steps=steps)
    config = {**field.config, "box_lo": lo.tolist(), "box_hi": hi.tolist()}
    info = copy.deepcopy(field.info)
    info.setdefault("updates", []).append({"n_new": len(points), "n_total": len(all_points), "steps": steps,
                                           "seconds": time.perf_counter() - t0,
                                           "final_losses": history[-1] if history else {}})
    return StochasticField(mean_net, cov_net, norm, config, noise=residual_noise(mean_net, targets, norm), info=info,
                           training_points=all_points, training_normals=all_normals)


def _refit_grid(field, all_points, all_normals, n_new, seed, quiet, options, option_overrides):
    """:func:`update_field` for a grid field: a fit of the union with the field's grid settings and options."""
    saved = dict(field.info.get("options") or {})
    base = options or GridFitOptions(**{k: v for k, v in saved.items() if k in GridFitOptions.__dataclass_fields__})
    new = fit_grid_cloud(all_points, all_normals, seed=seed, grid_mean=field.config.get("grid_mean"),
                         grid_cov=field.config.get("grid_cov"), options=base, **option_overrides)
    new.info["updates"] = copy.deepcopy(field.info.get("updates", [])) + [
        {"n_new": int(n_new), "n_total": len(all_points), "refit": True, "seconds": new.info["fit_seconds"]}]
    return new
