"""Scans denser than the model's training scans: scored on a random subset at the training scans' density.

A full-resolution view (a million points, as MVTec 3D-AD and Real3D-AD ship them) holds far more points than the
model can tell apart: its kernel lengthscale was drawn from its training scans' point spacing (``lengthscale =
DEFAULT_LENGTHSCALE_FACTOR x spacing``), and its calibration (the threshold, the region level) saw good scans at that
density. Such a scan is scored on a seeded random subset of its points at that spacing (:func:`evidence_sample`),
the density the calibration's scores were drawn at, so the threshold and the region level mean what they say for
it; its maps carry each scored point's value to the points nearest it (:meth:`EvidenceSample.full`), so a PLY map
still has every point of the scan. A random subset keeps the sensor's own sampling, only thinner: one point per
voxel cell (a regular pattern no training scan had) raised good scans' scores by a tenth of a standard deviation on
the tests' sphere, enough to flag half of them. A scan within a few times the training density (whose subset would
keep more than ``SAMPLE_BELOW`` of its points) is scored as it is: the benchmarks' 4,000-point scans, whose views
spread in density, and the calibration's good scans are never thinned.
"""
from dataclasses import dataclass, replace

import numpy as np

# a scan is thinned only when its subset at the training spacing keeps fewer than this share of its points: the
# densest views of the benchmark trees' 4,000-point scans would keep 0.44 (the bracket), 0.55 (fandisk), 0.70 (the
# cup), 0.84 (the real bunny) against their models' spacing, and are scored as they were; a 30,000-point view of the
# bracket keeps about 0.13, a million-point one 0.004
SAMPLE_BELOW = 0.2
# the scan's own spacing is measured on a random subset of at most this many points (its spacing scaled back by the
# square root of the share: a spacing is a square root of area per point): a few milliseconds a scan at any size
SPACING_POINTS = 2_000


@dataclass
class EvidenceSample:
    """Which of a scan's m points were scored, and how the scored values go back to every point.

    Attributes
    ----------
    kept : (k,) int64 array
        The scored points (indices into the scan's points, ascending).
    inverse : (m,) int64 array
        Each point's nearest scored point, as a position in ``kept`` (``inverse[kept] == arange(k)``).
    spacing : float
        The training scans' point spacing the subset was drawn at (model-frame units).
    """

    kept: np.ndarray
    inverse: np.ndarray
    spacing: float

    @property
    def points_in(self):
        """The scan's number of points m."""
        return len(self.inverse)

    def full(self, values):
        """Per-point values of the k scored points, (k, ...) -> (m, ...): each point gets its nearest scored
        point's."""
        values = np.asarray(values)
        if len(values) != len(self.kept):
            raise ValueError(f"EvidenceSample.full: {len(values)} values for {len(self.kept)} scored points")
        return values[self.inverse]


def training_spacing(model):
    """The training scans' point spacing (model-frame units) that ``model``'s kernel lengthscale was drawn from;
    None for a model without a lengthscale (a callable field), which scores every point."""
    from autodecoder.field.targets import DEFAULT_LENGTHSCALE_FACTOR

    lengthscale = getattr(model, "lengthscale", None)
    if lengthscale is None or not np.isfinite(lengthscale) or lengthscale <= 0:
        return None
    return float(lengthscale) / DEFAULT_LENGTHSCALE_FACTOR


def evidence_sample(points, spacing, seed=0):
    """The :class:`EvidenceSample` of a scan's ``points`` (m, 3) at the point ``spacing``, or None when the scan
    is scored on every point (no ``spacing``, or the subset would keep at least ``SAMPLE_BELOW`` of the points).

    The subset's size is m (d / ``spacing``)^2 for the scan's own spacing d (:func:`autodecoder.field.targets.
    point_spacing`, measured on up to ``SPACING_POINTS`` of its points); its points are drawn with ``seed``."""
    from autodecoder.field.targets import point_spacing
    from datasets.neighbours import NearestNeighbours

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    m = len(points)
    if spacing is None or m < 20 or not np.isfinite(points).all():
        return None  # too few to thin, or not a valid scan (gather_evidence's check names it)
    rng = np.random.default_rng(seed)
    probe = points if m <= SPACING_POINTS else points[rng.choice(m, SPACING_POINTS, replace=False)]
    own = point_spacing(probe) * np.sqrt(len(probe) / m)
    if not own > 0:  # most points repeated: no density to speak of, every point scored
        return None
    k = int(np.ceil(m * (own / float(spacing)) ** 2))
    if k >= SAMPLE_BELOW * m:
        return None
    kept = np.sort(rng.choice(m, max(k, 10), replace=False))
    inverse = NearestNeighbours(points[kept]).query(points, 1)[1].reshape(-1).astype(np.int64)
    inverse[kept] = np.arange(len(kept))  # a scored point is its own (ties of duplicate points aside)
    return EvidenceSample(kept, inverse, float(spacing))


def sampled_scan(scan, kept):
    """``scan`` (a Scan, a (points, normals) pair or an (m, 3) array) with only its points ``kept`` (k,) and
    everything per point taken alike (normals, labels, deviations); its name, origin and the rest as they are."""
    from datasets.validation import points_and_normals

    if hasattr(scan, "points") and hasattr(scan, "__dataclass_fields__"):
        per_point = {k: getattr(scan, k)[kept] for k in ("points", "normals", "point_labels", "point_deviation")
                     if getattr(scan, k, None) is not None}
        return replace(scan, **per_point)
    points, normals = points_and_normals(scan)
    if isinstance(scan, (tuple, list)):
        return points[kept], None if normals is None else normals[kept]
    return points[kept]
