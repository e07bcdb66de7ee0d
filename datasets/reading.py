"""How a scanner file becomes a scan: the rules an import applied, recorded so that a file read later reads the same.

A collection's import turns each file into points and normals by a few rules (a voxel grid or a random subset, stray
points dropped or kept, the file's own normals used or estimated again, and how the signs of normals estimated
without a sensor origin are decided). :class:`Reading` holds those rules; the importers record it in the collection's
provenance (``provenance['reading']``), inspection's calibration carries it (``Inspector.reading_``), and every file
read for scoring (``score --data FOLDER``, ``watch``, :func:`inspection.loading.load_scans`) is read by the same
rules, through the same functions (:func:`datasets.importer.load_source`, :func:`datasets.importer.read_scan`). So one file gives the
same points whether it was imported first or read from a folder.

The signs of normals estimated without a sensor origin are a guess (the estimator's consistent orientation, pointing
away from the cloud's centroid); the public template layouts (Real3D-AD, Anomaly-ShapeNet) decide them instead by the
good part's surface (:func:`datasets.layouts.orient_by_surface`): at import by the templates, and when a scan is
scored by the good scans' surface the calibration holds. Such a scan is marked ``Scan.extra[SIGNS_KEY] ==
SIGNS_FROM_SURFACE`` when it is read for scoring, and inspection decides its signs from its points and its normals'
lines alone, so that the imported scan (signed by the templates) and the file read from a folder (signed by the
estimator) end the same.
"""
import zlib
from dataclasses import asdict, dataclass, fields
from typing import Optional

import numpy as np

READING_VERSION = 1
SIGNS_KEY = "normal_signs"  # Scan.extra key: how the scan's normal signs are to be decided when it is scored
SIGNS_FROM_SURFACE = "surface"  # ... by the good part's surface (datasets.layouts.orient_by_surface)

_CHOICES = {"file_normals": ("used", "ignored"), "normals": ("before downsampling", "after downsampling"),
            "signs": ("estimated", SIGNS_FROM_SURFACE), "strays": ("kept", "dropped")}
_TEMPLATE_LAYOUTS = ("real3d-ad", "anomaly-shapenet")


