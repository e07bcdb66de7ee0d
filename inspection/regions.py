"""Defect regions: the connected parts of a scan's anomaly map above the calibration's region level, each typed and
measured in the scan's own units, as a quality engineer writes a non-conformance report.

What a region is
    The scan's points whose anomaly map value (:mod:`inspection.maps`, standard deviations) exceeds the **region
    level**, linked into connected parts (two points are linked when one is among the other's ``REGION_NEIGHBOURS``
    nearest points and they are closer than ``LINK_SPACINGS`` times the scan's median point spacing). The level is
    drawn from the good calibration scans' maps as the verdict's threshold is drawn from their scores
    (:func:`inspection.region_level.region_level`: each good scan's largest map value, at the calibration's
    false-alarm rate, its tail Pareto where the scans are too few for an exact level), so a good scan shows a region
    at about the stated rate; a scan the statistics call defective that shows none shows its strongest one, marked
    below the level (:func:`strongest_region`). Points the score leaves out (stray returns; surface no good scan
    covered, :mod:`inspection.coverage`) are in no region.

What is measured (:func:`measure_region`)
    Each point's **signed deviation** from where good parts put the surface, positive outside (material added),
    negative inside: how far, its offset from the plane through the nearest good points on its side
    (:meth:`inspection.reference.LocalReference.surface`, the joint score's good points' term); which way, the sign
    of the field's first-order signed distance less what good scans show there (the field alone where no good scan
    saw the point's side, sought among ``WIDE_CANDIDATES`` x k nearest good points: a dent pressed deeper than a thin
    wall has the other face's points nearest). Its standard deviation is that term's own denominator (the good points' spread about the
    plane, the measurement noise). The
    deviations are averaged over each point's ``REGION_NEIGHBOURS`` nearest points (the noise of one point averaged
    down). A region's
    - **deviation**: the averaged deviation of largest magnitude, signed;
    - **footprint**: the points around it where the surface moved the same way by at least ``FOOTPRINT_FRACTION`` of
      that (grown from the region over linked points): a defect with a smooth profile has no edge, so its size is
      stated at a fraction of its depth (the truth of the benchmarks is measured the same way);
    - **area**: the footprint's surface, each point counting the area its neighbours leave it (pi r^2 / k with r
      the distance to its k-th neighbour); **extent**: the footprint's largest distance across; **volume**: the sum of
      area x |deviation| over it;
    - each with its uncertainty: the deviation's standard deviation, the area's range when the threshold moves by two
      standard deviations either way, the volume's standard deviation.
    Lengths are reported in the scan files' units (the model's frame undone: :class:`datasets.frame.Frame`), the
    centroid in the part's frame (the training collection's file coordinates) and in the scan's own (before any
    registration moved it).

Types (:func:`region_type`)
    ``missing`` where the rays carry most of the region's evidence (the sensor saw through where material belongs).
    Otherwise by the way the surface moved (out: ``bump`` or ``foreign``; in: ``dent`` or ``missing``) and by its
    **sharpness**: its fill (the footprint's volume over its area times its depth: a smooth displacement fills about
    half of that, 0.47 for the synthesis' profile, 0.55 for a paraboloid; a part with walls most of it, a
    hemispherical pit 0.67, a box on the surface 1) plus its aspect (depth over the footprint's radius: a smooth dent
    is wider than deep). At least ``SHARPNESS``: ``missing`` (in) or ``foreign`` (out). Chosen on the defects suite's
    regions of three parts, 3 seeds each (docs/results.md, "defects"; its record's ``type_rules``): the fill alone
    typed 0.896 / 1.000 / 0.792 of the found defects of fandisk / the cup / the real bunny right (missing pits typed
    dents), the aspect alone 0.964 / 0.995 / 0.984, their sum at 1.15 0.943 / 0.984 / 0.969, at 1.2 0.974 / 0.995 /
    0.984, at 1.25 0.964 / 0.995 / 0.984, at 1.3 0.958 / 1.000 / 0.990.
"""
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .evidence import kept_points
from .maps import MAP_NEIGHBOURS
from .region_level import region_level

