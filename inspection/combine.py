"""One anomaly score from several per-scan scores (the point score and the ray score), calibrated on good scans.

Each component j of a scan's scores s (higher = more anomalous) is standardized against the good calibration scans,
z_j = (s_j - mean_j) / sd_j, and the combined score is the largest: c(s) = max_j z_j. A scan is as anomalous as its
most anomalous component, measured in the spread good scans show on that component; the union of the components'
detections, like a Bonferroni combination of p-values, but continuous: conformal p-values of the components stop at
1 / (n + 1) beyond the largest calibration score, so with a few dozen calibration scans a min-p (or Fisher)
combination ties every clearly defective scan and can no longer rank them.

The combined score is then calibrated like any other (:mod:`inspection.calibration`): the calibration scans'
own combined scores are computed leave-one-out (scan i standardized with the statistics of the other n - 1), so
that each is computed the way a new scan's is, from statistics it took no part in; the split-conformal threshold
on them keeps its false-alarm guarantee up to the n - 1 vs n difference.
"""
import numpy as np

MIN_SCANS = 3
_REL_FLOOR = 1e-3
_ABS_FLOOR = 1e-9


def _as_matrix(components, names=None):
    """dict name -> (n,) scores, or a list of such dicts per scan -> (names, (n, J) array)."""
    if isinstance(components, dict):
        names = list(components) if names is None else list(names)
        cols = [np.asarray(components[k], dtype=np.float64).reshape(-1) for k in names]
    else:
        rows = list(components)
        names = list(rows[0]) if names is None and rows else list(names or [])
        cols = [np.array([r[k] for r in rows], dtype=np.float64) for k in names]
    if not cols or len({len(c) for c in cols}) != 1:
        raise ValueError(f"components must give the same number of scans for every score, got "
                         f"{ {k: len(c) for k, c in zip(names, cols)} }")
    matrix = np.stack(cols, axis=1)
    if not np.isfinite(matrix).all():
        raise ValueError("component scores must be finite numbers")
    return names, matrix


def standardization(matrix):
    """Per-component (mean, sd) of calibration scores (n, J) -> (J,), (J,); sd floored (never 0)."""
    mean = matrix.mean(0)
    sd = matrix.std(0, ddof=1) if len(matrix) > 1 else np.zeros(matrix.shape[1])
    return mean, np.maximum(sd, _REL_FLOOR * np.abs(mean) + _ABS_FLOOR)


class Combination:
    """The max-of-standardized-scores combination fitted on good calibration scans.

    Parameters
    ----------
    components : dict name -> (n,) array, or a list of n dicts name -> float
        Component scores of the calibration scans (at least ``MIN_SCANS``).
    names : sequence of str, optional
        Component order (default: the dict's).
    """

    def __init__(self, components, names=None):
        self.names, self.matrix = _as_matrix(components, names)
        if len(self.matrix) < MIN_SCANS:
            raise ValueError(f"combining scores needs at least {MIN_SCANS} calibration scans, got "
                             f"{len(self.matrix)}")
        self.mean, self.sd = standardization(self.matrix)

    def score(self, components):
        """Combined scores of scans: dict name -> (k,) array or list of dicts -> (k,) array."""
        _, matrix = _as_matrix(components, self.names)
        return ((matrix - self.mean) / self.sd).max(1)

    def standardized(self, components):
        """The standardized components (k, J), in ``names`` order."""
        _, matrix = _as_matrix(components, self.names)
        return (matrix - self.mean) / self.sd

    def calibration_scores(self):
        """Leave-one-out combined scores (n,) of the calibration scans (see the module docstring)."""
        out = np.empty(len(self.matrix))
        for i in range(len(self.matrix)):
            mean, sd = standardization(np.delete(self.matrix, i, axis=0))
            out[i] = ((self.matrix[i] - mean) / sd).max()
        return out

    def as_dict(self):
        """Plain Python values: the calibration component scores (the statistics follow from them)."""
        return {name: [float(v) for v in self.matrix[:, j]] for j, name in enumerate(self.names)}

    @classmethod
    def from_dict(cls, d):
        return cls({k: np.asarray(v, dtype=np.float64) for k, v in d.items()})
