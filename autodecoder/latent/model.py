"""LatentModel: a trained autodecoder (mean and covariance nets conditioned on a code) and its checkpoint format.

A checkpoint is a plain dict of tensors and Python values, readable with ``torch.load(weights_only=True)``:

=====================  ==============================================================================================
key                    content
=====================  ==============================================================================================
format, version        ``"nsspr-latent-model"``, 2 (version 1, SIREN nets only, is still read)
config                 network and training configuration (see :func:`autodecoder.latent.train.train_latent`);
                       ``representation`` ('siren' or 'grid', absent in version 1: 'siren') and, for grids, the full
                       ``grid_mean`` / ``grid_cov`` settings the nets are rebuilt from
mean_state, cov_state  network weights
codes                  (T, L) float32: one code per training scan, in ``train_names`` order
code_mean, code_std    (L,) float32: statistics of the codes
train_names            list of str: the training scans (collection names)
train_part_ids         list of str: their part ids
calibration_names      list of str: good scans held back for the inspection threshold
frame                  {"center": [x, y, z], "scale": s}: file -> collection frame of the training collection
noise                  float: RMS of the mean at the training scans' points (collection units)
fingerprint            str: the training collection's fingerprint ('' when trained on in-memory scans)
epoch                  int: epochs completed
resume                 dict: optimiser and RNG states (only what ``--resume`` needs)
info                   dict: provenance (wall time, per-epoch losses summary)
=====================  ==============================================================================================

All coordinates the model takes and returns are in the training collection's frame (the unit cube the collection's
scans are stored in); :attr:`LatentModel.frame` maps scanner-file coordinates into it.
"""
import os
from dataclasses import dataclass
from typing import List
from pathlib import Path

import numpy as np
import torch

from autodecoder.field.checkpoint_io import atomic_torch_save, load_torch_file
from autodecoder.field.networks import build_networks
from datasets.frame import Frame
from autodecoder.field.stochastic_field import StochasticField
from autodecoder.latent.projection import project, project_many

LATENT_FORMAT = "nsspr-latent-model"
LATENT_VERSION = 2
# Versions this toolkit reads. 1: SIREN nets (no ``representation`` in the config); 2 adds the grid representation
# (a reader of version 1 only refuses those checkpoints instead of building the wrong nets).
READABLE_VERSIONS = (1, 2)
# Config keys a code's StochasticField needs to rebuild its nets (autodecoder.field.networks.build_networks).
FIELD_CONFIG_KEYS = ("representation", "width", "depth", "latent_dim", "covariance", "features", "omega0",
                     "grid_mean", "grid_cov", "lengthscale", "box_lo", "box_hi")
_REQUIRED_KEYS = ("config", "mean_state", "cov_state", "codes", "train_names", "calibration_names", "frame", "noise")


def check_checkpoint(state, source):
    """Raise one clear ValueError naming ``source`` unless ``state`` is a latent-model checkpoint of our version."""
    if not isinstance(state, dict) or state.get("format") != LATENT_FORMAT:
        raise ValueError(f"{source}: not a latent model checkpoint (format tag {LATENT_FORMAT!r} missing)")
    if state.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"{source}: latent model checkpoint version {state.get('version')} is not supported "
                         f"(this toolkit reads versions {', '.join(map(str, READABLE_VERSIONS))})")
    missing = [k for k in _REQUIRED_KEYS if k not in state]
    if missing:
        raise ValueError(f"{source}: damaged latent model checkpoint (missing {', '.join(missing)})")
    return state


def read_checkpoint(path):
    """The checkpoint dict at ``path`` (``torch.load(weights_only=True)``), validated; clear errors naming it."""
    return check_checkpoint(load_torch_file(path, what="latent model checkpoint"), os.fspath(Path(path)))