@dataclass(frozen=True)
class Reading:
    """The rules that turn one scanner file into a scan's points and normals (file units).

    Attributes
    ----------
    voxel : float > 0 or None
        Voxel side (file units) of :func:`datasets.ingest.voxel_downsample`; None: no voxel grid.
    points : int >= 3 or None
        A seeded random subset of this many points instead (files with fewer keep all); None: all points.
    seed : int
        Seeds the subset (:func:`subset`), together with the file's own points, so a file's subset depends on the
        file alone, not on its name, its place in a tree or the other files read with it.
    file_normals : {'used', 'ignored'}
        A file's own normals (PLY, six-column text, npz): used (normalised; rows with a zero or non-finite normal
        dropped), or ignored and estimated from the points (the public layouts, as their loaders read xyz only).
    normals : {'before downsampling', 'after downsampling'}
        Normals that are estimated are estimated on the full cloud and averaged per voxel (the tree import), or on
        the downsampled points (the public layouts).
    signs : {'estimated', 'surface'}
        The signs of normals estimated without a sensor origin: the estimator's own (consistent, away from the
        centroid), or decided by the good part's surface ('surface': module docstring). 'surface' needs
        ``file_normals='ignored'``, so that every scan without a sensor origin has estimated normals.
    strays : {'kept', 'dropped'}
        Stray points (:func:`datasets.outliers.stray_points`, found after downsampling) dropped from each scan.
    """

    voxel: Optional[float] = None
    points: Optional[int] = None
    seed: int = 0
    file_normals: str = "used"
    normals: str = "before downsampling"
    signs: str = "estimated"
    strays: str = "kept"

    def __post_init__(self):
        for name, allowed in _CHOICES.items():
            value = getattr(self, name)
            if value not in allowed:
                raise ValueError(f"reading: {name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        if self.voxel is not None and not (isinstance(self.voxel, (int, float)) and np.isfinite(self.voxel)
                                           and self.voxel > 0):
            raise ValueError(f"reading: voxel must be a finite number > 0 or None, got {self.voxel!r}")
        if self.points is not None and not (int(self.points) == self.points and self.points >= 3):
            raise ValueError(f"reading: points must be a whole number >= 3 or None, got {self.points!r}")
        if self.voxel is not None and self.points is not None:
            raise ValueError("reading: a voxel side or a number of points, not both")
        if self.signs == SIGNS_FROM_SURFACE and self.file_normals != "ignored":
            raise ValueError("reading: signs 'surface' needs file_normals 'ignored' (every scan without a sensor "
                             "origin must have estimated normals)")

    def as_dict(self):
        """Plain JSON values, with the format ``version`` (what provenance and calibrations store)."""
        return {"version": READING_VERSION, **asdict(self)}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`as_dict`; None gives the default reading (a folder read without a record).

        Raises
        ------
        ValueError
            Another format version, unknown keys or values out of range (naming them).
        """
        if d is None:
            return cls()
        if isinstance(d, Reading):
            return d
        if not isinstance(d, dict) or d.get("version") != READING_VERSION:
            version = d.get("version") if isinstance(d, dict) else d
            raise ValueError(f"reading record of unsupported version {version!r} (this toolkit reads version "
                             f"{READING_VERSION})")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known - {"version"})
        if unknown:
            raise ValueError(f"reading record with unknown keys {unknown}")
        return cls(**{k: v for k, v in d.items() if k in known})

    @classmethod
    def from_provenance(cls, provenance):
        """The reading a collection's import applied, from its provenance: the recorded ``reading``, or for a
        collection imported before it was recorded what its import then did (a template layout's scans without a
        sensor origin had estimated normals whose signs the templates decided; a tree kept the files' normals)."""
        provenance = provenance if isinstance(provenance, dict) else {}
        if provenance.get("reading") is not None:
            return cls.from_dict(provenance["reading"])
        voxel, points = provenance.get("voxel"), provenance.get("points")
        common = dict(voxel=voxel, points=None if voxel is not None else points, seed=int(provenance.get("seed", 0)))
        if provenance.get("layout") in _TEMPLATE_LAYOUTS:
            return cls(**common, file_normals="ignored", normals="after downsampling", signs=SIGNS_FROM_SURFACE)
        if provenance.get("layout") == "mvtec3d":
            return cls(**common, file_normals="ignored", normals="after downsampling")
        stray = provenance.get("stray_points")
        dropped = isinstance(stray, dict) and bool(stray.get("dropped"))
        return cls(**common, strays="dropped" if dropped else "kept")


def subset(points, n, seed):
    """A seeded random subset of ``n`` points of a cloud (all of them when it has no more), in file order.

    The generator is seeded with (``seed``, crc32 of the points' bytes), so the subset is a function of the file's
    points and ``seed`` only.

    Parameters
    ----------
    points : (N, 3) float64 array
    n : int
    seed : int

    Returns
    -------
    keep : (m,) int array
        Row indices, increasing; m = min(n, N).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) <= n:
        return np.arange(len(points))
    rng = np.random.default_rng([int(seed), zlib.crc32(points.tobytes())])
    return np.sort(rng.choice(len(points), size=int(n), replace=False))


def downsample(points, normals, labels, reading):
    """``reading``'s voxel grid or random subset applied to a cloud (file units); labels follow the points.

    Parameters
    ----------
    points : (N, 3) float64 array
    normals : (N, 3) float64 array
        Unit normals (zeros when they are estimated afterwards).
    labels : (N,) uint8 array or None
    reading : Reading

    Returns
    -------
    points (M, 3), normals (M, 3), labels (M,) or None
    """
    from .ingest import voxel_downsample

    if reading.voxel is not None:
        return voxel_downsample(points, normals, labels, reading.voxel)
    if reading.points is not None:
        keep = subset(points, reading.points, reading.seed)
        return points[keep], normals[keep], None if labels is None else labels[keep]
    return points, normals, labels


def downsample_values(points, values, reading):
    """A per-point quantity (a ground-truth deviation) through :func:`downsample` of the same ``points``: the
    voxel's mean (:func:`datasets.ingest.voxel_mean`) or the subset's rows, row for row with the points it returns.

    Parameters
    ----------
    points : (N, 3) float64 array
        The points given to :func:`downsample`.
    values : (N,) float array
    reading : Reading

    Returns
    -------
    (M,) array
    """
    from .ingest import voxel_mean

    if reading.voxel is not None:
        return voxel_mean(points, values, reading.voxel)
    if reading.points is not None:
        return values[subset(points, reading.points, reading.seed)]
    return values


def mark_signs(scan, reading):
    """Mark ``scan`` (in place) as one whose normal signs the good surface decides when it is scored, when
    ``reading`` says so for a scan without a sensor origin (``scan.extra[SIGNS_KEY]``). Returns ``scan``."""
    if reading.signs == SIGNS_FROM_SURFACE and scan.sensor_origin is None:
        scan.extra = {**(scan.extra or {}), SIGNS_KEY: SIGNS_FROM_SURFACE}
    return scan
