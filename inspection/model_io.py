"""Loading what inspection scores against: a latent model checkpoint or a single stochastic field file.

Both are torch files holding a dict; inspection adds one entry, ``"calibration"`` (see
:mod:`inspection.calibration`), and reads:

* a latent checkpoint (``train_latent.py``): loaded with ``autodecoder.load_model``; each scan is projected
  (its latent code fitted) before scoring. Its frame, collection fingerprint and held-back calibration scan names
  come from the checkpoint.
* a field file (``StochasticField.save``, format ``nsspr-field``): one fixed surface that every scan is scored against
  (the classical, non-latent version). Inspection's own reference fields (:func:`save_reference_field`) also carry
  a ``"collection"`` entry with the frame, fingerprint and scan names.
"""
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

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
    checkpoint: dict = field(default_factory=dict, repr=False)

    def reference_points(self, n=20000, seed=0):
        """Points on the model's mean surface (for alignment), or None when the model cannot give them."""
        f = None
        if self.kind == "field":
            f = self.model
        elif callable(getattr(self.model, "field", None)) and hasattr(self.model, "code_mean"):
            f = self.model.field(self.model.code_mean)  # the field of the mean code: a typical part
        if f is None:
            return None
        import trimesh

        mesh = f.mesh(96)
        pts, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
        return np.asarray(pts), np.asarray(mesh.face_normals[faces])


def _first(d, keys, default=None):
    for k in keys:
        if isinstance(d, dict) and d.get(k) is not None:
            return d[k]
    return default


def _frame_from(value):
    from datasets import Frame

    if value is None:
        return None
    if isinstance(value, Frame):
        return value
    if isinstance(value, dict) and "center" in value and "scale" in value:
        return Frame.from_dict(value)
    if hasattr(value, "center") and hasattr(value, "scale"):
        return Frame(np.asarray(value.center), float(value.scale))
    return None


def load_model(path):
    """Load a latent checkpoint or a field file for inspection.

    Returns
    -------
    ModelHandle

    Raises
    ------
    FileNotFoundError, ValueError
        Naming ``path``: missing, unreadable, or not a model.
    """
    from autodecoder.field.checkpoint_io import load_torch_file

    from .calibration import CALIBRATION_KEY, Calibration

    path = Path(path)
    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (holds a {type(ckpt).__name__}, expected a dict)")
    calib = ckpt.get(CALIBRATION_KEY)
    calib = None if calib is None else Calibration.from_dict(calib, source=str(path))
    if ckpt.get("format") == "nsspr-field":
        from autodecoder.field.stochastic_field import StochasticField

        model = StochasticField.from_state(ckpt, source=str(path))
        info = ckpt.get(COLLECTION_KEY) or {}
        return ModelHandle(path, "field", model, frame=_frame_from(info.get("frame")),
                           fingerprint=info.get("fingerprint", ""), train_names=list(info.get("train_names", [])),
                           heldback_names=list(info.get("heldback_names", [])), calibration=calib, checkpoint=ckpt)
    import autodecoder

    loader = getattr(autodecoder, "load_model", None)
    if loader is None:
        try:
            from autodecoder.latent.model import load_model as loader
        except ImportError:
            raise ValueError(f"{path}: not a field file, and this toolkit has no latent model loader") from None
    try:
        model = loader(path)
    except (FileNotFoundError, ValueError):
        raise
    except Exception as exc:  # noqa: BLE001 - report one line naming the file
        raise ValueError(f"{path}: cannot load the model ({type(exc).__name__}: {exc})") from None
    data = ckpt.get("data") if isinstance(ckpt.get("data"), dict) else {}
    frame = _frame_from(getattr(model, "frame", None)) or _frame_from(_first(ckpt, ("frame",))) \
        or _frame_from(data.get("frame"))
    fingerprint = _first(ckpt, ("collection_fingerprint", "fingerprint"), None) or \
        _first(data, ("collection_fingerprint", "fingerprint"), "") or ""
    heldback = _first(ckpt, ("calibration_names", "heldback_names", "held_back_names", "calibration_scans"), None) \
        or _first(data, ("calibration_names", "heldback_names", "held_back_names", "calibration_scans"), []) or []
    train = _first(ckpt, ("train_names", "scan_names", "names"), None) or \
        _first(data, ("train_names", "scan_names", "names"), []) or []
    for attr, current in (("calibration_names", heldback), ("train_names", train)):
        if not current and isinstance(getattr(model, attr, None), (list, tuple)):
            if attr == "calibration_names":
                heldback = list(getattr(model, attr))
            else:
                train = list(getattr(model, attr))
    return ModelHandle(path, "latent", model, frame=frame, fingerprint=str(fingerprint), train_names=list(train),
                       heldback_names=list(heldback), calibration=calib, checkpoint=ckpt)


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