class LatentModel:
    """A trained latent model: g(x, z), c(x1, x2, z) and the codes of its training scans.

    Build it with :func:`load_model`; fit a code to a new scan with :meth:`project`.

    Attributes
    ----------
    mean_net, cov_net : torch.nn.Module
        Frozen (eval mode, no gradients) networks.
    codes : (T, L) float32 tensor
        Training codes.
    code_mean, code_std : (L,) float32 tensors
        (A grid covariance net reads codes clamped to the training codes' per-coordinate box, set here:
        :meth:`autodecoder.field.grid_networks.GridCovarianceNet.set_code_range`.)
    train_names, calibration_names : list of str
    noise : float
        Measurement noise level in collection units (RMS training residual).
    config : dict
    fingerprint : str
        The training collection's fingerprint.
    state : dict
        The checkpoint it was built from.
    calibration_folds : list of autodecoder.latent.folds.CalibrationFold
        Its fold models (each trained without some of its training scans, which it scores as new), or [].
    """

    def __init__(self, state, source="<state>"):
        state = check_checkpoint(state, source)
        self.source = source
        self.state = state
        self.config = dict(state["config"])
        self.mean_net, self.cov_net = build_networks(self.config)
        self.mean_net.load_state_dict(state["mean_state"])
        self.cov_net.load_state_dict(state["cov_state"])
        for net in (self.mean_net, self.cov_net):
            net.eval()
            net.requires_grad_(False)
        self.codes = state["codes"].detach().float()
        self.code_mean = state.get("code_mean", self.codes.mean(0)).float()
        self.code_std = state.get("code_std", self.codes.std(0) if len(self.codes) > 1 else torch.ones_like(self.code_mean)).float()
        if hasattr(self.cov_net, "set_code_range") and len(self.codes) > 1:
            # a grid covariance decoder reads projected codes clamped to the training codes' box (its docstring)
            self.cov_net.set_code_range(self.codes.min(0).values, self.codes.max(0).values)
        self.train_names = list(state["train_names"])
        self.train_part_ids = list(state.get("train_part_ids", [""] * len(self.train_names)))
        self.calibration_names = list(state["calibration_names"])
        self.frame_dict = dict(state["frame"])
        self.noise = float(state["noise"])
        self.fingerprint = str(state.get("fingerprint", ""))
        self.epoch = int(state.get("epoch", 0))
        self.info = dict(state.get("info", {}))
        self._folds = None
        self._family = None

    @property
    def calibration_folds(self):
        """The fold models stored in the checkpoint (:mod:`autodecoder.latent.folds`), built and checked on first
        use; [] when it has none."""
        if self._folds is None:
            self._folds = read_folds(self.state, self.source)
        return self._folds

    @property
    def family(self):
        """The :class:`autodecoder.latent.family.FamilyFrame` the training scans were brought into before training
        (one size: a product family; one pose: parts placed by hand), or None. Its model explains scans in that
        frame: register a new scan with :meth:`normalise` before projecting it (the inspection does)."""
        if self._family is None and self.state.get("family") is not None:
            from autodecoder.latent.family import FamilyFrame

            try:
                self._family = FamilyFrame.from_dict(self.state["family"])
            except (ValueError, TypeError, KeyError) as exc:
                raise ValueError(f"{self.source}: the checkpoint's family frame is unreadable ({exc})") from None
        return self._family

    def normalise(self, scan):
        """``scan`` (a Scan or (m, 3) points, collection frame) registered onto the training scans' common frame
        (:meth:`FamilyFrame.normalise`); returned as it is by a model without one (a part in a fixture)."""
        family = self.family
        return scan if family is None else family.normalise(scan)

    @property
    def latent_dim(self):
        return int(self.config["latent_dim"])

    @property
    def frame(self):
        """The training collection's :class:`datasets.frame.Frame` (x_collection = scale * (x_file - center))."""
        return Frame.from_dict(self.frame_dict)

    @property
    def lengthscale(self):
        """GP kernel lengthscale the model was trained with (collection units)."""
        return float(self.config["lengthscale"])

    @property
    def representation(self):
        """'siren' or 'grid': the kind of nets (version-1 checkpoints are all 'siren')."""
        return str(self.config.get("representation", "siren"))

    def __repr__(self):
        nets = (f"width={self.config['width']}, depth={self.config['depth']}" if self.representation == "siren"
                else "grid")
        return (f"LatentModel({self.source!r}, {len(self.train_names)} training codes, latent_dim={self.latent_dim}, "
                f"{nets}, epoch={self.epoch})")

    def field(self, code, mean_net=None, cov_net=None, info=None):
        """The :class:`StochasticField` of a code (L,), in the collection frame (identity frame)."""
        code = torch.as_tensor(code, dtype=torch.float32).reshape(-1)
        if code.shape != (self.latent_dim,):
            raise ValueError(f"code must have {self.latent_dim} entries, got {tuple(code.shape)}")
        field_config = {k: self.config[k] for k in FIELD_CONFIG_KEYS if k in self.config}
        return StochasticField(mean_net or self.mean_net, cov_net or self.cov_net, Frame.identity(),
                               field_config, code=code, noise=self.noise, info=info)

    def training_field(self, name):
        """The field of training scan ``name`` (its learned code)."""
        try:
            i = self.train_names.index(name)
        except ValueError:
            raise KeyError(f"{self.source}: no training scan named {name!r}") from None
        return self.field(self.codes[i], info={"training_scan": name})

    def project(self, points, normals=None, **options):
        """Fit a code to one scan with the nets frozen; see :func:`autodecoder.latent.projection.project`."""
        return project(self, points, normals, **options)

    def project_many(self, scans, **options):
        """Fit codes to many scans at once; see :func:`autodecoder.latent.projection.project_many`."""
        return project_many(self, scans, **options)


