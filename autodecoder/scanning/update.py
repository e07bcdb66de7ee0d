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
    """
    if field.code is not None:
        raise ValueError("update_field fine-tunes single-cloud fields; this field has a latent code")
    if field.config.get("representation", "siren") != "siren":
        raise ValueError("update_field fine-tunes SIREN fields; refit a grid field to the old and new points "
                         "(fit_cloud(..., representation='grid'))")
    points, normals = check_oriented_cloud(points, normals)
    if old_points is None:
        if field.training_points is None:
            raise ValueError("the field does not carry its training cloud: pass old_points and old_normals "
                             "(or set field.training_points / field.training_normals)")
        old_points, old_normals = field.training_points.numpy(), field.training_normals.numpy()
    old_points, old_normals = check_oriented_cloud(old_points, old_normals)
    all_points = np.concatenate([old_points, points]).astype(np.float64)
    all_normals = np.concatenate([old_normals, normals]).astype(np.float64)
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
    with torch.no_grad():
        residual = mean_net(torch.from_numpy(targets.points32)).double().numpy() / norm.scale
    config = {**field.config, "box_lo": lo.tolist(), "box_hi": hi.tolist()}
    info = copy.deepcopy(field.info)
    info.setdefault("updates", []).append({"n_new": len(points), "n_total": len(all_points), "steps": steps,
                                           "seconds": time.perf_counter() - t0,
                                           "final_losses": history[-1] if history else {}})
    return StochasticField(mean_net, cov_net, norm, config, noise=float(np.sqrt(np.mean(residual**2))), info=info,
                           training_points=all_points, training_normals=all_normals)