REGION_NEIGHBOURS = 8  # points per neighbourhood: the deviation's average, a point's area, the links' length
LINK_SPACINGS = 1.5  # the longest link between two points of a region, in median distances to that neighbour
FOOTPRINT_FRACTION = 0.1  # a region's footprint: where the surface moved by at least this share of its deviation
RAY_SHARE = 0.5  # a region whose rays carry at least this share of its evidence was seen through
SHARPNESS = 1.2  # fill + depth / footprint radius at which a region has walls (a pit, an object), not a smooth slope
MIN_REGION_POINTS = 8  # a region holds at least this many points above the level (fewer: a few noisy returns)
REGION_TYPES = ("bump", "dent", "missing", "foreign")
# where a point's side of the surface had too few good points among the nearest (reference.SURFACE_CANDIDATES x k),
# they are sought among this many times k: a dent pressed deeper than a thin wall has the far face's points nearest
WIDE_CANDIDATES = 16
_MAX_EXTENT_POINTS = 600  # the extent's pairwise distances on at most this many footprint points


@dataclass
class RegionEvidence:
    """What a scan's regions are found and measured from, per point (m,), model frame.

    Attributes
    ----------
    points : (m, 3) float64
    map : (m,) float64
        The anomaly map (standard deviations).
    ray_nats : (m,) float64 or None
        Each point's ray evidence (nats) inside ``map`` (map^2 = r^2 + 2 ray_nats), None without rays.
    deviation, deviation_sd : (m,) float64
        Signed deviation from where good parts put the surface and its standard deviation (model frame units).
    eligible : (m,) bool
        Points that may belong to a region (the score's points: not stray, on covered surface).
    """

    points: np.ndarray
    map: np.ndarray
    deviation: np.ndarray
    deviation_sd: np.ndarray
    eligible: np.ndarray
    ray_nats: Optional[np.ndarray] = None


@dataclass
class DefectRegion:
    """One defect region of a scan, measured in the scan files' units (module docstring).

    Attributes
    ----------
    id : int
        0, 1, ... in the order of decreasing ``peak``.
    kind : str
        One of ``REGION_TYPES``.
    points : (p,) int array
        The scan's points that belong to it (its footprint and the map's region), in the scan's point order.
    peak : float
        Its largest anomaly map value (standard deviations).
    deviation, deviation_sd : float
        The largest signed deviation (positive outside) and its standard deviation.
    area, area_low, area_high : float
        The footprint's area and its range (squared units).
    extent : float
        The footprint's largest distance across.
    volume, volume_sd : float or None
        Sum of area x |deviation| over the footprint (cubed units; None for a region the rays found, whose points
        lie on good surface behind).
    centroid_part, centroid_scan : (3,) float arrays
        The footprint's centroid in the part's frame and in the scan's own.
    ray_share : float
        The share of its evidence the rays carry.
    fill : float or None
        ``volume`` / (``area`` x |``deviation``|) (None without a volume).
    feature : str
        The nearest named feature ('' when none were given).
    above_level : bool
        False for the strongest region of a scan called defective that shows none above the region level
        (:meth:`RegionMixin.regions_of_result`): where its evidence lies, below the level good scans pass at alpha.
    """

    id: int
    kind: str
    points: np.ndarray
    peak: float
    deviation: float
    deviation_sd: float
    area: float
    area_low: float
    area_high: float
    extent: float
    volume: Optional[float]
    volume_sd: Optional[float]
    centroid_part: np.ndarray
    centroid_scan: np.ndarray
    ray_share: float = 0.0
    fill: Optional[float] = None
    feature: str = ""
    above_level: bool = True

    @property
    def radius(self):
        """The radius of a disc of the footprint's area: sqrt(area / pi)."""
        return float(np.sqrt(self.area / np.pi))

    def row(self):
        """The region as a ``defects.csv`` row (without the scan's columns): plain floats and strings."""
        part, scan = (np.asarray(c, dtype=np.float64) for c in (self.centroid_part, self.centroid_scan))
        return {"region": self.id, "type": self.kind, "deviation": self.deviation, "deviation_sd": self.deviation_sd,
                "area": self.area, "area_low": self.area_low, "area_high": self.area_high, "extent": self.extent,
                "volume": self.volume, "volume_sd": self.volume_sd, "points": int(len(self.points)),
                "peak": self.peak, "x": part[0], "y": part[1], "z": part[2],
                "scan_x": scan[0], "scan_y": scan[1], "scan_z": scan[2], "fill": self.fill, "ray_share": self.ray_share,
                "feature": self.feature, "above_level": self.above_level}


