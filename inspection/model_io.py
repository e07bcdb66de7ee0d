"""Loading what inspection scores against: a latent model checkpoint or a single stochastic field file.

Both are torch files holding a dict, told apart by their format tag; inspection adds one entry, ``"calibration"``
(see :mod:`inspection.calibration`), and reads:

* a latent checkpoint (format ``nsspr-latent-model``, written by ``train_latent.py``): a
  :class:`autodecoder.latent.model.LatentModel`, validated by that module; each scan is projected (its latent code
  fitted) before scoring. Its frame, collection fingerprint, training and held-back calibration scan names come from
  the checkpoint (see the format table in :mod:`autodecoder.latent.model`).
* a field file (``StochasticField.save``, format ``nsspr-field``): one fixed surface that every scan is scored against
  (the classical, non-latent version). Inspection's own reference fields (:func:`save_reference_field`) also carry
  a ``"collection"`` entry with the frame, fingerprint and scan names.
"""
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import numpy as np

COLLECTION_KEY = "collection"


@dataclass
class ModelHandle:
    """A loaded model and what inspection needs to know about it."""

    path: Path
    kind: str  # 'latent' or 'field'
    model: object
    frame: object = None  # datasets.Frame or None (unknown)
    fingerprint: str = ""
    train_names: List[str] = field(default_factory=list)
    heldback_names: List[str] = field(default_factory=list)
    calibration: object = None  # inspection.calibration.Calibration or None

    def reference_points(self, n=20000, seed=0):
        """Points on the model's mean surface (for alignment): the field's, or a latent model's at its mean code
        (a typical part). Returns (points (n, 3), normals (n, 3))."""
        f = self.model if self.kind == "field" else self.model.field(self.model.code_mean)
        import trimesh

        mesh = f.mesh(96)
        pts, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
        return np.asarray(pts), np.asarray(mesh.face_normals[faces])


def load_model_handle(path):
    """Load a latent checkpoint or a field file for inspection (the file is read once): the model with what
    inspection needs to know of it. (:func:`autodecoder.load_model` loads a latent checkpoint as the model alone.)

    Returns
    -------
    ModelHandle

    Raises
    ------
    FileNotFoundError, ValueError
        Naming ``path``: missing, unreadable, not a model, another format version, or damaged.
    """
    from autodecoder.field.checkpoint_io import load_torch_file
    from autodecoder.field.stochastic_field import FIELD_FORMAT
    from autodecoder.latent.model import LATENT_FORMAT

    from .calibration import CALIBRATION_KEY, Calibration

    path = Path(path)
    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (holds a {type(ckpt).__name__}, expected a dict)")
    if ckpt.get("format") not in (LATENT_FORMAT, FIELD_FORMAT):
        raise ValueError(f"{path}: not a model file (format tag {ckpt.get('format')!r}; expected a latent model "
                         f"checkpoint {LATENT_FORMAT!r} or a field file {FIELD_FORMAT!r})")
    calib = ckpt.get(CALIBRATION_KEY)
    calib = None if calib is None else Calibration.from_dict(calib, source=str(path))
    if ckpt["format"] == FIELD_FORMAT:
        from autodecoder.field.stochastic_field import StochasticField
        from datasets import Frame

        model = StochasticField.from_state(ckpt, source=str(path))
        info = ckpt.get(COLLECTION_KEY) or {}
        # the scans it was fitted on and held back, by name, as a latent model records them: the Inspector's scan
        # selection (inspection.selection) reads them from the model it is given
        model.train_names = [str(n) for n in info.get("train_names", [])]
        model.calibration_names = [str(n) for n in info.get("heldback_names", [])]
        model.fingerprint = str(info.get("fingerprint", ""))
        frame = Frame.from_dict(info["frame"]) if info.get("frame") else None
        return ModelHandle(path, "field", model, frame=frame, fingerprint=info.get("fingerprint", ""),
                           train_names=list(info.get("train_names", [])),
                           heldback_names=list(info.get("heldback_names", [])), calibration=calib)
    from autodecoder.latent.model import LatentModel

    try:
        model = LatentModel(ckpt, str(path))  # validates the format version and the keys
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - damaged weights: report one line naming the file
        raise ValueError(f"{path}: cannot load the model ({type(exc).__name__}: {exc})") from None
    return ModelHandle(path, "latent", model, frame=model.frame, fingerprint=model.fingerprint,
                       train_names=list(model.train_names), heldback_names=list(model.calibration_names),
                       calibration=calib)


def save_reference_field(field_, path, frame=None, fingerprint="", train_names=(), heldback_names=()):
    """Save a fixed field (e.g. ``fit_cloud`` on the union of good training scans) with its collection's frame,
    fingerprint and scan names, so inspection can check data against it and calibrate on held-back scans."""
    from autodecoder.field.checkpoint_io import atomic_torch_save

    state = field_.state()
    state[COLLECTION_KEY] = {"frame": None if frame is None else frame.as_dict(), "fingerprint": str(fingerprint),
                             "train_names": [str(n) for n in train_names],
                             "heldback_names": [str(n) for n in heldback_names]}
    atomic_torch_save(state, path)
    return Path(path)