# fold models (autodecoder.latent.folds) inside a checkpoint: a list of {"scored_names", "checkpoint", "rule"}
FOLDS_KEY = "calibration_folds"
# what a fold model trains on, stored with each fold: a fold model trained by another rule is retrained by tools
# that keep fold models up to date (benchmarks.cache)
FOLD_RULE = "outside the fold, and the held-back scans"


@dataclass
class CalibrationFold:
    """One fold model and the training scans of the main model it scores as new scans."""

    model: object  # LatentModel
    scored_names: List[str]
    rule: str = ""  # FOLD_RULE when it was trained by today's rule


def read_folds(state, source="<state>"):
    """The :class:`CalibrationFold` s stored in a main checkpoint (``[]`` without any), each checked: a complete
    latent checkpoint, trained on none of the scans it scores and only on the main model's training and held-back
    scans, scoring only the main model's training scans."""
    out = []
    train = set(state.get("train_names", []))
    for j, fold in enumerate(state.get(FOLDS_KEY) or []):
        where = f"{source}: calibration fold {j + 1}"
        if not isinstance(fold, dict) or "scored_names" not in fold or "checkpoint" not in fold:
            raise ValueError(f"{where}: damaged (scored_names or checkpoint missing)")
        scored = [str(n) for n in fold["scored_names"]]
        model = LatentModel(fold["checkpoint"], f"{where}")
        seen = sorted(set(scored) & set(model.train_names))
        if seen:
            raise ValueError(f"{where}: trained on {len(seen)} of the scans it scores (e.g. {seen[0]!r}); its scores "
                             f"would not be out of sample")
        foreign = sorted(set(scored) - train)
        if foreign:
            raise ValueError(f"{where}: scores {foreign[0]!r}, which is not one of the model's training scans")
        unknown = sorted(set(model.train_names) - train - set(state.get("calibration_names", [])))
        if unknown:
            raise ValueError(f"{where}: trained on {unknown[0]!r}, which is neither a training nor a held-back scan "
                             f"of the model")
        out.append(CalibrationFold(model, scored, str(fold.get("rule", ""))))
    return out


def load_model(path):
    """Read a latent model checkpoint written by ``train_latent.py``.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    LatentModel

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not a latent model checkpoint, another format version, or damaged (the message names the file).
    """
    return LatentModel(read_checkpoint(path), os.fspath(Path(path)))


def save_checkpoint(state, path):
    """Write a checkpoint dict atomically (see :func:`autodecoder.field.checkpoint_io.atomic_torch_save`)."""
    check_checkpoint(state, os.fspath(path))
    atomic_torch_save(state, path)


def code_statistics(codes):
    """(mean, std) of the codes (T, L); std is ones for a single code."""
    codes = codes.detach().float()
    mean = codes.mean(0)
    std = codes.std(0) if len(codes) > 1 else torch.ones_like(mean)
    return mean, std


def as_float_array(x):
    return np.ascontiguousarray(np.asarray(x, dtype=np.float32))