@dataclass
class Units:
    """How the scored frame's positions and lengths go back to the scan files' units.

    The scored frame is the model's frame (:class:`datasets.frame.Frame`: x_model = ``frame_scale`` (x_file -
    ``center``)), after the registration ``transform`` (4, 4; None: none) moved the scan there. A length in the scored
    frame is ``length_scale`` = ``frame_scale`` x the registration's own scale (1 for a rigid one) times the same
    length in file units."""

    frame_scale: float = 1.0
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    transform: Optional[np.ndarray] = None

    @classmethod
    def of(cls, model, transform=None):
        """The units of ``model``'s frame (:attr:`autodecoder.latent.model.LatentModel.frame`; a model without one:
        the identity) after the registration ``transform``."""
        frame = getattr(model, "frame", None)
        if frame is None:
            return cls(1.0, np.zeros(3), transform)
        return cls(float(frame.scale), np.asarray(frame.center, dtype=np.float64), transform)

    @property
    def length_scale(self):
        scale = self.frame_scale
        if self.transform is not None:
            scale *= float(abs(np.linalg.det(np.asarray(self.transform)[:3, :3]))) ** (1.0 / 3.0)
        return scale

    def to_part(self, points):
        """Scored-frame points (p, 3) in the part's file coordinates (the training collection's)."""
        return np.asarray(points, dtype=np.float64).reshape(-1, 3) / self.frame_scale + self.center

    def to_scan(self, points):
        """Scored-frame points (p, 3) in the scan's own file coordinates (the registration undone)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.transform is not None:
            t = np.asarray(self.transform, dtype=np.float64)
            p = (p - t[:3, 3]) @ np.linalg.inv(t[:3, :3]).T
        return p / self.frame_scale + self.center


def map_maximum(evidence: RegionEvidence, geometry=None):
    """The level below which a scan shows a region: the largest map value t such that its eligible points with map
    values of at least t hold a connected part of at least ``MIN_REGION_POINTS`` points (0 when none does). What
    :func:`region_level` ranks: a scan shows a region (:func:`find_regions`) exactly when this exceeds the level, as
    a scan is flagged when its score exceeds the threshold. Found by bisection (a part only grows as the level
    falls)."""
    values = evidence.map[evidence.eligible]
    if len(values) < MIN_REGION_POINTS:
        return 0.0
    geometry = geometry or _Geometry(evidence.points)
    candidates = np.unique(values)[::-1]  # the answer is one of the map's values (just below it)

    def shows(i):  # a region of enough points above the level just below candidates[i]
        return len(_large_components(geometry, evidence.eligible & (evidence.map >= candidates[i]))) > 0

    lo, hi = 0, len(candidates) - 1  # shows(hi) is True (every eligible point), unless too few are linked
    if not shows(hi):
        return 0.0
    while lo < hi:  # the first (highest) candidate that shows one
        mid = (lo + hi) // 2
        if shows(mid):
            hi = mid
        else:
            lo = mid + 1
    return float(candidates[lo])


def _large_components(geometry, mask):
    """The connected parts of ``mask`` with at least ``MIN_REGION_POINTS`` points."""
    return [c for c in geometry.components(mask) if len(c) >= MIN_REGION_POINTS]


def find_regions(evidence: RegionEvidence, level, units=None, features=None):
    """A scan's defect regions (module docstring).

    Parameters
    ----------
    evidence : RegionEvidence
    level : float
        The region level (standard deviations; +inf or None: no region).
    units : Units, optional
        Back to the scan files' units (default: the model frame's).
    features : dict of str -> (3,) array, optional
        Named places in the part's frame: each region's nearest one is its ``feature``.

    Returns
    -------
    regions : list of DefectRegion
        In the order of decreasing peak.
    labels : (m,) int array
        Each point's region id, -1 outside every region.
    """
    m = len(evidence.points)
    labels = np.full(m, -1, dtype=np.int64)
    if level is None or not np.isfinite(level) or m < 2:
        return [], labels
    units = units or Units()
    geometry = _Geometry(evidence.points)
    components = _large_components(geometry, evidence.eligible & (evidence.map > level))
    smoothed = geometry.smooth(evidence.deviation)
    smoothed_sd = np.sqrt(geometry.smooth(evidence.deviation_sd ** 2) / geometry.k)
    measured = [measure_region(evidence, geometry, members, smoothed, smoothed_sd, units)
                for members in _merged(geometry, components, smoothed, smoothed_sd)]
    measured.sort(key=lambda r: -r.peak)
    for i, region in enumerate(measured):
        region.id = i
        labels[region.points[labels[region.points] < 0]] = i
        if features:
            names = list(features)
            where = np.array([features[n] for n in names], dtype=np.float64).reshape(-1, 3)
            region.feature = names[int(np.argmin(np.linalg.norm(where - region.centroid_part, axis=1)))]
    return measured, labels


def strongest_region(evidence: RegionEvidence, floor, units=None, features=None):
    """The region of largest peak among the scan's regions above ``floor`` (:func:`find_regions`), alone, its id 0
    and ``above_level`` False: ``([region], labels)``, or ``([], labels)`` when none rises above ``floor``."""
    regions, labels = find_regions(evidence, floor, units, features)
    if not regions:
        return [], labels
    top = regions[0]
    labels = np.where(labels == top.id, 0, -1)
    top.id, top.above_level = 0, False
    return [top], labels


def point_areas(points):
    """Each point's share of the surface (m,), in squared units of the (m, 3) ``points``: pi r^2 / (k - 1) with r
    the distance to its k-th nearest point (itself the first), k = ``REGION_NEIGHBOURS`` (the k - 1 others share the
    disc of radius r); what a region's area sums."""
    from datasets.neighbours import NearestNeighbours

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return _areas(NearestNeighbours(points).query(points, min(REGION_NEIGHBOURS, len(points)))[0])


