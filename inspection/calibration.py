"""The calibration record a model file stores: good scans' scores and how they were computed, and its storage.

The thresholds drawn from those scores are :mod:`inspection.threshold`'s.
"""
from dataclasses import asdict, dataclass, field
from typing import List, Optional

from .threshold import DEFAULT_ALPHA, fit_threshold

CALIBRATION_KEY = "calibration"
CALIBRATION_VERSION = 1


@dataclass
class Calibration:
    """What the model file stores under ``"calibration"``: enough to score new scans without other data.

    Attributes
    ----------
    scores : list of float
        Anomaly scores of the good calibration scans.
    names : list of str
        Their scan names.
    roles : list of str
        For each, ``'held-back'`` (a good scan the model did not train on), ``'fold'`` (a training scan scored by a
        fold model that never trained on it) or ``'cross-fitted'`` (a training scan scored by the model as if new,
        :meth:`inspection.Inspector.fit`); empty in records written before roles existed.
    aggregate, point_score : str
        How the scores were computed (see :mod:`inspection.scores`); scoring must use the same.
    noise : float or None
        The noise floor used (None: the field's own).
    alpha : float
        Default false-alarm rate.
    source : str
        Where the calibration scans came from (a file, "held-back", ...).
    fingerprint : str
        Fingerprint of the collection they came from ('' when unknown).
    """

    scores: List[float]
    names: List[str]
    aggregate: str
    point_score: str
    noise: Optional[float] = None
    alpha: float = DEFAULT_ALPHA
    source: str = ""
    fingerprint: str = ""
    version: int = CALIBRATION_VERSION
    extra: dict = field(default_factory=dict)
    roles: List[str] = field(default_factory=list)

    def threshold(self, alpha=None):
        """The :class:`inspection.threshold.Threshold` of these scores at ``alpha`` (default: the stored one)."""
        return fit_threshold(self.scores, self.alpha if alpha is None else alpha, self.roles or None)

    def config(self):
        """The :class:`inspection.config.InspectionConfig` the scores were computed with (its 'auto' settings
        decided). Records written before the configuration was stored whole are read from their separate fields."""
        from .config import InspectionConfig

        extra = self.extra or {}
        if extra.get("config") is not None:
            return InspectionConfig.from_dict(extra["config"])
        rays = extra.get("rays")
        return InspectionConfig(alpha=self.alpha, aggregate=self.aggregate, point_score=self.point_score,
                                noise=self.noise, projection=extra.get("projection"), rays=rays is not None,
                                ray_options=None if rays is None else dict(rays["options"])).validated()

    def as_dict(self):
        d = asdict(self)
        d["scores"] = [float(s) for s in self.scores]
        d["names"] = [str(n) for n in self.names]
        return d

    @classmethod
    def from_dict(cls, d, source="<model>"):
        if not isinstance(d, dict) or d.get("version") != CALIBRATION_VERSION:
            raise ValueError(f"{source}: calibration record of unsupported version {d.get('version') if isinstance(d, dict) else d!r}")
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        return cls(**known)


def read_calibration(path):
    """The :class:`Calibration` stored in a model file, or None when it has none."""
    from autodecoder.field.checkpoint_io import load_torch_file

    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (a {type(ckpt).__name__}, expected a dict)")
    record = ckpt.get(CALIBRATION_KEY)
    return None if record is None else Calibration.from_dict(record, source=str(path))


def write_calibration(path, calibration):
    """Store ``calibration`` in the model file at ``path`` (atomically: a temporary file renamed into place).

    The checkpoint is loaded as a dict, gets (or replaces) its ``"calibration"`` entry of plain Python values, and is
    written back; every other entry is untouched, so the model loads as before.
    """
    from autodecoder.field.checkpoint_io import atomic_torch_save, load_torch_file

    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (a {type(ckpt).__name__}, expected a dict)")
    ckpt[CALIBRATION_KEY] = calibration.as_dict()
    atomic_torch_save(ckpt, path)
