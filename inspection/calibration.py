"""Conformal calibration from good scans: p-values, the threshold at a false-alarm rate, and its storage in the model.

Split-conformal p-value of a score s against n calibration scores c_1..c_n of good scans the model never trained on:

    p(s) = (1 + #{i : c_i >= s}) / (n + 1)

If the good scans are exchangeable, P(p(s) <= alpha) <= alpha for a new good scan: flagging p <= alpha keeps the
false-alarm rate at most alpha. The smallest p-value reachable is 1 / (n + 1), so alpha needs n >= 1 / alpha - 1.
"""
import logging
import math
import warnings
from dataclasses import asdict, dataclass, field
from typing import List, Optional

import numpy as np

log = logging.getLogger(__name__)

CALIBRATION_KEY = "calibration"
CALIBRATION_VERSION = 1
_TOL = 1e-9


class SmallCalibrationWarning(UserWarning):
    """Too few calibration scores for the requested alpha: nothing can be flagged."""


def check_alpha(alpha):
    alpha = float(alpha)
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    return alpha


def conformal_p_values(calibration_scores, scores):
    """Conformal p-values of ``scores`` against the calibration scores (ties count as at least as extreme).

    Parameters
    ----------
    calibration_scores : (n,) array
        Anomaly scores of good held-out scans (higher = more anomalous), n >= 1.
    scores : (m,) array
        Anomaly scores to test.

    Returns
    -------
    (m,) float64 array in [1 / (n + 1), 1]
    """
    cal = np.sort(np.asarray(calibration_scores, dtype=np.float64).reshape(-1))
    if len(cal) == 0:
        raise ValueError("calibration_scores is empty: calibrate on at least one good scan")
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    at_least = len(cal) - np.searchsorted(cal, s, side="left")  # #{c >= s}
    return (1.0 + at_least) / (len(cal) + 1.0)


def allowed_exceedances(n, alpha):
    """k = floor(alpha (n + 1) - 1): a score is flagged iff at most k calibration scores are >= it (-1: never)."""
    return int(math.floor(alpha * (n + 1) - 1 + _TOL))


def conformal_threshold(calibration_scores, alpha, warn=True):
    """The score threshold t with ``p(s) <= alpha  <=>  s > t`` (ties included).

    Parameters
    ----------
    calibration_scores : (n,) array
    alpha : float in (0, 1)
        Target false-alarm rate.
    warn : bool
        Warn (and log) when 1 / (n + 1) > alpha: then no score can reach p <= alpha and t = +inf.

    Returns
    -------
    float
        The (k+1)-th largest calibration score, k = floor(alpha (n + 1) - 1); +inf when k < 0.
    """
    alpha = check_alpha(alpha)
    cal = np.sort(np.asarray(calibration_scores, dtype=np.float64).reshape(-1))[::-1]
    n = len(cal)
    if n == 0:
        raise ValueError("calibration_scores is empty: calibrate on at least one good scan")
    k = allowed_exceedances(n, alpha)
    if k < 0:
        if warn:
            msg = (f"{n} calibration scan(s) are too few for alpha={alpha:g}: the smallest possible p-value is "
                   f"1/(n+1) = {1 / (n + 1):.3g} > alpha, so nothing will be flagged; calibrate on at least "
                   f"{math.ceil(1 / alpha - 1)} good scans or raise alpha")
            log.warning(msg)
            warnings.warn(msg, SmallCalibrationWarning, stacklevel=2)
        return math.inf
    if k >= n:
        return -math.inf
    return float(cal[k])


@dataclass
class Calibration:
    """What the model file stores under ``"calibration"``: enough to score new scans without other data.

    Attributes
    ----------
    scores : list of float
        Anomaly scores of the good calibration scans.
    names : list of str
        Their scan names.
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
    alpha: float = 0.01
    source: str = ""
    fingerprint: str = ""
    version: int = CALIBRATION_VERSION
    extra: dict = field(default_factory=dict)

    def threshold(self, alpha=None):
        return conformal_threshold(self.scores, self.alpha if alpha is None else alpha)

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
    from autodecoder.checkpoint_io import load_torch_file

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
    from autodecoder.checkpoint_io import atomic_torch_save, load_torch_file

    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (a {type(ckpt).__name__}, expected a dict)")
    ckpt[CALIBRATION_KEY] = calibration.as_dict()
    atomic_torch_save(ckpt, path)