def _areas(dist):
    return np.pi * dist[:, -1] ** 2 / max(dist.shape[1] - 1, 1)


class _Geometry:
    """A scan's neighbourhoods: its ``REGION_NEIGHBOURS`` nearest points (the deviation's average, each point's
    area) and its links: every pair of points closer than ``LINK_SPACINGS`` times the median distance to the
    ``REGION_NEIGHBOURS``-th neighbour (a radius, so that links are mutual and a point in a sparse spot is not cut
    off)."""

    def __init__(self, points):
        from scipy.sparse import coo_matrix
        from scipy.spatial import cKDTree

        from datasets.neighbours import NearestNeighbours

        self.points = np.asarray(points, dtype=np.float64)
        self.k = min(REGION_NEIGHBOURS, len(self.points))
        self.index = NearestNeighbours(self.points)
        dist, self.idx = self.index.query(self.points, self.k)
        self.area = _areas(dist)
        pairs = cKDTree(self.points).query_pairs(LINK_SPACINGS * float(np.median(dist[:, -1])), output_type="ndarray")
        m = len(self.points)
        both = np.r_[pairs, pairs[:, ::-1]] if len(pairs) else np.zeros((0, 2), dtype=np.intp)
        self.links = coo_matrix((np.ones(len(both), dtype=bool), (both[:, 0], both[:, 1])), shape=(m, m)).tocsr()

    def smooth(self, values):
        """The mean of ``values`` (m,) over each point's neighbourhood (itself included)."""
        return np.asarray(values, dtype=np.float64)[self.idx].mean(axis=1)

    def neighbours(self, points):
        """The points linked to any of ``points`` (indices), unsorted, with repeats."""
        rows = self.links[np.asarray(points, dtype=np.intp)]
        return rows.indices

    def components(self, mask):
        """The connected parts (lists of point indices) of the points in ``mask`` (m,) bool."""
        from scipy.sparse.csgraph import connected_components

        inside = np.flatnonzero(mask)
        if len(inside) == 0:
            return []
        _, label = connected_components(self.links[inside][:, inside], directed=False)
        return [inside[label == c] for c in np.unique(label)]

    def grow(self, start, allowed):
        """The points reachable from ``start`` (indices) over links through points where ``allowed`` (m,) bool."""
        reached = np.zeros(len(self.points), dtype=bool)
        reached[start] = True
        front = np.asarray(start, dtype=np.intp)
        while len(front):
            nb = self.neighbours(front)
            nb = np.unique(nb[allowed[nb] & ~reached[nb]])
            reached[nb] = True
            front = nb
        return np.flatnonzero(reached)


def _merged(geometry, components, smoothed, smoothed_sd):
    """The map's connected parts (lists of point indices) merged where they are one defect: where one's footprint
    (:func:`_footprint`), with the patches its points' map values were taken over (:mod:`inspection.maps`), meets
    another's. A defect's rim, where its map wavers about the level, leaves fragments of it; an object standing off
    the surface leaves a halo on the surface around it, whose patches reach its points."""
    if len(components) < 2:
        return components
    territory = []
    for members in components:
        _, footprint, _ = _footprint(geometry, members, smoothed, smoothed_sd)
        around = np.union1d(members, footprint)
        patches = geometry.index.query(geometry.points[around], min(MAP_NEIGHBOURS, len(geometry.points)))[1]
        territory.append(np.union1d(around, patches.reshape(-1)))
    parent = list(range(len(components)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    owner = np.full(len(geometry.points), -1)
    for i, points in enumerate(territory):
        for j in np.unique(owner[points][owner[points] >= 0]):
            parent[root(int(j))] = root(i)
        owner[points] = i
    groups = {}
    for i, members in enumerate(components):
        groups.setdefault(root(i), []).append(members)
    return [np.unique(np.concatenate(g)) for g in groups.values()]


def _footprint(geometry, members, smoothed, smoothed_sd):
    """(the point of largest |averaged deviation| among ``members``, the footprint, whether that deviation is
    significant): the points linked to the members' where the surface moved the peak's way by at least
    ``FOOTPRINT_FRACTION`` of it (module docstring); the members themselves when it is not significant (more than
    two standard deviations)."""
    peak_at = members[int(np.argmax(np.abs(smoothed[members])))]
    along = np.sign(smoothed[peak_at] or 1.0) * smoothed
    if not abs(smoothed[peak_at]) > 2.0 * smoothed_sd[peak_at]:
        return peak_at, members, False
    threshold = FOOTPRINT_FRACTION * abs(smoothed[peak_at])
    footprint = geometry.grow(members[along[members] >= threshold], along >= threshold)
    return peak_at, (footprint if len(footprint) else np.array([peak_at])), True


def measure_region(evidence, geometry, members, smoothed, smoothed_sd, units):
    """One :class:`DefectRegion` (id 0, no feature) of the map's region ``members`` (point indices): its deviation,
    footprint, area, extent, volume and type (module docstring)."""
    peak_at, footprint, significant = _footprint(geometry, members, smoothed, smoothed_sd)
    deviation, sd = float(smoothed[peak_at]), float(smoothed_sd[peak_at])
    along = (1.0 if deviation >= 0 else -1.0) * smoothed  # how far each point moved the region's way
    threshold = FOOTPRINT_FRACTION * abs(deviation)
    if significant:
        low = geometry.grow(np.intersect1d(footprint, np.flatnonzero(along - 2 * smoothed_sd >= threshold)),
                            along - 2 * smoothed_sd >= threshold)
        high = geometry.grow(footprint, along + 2 * smoothed_sd >= threshold)
        volume = float(np.sum(geometry.area[footprint] * np.abs(smoothed[footprint]))) / units.length_scale ** 3
        volume_sd = float(np.sqrt(np.sum((geometry.area[footprint] * smoothed_sd[footprint]) ** 2))) / \
            units.length_scale ** 3
    else:
        footprint, low, high, volume, volume_sd = members, members, members, None, None
    ray_share = _ray_share(evidence, members)
    area = float(geometry.area[footprint].sum())
    region = DefectRegion(
        id=0, kind="", points=np.union1d(members, footprint), peak=float(evidence.map[members].max()),
        deviation=deviation / units.length_scale, deviation_sd=sd / units.length_scale,
        area=area / units.length_scale ** 2, area_low=float(geometry.area[low].sum()) / units.length_scale ** 2,
        area_high=float(geometry.area[high].sum()) / units.length_scale ** 2,
        extent=_extent(geometry.points[footprint]) / units.length_scale, volume=volume, volume_sd=volume_sd,
        centroid_part=units.to_part(geometry.points[footprint].mean(0))[0],
        centroid_scan=units.to_scan(geometry.points[footprint].mean(0))[0], ray_share=ray_share)
    if volume is not None and area > 0:
        region.fill = float(volume * units.length_scale ** 3 / (area * abs(deviation)))
    region.kind = region_type(region)
    if region.kind == "missing" and ray_share >= RAY_SHARE:
        region.volume = region.volume_sd = None  # its points lie on good surface behind the hole
    return region


def region_type(region):
    """``region``'s type from its measurements (module docstring): one of ``REGION_TYPES``."""
    if region.ray_share >= RAY_SHARE:
        return "missing"
    sharp = region.fill is not None and region.fill + abs(region.deviation) / max(region.radius, 1e-300) >= SHARPNESS
    if region.deviation >= 0:
        return "foreign" if sharp else "bump"
    return "missing" if sharp else "dent"


def _ray_share(evidence, members):
    """The share of the region's evidence (sum of map^2 over its points) that the rays carry (2 nats a point)."""
    if evidence.ray_nats is None:
        return 0.0
    total = float(np.sum(evidence.map[members] ** 2))
    return float(np.sum(2.0 * np.maximum(evidence.ray_nats[members], 0.0))) / total if total > 0 else 0.0


def _extent(points):
    """The largest distance between two of (p, 3) points (on a subsample of ``_MAX_EXTENT_POINTS``)."""
    if len(points) < 2:
        return 0.0
    if len(points) > _MAX_EXTENT_POINTS:
        points = points[np.linspace(0, len(points) - 1, _MAX_EXTENT_POINTS).astype(int)]
    from scipy.spatial.distance import pdist

    return float(pdist(points).max())


def region_evidence(result, settings, reference):
    """The :class:`RegionEvidence` of a scored scan: its :class:`inspection.scoring.ScanResult` ``result`` (with its
    ``evidence``; with rays weighed by the calibration, :func:`inspection.scoring.weigh_rays`, where it has any), the
    settings in force and the per-location ``reference`` (its statistics give where good parts put the surface).
    None when there is nothing to measure: no reference (a point score without one) or no evidence."""
    from .maps import map_values
    from .reference import total_variance
    from .scores import noise_floor

    ev = getattr(result, "evidence", None)
    if reference is None or ev is None or ev.value is None:
        return None
    values, _ = map_values(settings, ev, result)
    nats = None
    if settings.rays and result.rays is not None:
        nats = result.ray_point_nats if result.ray_point_nats is not None else result.rays.point_surprisal
    m_ref, s_ref = reference.stats(ev.points)
    noise = noise_floor(ev.field, settings.noise)
    # how far: the offset from the plane through the nearest good points on the point's side (the good points' term:
    # within a few % of the synthesis' truth, where the field's first-order distance overstated dents and bumps
    # up to twice, its gradient fading off the surface); which way: the field's. The field's distance where no good
    # scan saw the point's side.
    offset, spread, supported = reference.surface(ev.points, ev.normals, with_support=True)
    if ev.normals is not None and not supported.all():  # a dent deeper than a thin wall: its side, sought farther
        again = np.flatnonzero(~supported)
        far = reference.surface(ev.points[again], ev.normals[again], with_support=True,
                                candidates=WIDE_CANDIDATES)
        offset[again], spread[again], supported[again] = far
    field_deviation = np.asarray(ev.value, np.float64) - m_ref
    deviation = np.where(supported, np.abs(offset) * np.where(field_deviation < 0, -1.0, 1.0), field_deviation)
    variance = np.where(supported, total_variance(spread, 0.0, noise ** 2, ev.grazing, 0.0, reference.grazing_scale),
                        total_variance(s_ref ** 2, ev.variance, noise ** 2, ev.grazing, reference.variance_scale,
                                       reference.grazing_scale))
    eligible = kept_points(ev.stray, len(ev.points))
    coverage = result.coverage
    if coverage is not None and not coverage.counted_all:
        eligible = eligible & coverage.covered
    return RegionEvidence(points=np.asarray(ev.points, dtype=np.float64), map=np.asarray(values, np.float64),
                          deviation=deviation, deviation_sd=np.sqrt(variance),
                          eligible=eligible, ray_nats=None if nats is None else np.asarray(nats, np.float64))


def good_map_maxima(results, references, settings, combination=None):
    """The largest map value (:func:`map_maximum`) of each good calibration scan's result (its rays weighed by
    ``combination`` first, in place), against its own reference; None when the results have nothing to measure
    (no reference): the calibration then stores no region level."""
    from .scoring import weigh_rays

    maxima = []
    for result, reference in zip(results, references):
        if combination is not None and result.rays is not None:
            weigh_rays(result, combination)
        evidence = region_evidence(result, settings, reference)
        if evidence is None:
            return None
        maxima.append(map_maximum(evidence))
    return np.asarray(maxima, dtype=np.float64)


def read_features(path):
    """Named features of the part from a CSV file with columns ``name, x, y, z`` (a header row; the part's frame, the
    scan files' units): ``{name: (3,) array}``. A missing file, a missing column, a non-number or no rows is one
    ValueError naming the file."""
    import csv
    from pathlib import Path

    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the features file ({exc.strerror or exc})") from None
    if not rows or not {"name", "x", "y", "z"} <= set(rows[0]):
        raise ValueError(f"{path}: a features file needs a header 'name,x,y,z' and one row per feature")
    features = {}
    for i, row in enumerate(rows, start=2):
        try:
            where = np.array([float(row[k]) for k in ("x", "y", "z")])
        except (TypeError, ValueError):
            where = np.full(3, np.nan)
        if not (row["name"] or "").strip() or not np.all(np.isfinite(where)):
            raise ValueError(f"{path}: line {i}: a feature needs a name and three finite coordinates, got {row}")
        features[row["name"].strip()] = where
    return features


class RegionMixin:
    """The defect regions of a fitted :class:`inspection.Inspector` (its ``region_maxima_`` and ``region_roles_``,
    set by the calibration; None: a calibration that did not measure its good scans' maps, and no regions)."""

    def region_level(self, scan=None):
        """The region level (standard deviations) of ``scan``'s part at the inspector's ``alpha``
        (:func:`region_level`); None when the calibration stores no map maxima."""
        one = self.for_scan(scan)
        maxima = getattr(one, "region_maxima_", None)
        if maxima is None:
            return None
        key = (float(one.alpha), len(maxima))
        cached = getattr(one, "_region_level_cache", None)
        if cached is None or cached[0] != key:
            cached = (key, region_level(maxima, one.alpha, getattr(one, "region_roles_", None)))
            one._region_level_cache = cached
        return cached[1]

    def regions_of_result(self, scan, result, features=None, defective=False):
        """The defect regions (:func:`find_regions`) of ``scan`` already inspected into ``result``
        (:meth:`inspect`): ``(regions, labels)``; ``([], None)`` when its calibration has no region level or its
        point score measures no deviation. A scan the statistics call ``defective`` that shows no region above the
        level shows its strongest one (:func:`strongest_region`, ``above_level`` False) down to the median of the
        good calibration scans' map maxima: the verdict says there is a defect, the region says where."""
        one = self.for_scan(scan)
        level = one.region_level(scan)
        evidence = None if level is None else region_evidence(result, one.settings_, one.reference_)
        if evidence is None:
            return [], None
        units = Units.of(one.model, result.transform)
        regions, labels = find_regions(evidence, level, units, features)
        if regions or not defective:
            return regions, labels
        return strongest_region(evidence, float(np.median(one.region_maxima_)), units, features)

    def defect_regions(self, scan, index=0, features=None):
        """Inspect ``scan`` and return its defect regions and each point's region id: ``(regions, labels)``
        (:meth:`regions_of_result`, ``defective`` from its verdict, as :func:`inspection.job.inspect_scan` has it)."""
        one = self.for_scan(scan)
        result = one.inspect(scan, index)
        (verdict,), _ = one.verdicts_from_results([result], [scan])
        return one.regions_of_result(scan, result, features, defective=verdict == "defective")
