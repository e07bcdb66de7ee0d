"""The public 3D anomaly benchmarks' class folders (Real3D-AD, Anomaly-ShapeNet, MVTec 3D-AD), read as their loaders do.

Each layout is described, with the loader it follows, in ``docs/public_layouts.md``. In short (one class folder):

- ``real3d-ad``: ``train/*template*.pcd`` (complete clouds), ``test/*.pcd`` (``temp`` in the name: not a sample;
  ``good`` in the name: good), ``gt/<stem>.txt`` (``x y z label``: for a defective sample the txt IS the labelled
  cloud, the .pcd is not read). Millimetres.
- ``anomaly-shapenet``: ``train/*template*.pcd``, ``test/*.pcd`` (good ones named ``positive*``), ``GT/<stem>.txt``
  (x, y, z, label; comma or space separated; rows matched to the .pcd's points by coordinates). Unit scale.
- ``mvtec3d``: ``{train,validation}/good/xyz/NNN.tiff``, ``test/<good|defect>/xyz/NNN.tiff`` and ``gt/NNN.png``;
  organised H x W x 3 clouds in metres in the sensor's frame (so the sensor is at the origin), zeros = no point; the
  table plane is removed (RANSAC plane on the image border, then the largest DBSCAN cluster, as the Back-to-the-Feature
  / M3DM preprocessing does) unless ``keep_plane``.

The templates of the first two are turned into partial views (:mod:`datasets.templates`): split 'train' for training,
'validation' for calibration. Large clouds are voxel-downsampled with one voxel size for the whole class, set from
the training clouds' own point spacing so that a scan keeps about ``max_points`` points; labels follow the points.
"""
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .normals import orient_consistently

log = logging.getLogger(__name__)

LAYOUT_SIGNS = {
    "real3d-ad": "train/*template*.pcd, test/*.pcd, gt/*.txt",
    "anomaly-shapenet": "train/*template*.pcd, test/positive*.pcd, GT/*.txt",
    "mvtec3d": "train/good/xyz/*.tiff, test/<defect>/{xyz,gt}/",
    "tree": "train/good/*, test/<defect>/*, ground_truth/<defect>/*.txt (datasets.importer)",
}
LAYOUTS = tuple(LAYOUT_SIGNS)
UNITS = {"real3d-ad": "mm", "anomaly-shapenet": "unit scale", "mvtec3d": "m"}

# MVTec 3D-AD table-plane removal: the constants of the Back-to-the-Feature preprocessing (Horwitz & Hoshen 2022,
# utils/preprocessing.py), in metres: plane fitted by RANSAC to a 10-pixel image border, points within 5 mm of it
# dropped, then the largest DBSCAN cluster (eps 6 mm, 30 points) kept.
BORDER_PIXELS = 10
PLANE_FIT_THRESHOLD = 0.004
PLANE_RANSAC_N = 50
PLANE_ITERATIONS = 1000
PLANE_DISTANCE = 0.005
CLUSTER_EPS = 0.006
CLUSTER_MIN_POINTS = 30
_CLUSTER_SUBSAMPLE = 5000  # DBSCAN on more points than this runs on a seeded subset; the rest take their nearest's

DEFAULT_VIEWS = 16
DEFAULT_VALIDATION_VIEWS = 4
DEFAULT_MAX_POINTS = 20000
_SPACING_SAMPLE = 4000  # points whose nearest-neighbour distance estimates a cloud's spacing
# template normals that vote on the sign of each test point's normal (orient_like_templates)
TEMPLATE_NORMAL_VOTES = 8
_VOXEL_SAMPLE_FILES = 8  # training files (evenly spread) whose spacing sets the voxel size


@dataclass(frozen=True)
class PublicSource:
    """One file of a public layout and what the layout says about it.

    ``role``: 'template' (complete cloud, rendered into views), 'cloud' (a scan: .pcd) or 'organized' (MVTec TIFF).
    ``ground_truth``: the txt (Real3D-AD, Anomaly-ShapeNet) or png (MVTec 3D-AD) of a defective sample.
    """

    path: Path
    name: str
    split: str
    label: str
    defect: str
    role: str
    layout: str
    ground_truth: Optional[Path] = None


# ---- which layout --------------------------------------------------------------------------------------------------
def _templates(root):
    train = root / "train"
    if not train.is_dir():
        return []
    return sorted(p for p in train.glob("*.pcd") if "template" in p.name)


def detect_layout(root):
    """The layout of a class folder: one of :data:`LAYOUTS` ('tree' when no public layout's signs are there)."""
    root = Path(root)
    if any(root.glob("train/good/xyz/*.tif*")) or any(root.glob("test/*/xyz/*.tif*")):
        return "mvtec3d"
    if _templates(root) and (root / "test").is_dir():
        names = {p.name for p in root.iterdir()}
        if "GT" in names or any(root.glob("test/positive*.pcd")):
            return "anomaly-shapenet"
        return "real3d-ad"
    return "tree"


def resolve_layout(root, layout="auto"):
    """``layout`` checked ('auto': detected). Raises ValueError naming the known layouts for an unknown name."""
    if layout == "auto":
        return detect_layout(root)
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; known layouts: auto, "
                         + "; ".join(f"{k} ({v})" for k, v in LAYOUT_SIGNS.items()))
    return layout


# ---- finding files -------------------------------------------------------------------------------------------------
def _defect_from_stem(stem, layout):
    """Defect type from a test file's stem: Real3D-AD '482_bulge_cut' -> 'bulge'; Anomaly-ShapeNet 'concavity3' ->
    'concavity'."""
    if layout == "anomaly-shapenet":
        return re.sub(r"[_\-\d]+$", "", stem) or "defect"
    words = [w for w in re.split(r"[_\-\s]+", stem) if w and not w.isdigit() and w not in ("cut", "copy")]
    return "_".join(words) or "defect"


def find_public_sources(root, layout):
    """The files of a class folder of a public layout, in a fixed order (split, name).

    Parameters
    ----------
    root : str or Path
        The class folder (e.g. ``Real3D-AD-PCD/airplane``, ``Anomaly-ShapeNet/pcd/ashtray0``, ``mvtec_3d/bagel``).
    layout : {'real3d-ad', 'anomaly-shapenet', 'mvtec3d'}

    Returns
    -------
    list of PublicSource

    Raises
    ------
    ValueError
        No files where the layout has them, or a defective sample without its ground truth (names the file).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    if layout == "mvtec3d":
        return _mvtec_sources(root)
    if layout not in ("real3d-ad", "anomaly-shapenet"):
        raise ValueError(f"find_public_sources: layout {layout!r} is not a public layout")
    templates = _templates(root)
    if not templates:
        raise ValueError(f"{root}: no train/*template*.pcd files ({layout} layout: {LAYOUT_SIGNS[layout]})")
    sources = [PublicSource(p, p.stem, "train", "good", "", "template", layout) for p in templates]
    gt_dir = root / ("gt" if layout == "real3d-ad" else "GT")
    tests = sorted((root / "test").glob("*.pcd"))
    for p in tests:
        if layout == "real3d-ad" and "temp" in p.name:  # Real3D-AD's loader skips these: not test samples
            continue
        good = "good" in p.name if layout == "real3d-ad" else p.name.startswith("positive")
        if good:
            sources.append(PublicSource(p, f"test/good/{p.stem}", "test", "good", "", "cloud", layout))
            continue
        gt = gt_dir / f"{p.stem}.txt"
        if not gt.is_file():
            raise ValueError(f"{p}: a defective test sample ({layout}) without its ground truth {gt}")
        defect = _defect_from_stem(p.stem, layout)
        sources.append(PublicSource(p, f"test/{defect}/{p.stem}", "test", "defective", defect, "cloud", layout, gt))
    if len(sources) == len(templates):
        raise ValueError(f"{root}: no test/*.pcd samples ({layout} layout: {LAYOUT_SIGNS[layout]})")
    return sources


def _mvtec_sources(root):
    sources = []
    for split in ("train", "validation", "test"):
        sdir = root / split
        if not sdir.is_dir():
            continue
        for cdir in sorted(d for d in sdir.iterdir() if d.is_dir() and not d.name.startswith(".")):
            good = cdir.name == "good"
            for p in sorted((cdir / "xyz").glob("*.tif*")):
                gt = cdir / "gt" / f"{p.stem}.png"
                if split == "test" and not good and not gt.is_file():
                    raise ValueError(f"{p}: a defective test sample (mvtec3d) without its ground truth {gt}")
                sources.append(PublicSource(p, f"{split}/{cdir.name}/{p.stem}", split,
                                            "good" if good else "defective", "" if good else cdir.name, "organized",
                                            "mvtec3d", gt if gt.is_file() and not good else None))
    if not any(s.split == "train" for s in sources):
        raise ValueError(f"{root}: no train/good/xyz/*.tiff files (mvtec3d layout: {LAYOUT_SIGNS['mvtec3d']})")
    return sources


# ---- reading one file ----------------------------------------------------------------------------------------------
def _read_table(path):
    """A numeric text table, comma or whitespace separated (Anomaly-ShapeNet's releases differ)."""
    with open(path, "r", errors="replace") as f:
        first = next((ln for ln in f if ln.strip()), "")
    try:
        table = np.loadtxt(path, delimiter="," if "," in first else None, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{path}: not a table of numbers ({e})") from None
    if table.shape[1] < 4:
        raise ValueError(f"{path}: {table.shape[1]} columns, expected x y z label")
    labels = table[:, 3]
    if not np.all(np.isin(labels, (0, 1))):
        raise ValueError(f"{path}: the 4th column must hold per-point labels 0 or 1")
    return table[:, :3], labels.astype(np.uint8)


def cloud_spacing(points, seed=0):
    """Median nearest-neighbour distance of a cloud (N, 3), estimated on a seeded sample of its points (file units)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    sample = pts if len(pts) <= _SPACING_SAMPLE else pts[rng.choice(len(pts), _SPACING_SAMPLE, replace=False)]
    d = cKDTree(pts).query(sample, k=2)[0][:, 1]
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.0


def match_ground_truth(points, gt_points, gt_labels, gt_path, cloud_path):
    """Per-point labels of ``points`` from ground-truth rows given in any order, matched by coordinates.

    Each point takes the label of its nearest ground-truth row, which must lie within a quarter of the cloud's
    median point spacing (the same point written with fewer digits); a point with no such row is a mismatch.

    Returns
    -------
    (N,) uint8 array

    Raises
    ------
    ValueError
        Naming the ground-truth file and the cloud, and how many of the cloud's points failed to match.
    """
    from scipy.spatial import cKDTree

    tol = 0.25 * cloud_spacing(points)
    d, idx = cKDTree(gt_points).query(points, k=1)
    bad = int(np.count_nonzero(d > tol))
    if bad:
        raise ValueError(f"{gt_path}: {bad} of the {len(points)} points of {cloud_path} have no ground-truth row "
                         f"within {tol:.3g} (a quarter of the cloud's point spacing)")
    return gt_labels[idx].astype(np.uint8)


def read_mask(path, shape):
    """A ground-truth PNG mask on the point map's grid -> (H, W) bool (any non-zero pixel is a defect)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            mask = np.asarray(im)
    except Exception as e:  # PIL raises many types for corrupt files
        raise ValueError(f"{path}: cannot read as a PNG mask ({type(e).__name__}: {e})") from None
    if mask.ndim == 3:
        mask = mask[..., :3].max(axis=2)
    if mask.shape != tuple(shape):
        raise ValueError(f"{path}: mask of {mask.shape[1]} x {mask.shape[0]} pixels, but its point map is "
                         f"{shape[1]} x {shape[0]}")
    return mask > 0


def remove_table_plane(grid, seed=0):
    """Which pixels of an MVTec 3D-AD point map belong to the object: off the table plane, largest cluster.

    Follows the Back-to-the-Feature preprocessing: a plane fitted by RANSAC to the points of the image's 10-pixel
    border (where the table shows), every point within 5 mm of it removed, then the largest DBSCAN cluster (eps 6 mm,
    30 points) of what is left kept. On more than 5000 points DBSCAN runs on a seeded subset of 5000 (min_points scaled
    by its share) and the other points take their nearest subset point's cluster (within eps): at 6 mm, a full-size
    map gives each point thousands of neighbours, which makes DBSCAN on the full map slow (timing:
    docs/results.md#import-timings).

    Parameters
    ----------
    grid : (H, W, 3) float array
        Metres, NaN where there is no point.
    seed : int
        Seeds open3d's RANSAC and the subset.

    Returns
    -------
    (H, W) bool array
    """
    import open3d as o3d

    valid = np.all(np.isfinite(grid), axis=2)
    border = np.zeros_like(valid)
    b = BORDER_PIXELS
    border[:b], border[-b:], border[:, :b], border[:, -b:] = True, True, True, True
    edge = grid[valid & border]
    if len(edge) < 3:
        raise ValueError("no points on the image border to fit the table plane to")
    o3d.utility.random.seed(int(seed))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(edge))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        plane, _ = pcd.segment_plane(PLANE_FIT_THRESHOLD, min(PLANE_RANSAC_N, len(edge)), PLANE_ITERATIONS)
    plane = np.asarray(plane, dtype=np.float64)
    plane = plane / np.linalg.norm(plane[:3])
    keep = valid.copy()
    keep[valid] = np.abs(grid[valid] @ plane[:3] + plane[3]) >= PLANE_DISTANCE
    pts = grid[keep]
    if len(pts) == 0:
        return keep
    largest = _largest_cluster(pts, seed)
    keep[keep] = largest
    return keep


def _largest_cluster(pts, seed):
    import open3d as o3d
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    sub = np.arange(len(pts)) if len(pts) <= _CLUSTER_SUBSAMPLE else \
        np.sort(rng.choice(len(pts), _CLUSTER_SUBSAMPLE, replace=False))
    min_points = max(3, int(round(CLUSTER_MIN_POINTS * len(sub) / len(pts))))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sub]))
    labels = np.asarray(pcd.cluster_dbscan(eps=CLUSTER_EPS, min_points=min_points, print_progress=False))
    if labels.max(initial=-1) < 0:  # no cluster at all: keep everything rather than nothing
        return np.ones(len(pts), dtype=bool)
    big = int(np.argmax(np.bincount(labels[labels >= 0])))
    if len(sub) == len(pts):
        return labels == big
    d, j = cKDTree(pts[sub]).query(pts, k=1)
    return (labels[j] == big) & (d <= CLUSTER_EPS)


def read_public_source(src, keep_plane=False, seed=0):
    """Points (file units), per-point labels and sensor origin of one file, as its layout's loader reads it.

    Returns
    -------
    points : (N, 3) float64 array, finite
    labels : (N,) uint8 array or None
        Test samples only (all zeros for good ones).
    origin : (3,) float64 array or None
        MVTec 3D-AD: the origin (its point maps are in the sensor's frame); None otherwise.
    n_dropped : int
        Non-finite rows of a cloud file that were dropped (pixels without a point do not count).
    """
    from .cloud_io import read_cloud, read_organized_cloud

    origin, labels = None, None
    if src.role == "organized":
        grid = read_organized_cloud(src.path)
        try:
            keep = np.all(np.isfinite(grid), axis=2) if keep_plane else remove_table_plane(grid, seed)
        except ValueError as e:
            raise ValueError(f"{src.path}: {e}") from None
        points = grid[keep]
        if src.split == "test":
            labels = (read_mask(src.ground_truth, grid.shape[:2])[keep] if src.ground_truth is not None
                      else np.zeros(len(points), np.uint8)).astype(np.uint8)
        origin = np.zeros(3)
    elif src.ground_truth is not None and src.layout == "real3d-ad":  # the txt is the labelled cloud
        points, labels = _read_table(src.ground_truth)
    else:
        points, _ = read_cloud(src.path)
        if src.ground_truth is not None:
            gt_points, gt_labels = _read_table(src.ground_truth)
            points = points[np.all(np.isfinite(points), axis=1)]
            labels = match_ground_truth(points, gt_points, gt_labels, src.ground_truth, src.path)
        elif src.split == "test":
            labels = np.zeros(len(points), np.uint8)
    ok = np.all(np.isfinite(points), axis=1)
    points = points[ok]
    labels = None if labels is None else labels[ok]
    if len(points) < 3:
        raise ValueError(f"{src.path}: {len(points)} point(s) left, need at least 3")
    return points, labels, origin, int(np.count_nonzero(~ok))


# ---- a whole class folder ------------------------------------------------------------------------------------------
def auto_voxel(sources, max_points, keep_plane=False, seed=0):
    """One voxel side (file units) for a class folder, from its training clouds' own point spacing, or None.

    A surface voxelised at side v keeps about (s / v)^2 of its points at spacing s, so v = s sqrt(n / max_points)
    brings a scan of n points to about ``max_points``. Up to 8 training files (evenly spread) are read; a complete
    template counts as half its points (a view sees about one side of it). The largest such v is used for every file
    of the class, so training and test scans keep one density. None when no sampled cloud is larger.
    """
    train = [s for s in sources if s.split == "train"]
    pick = np.unique(np.linspace(0, len(train) - 1, min(_VOXEL_SAMPLE_FILES, len(train))).round().astype(int))
    voxel = 0.0
    for k in pick:
        points = read_public_source(train[k], keep_plane, seed)[0]
        n_eff = len(points) / 2 if train[k].role == "template" else len(points)
        if n_eff > max_points:
            voxel = max(voxel, cloud_spacing(points, seed) * float(np.sqrt(n_eff / max_points)))
    return voxel or None


def orient_like_templates(points, normals, templates, max_offset=3.0, votes=TEMPLATE_NORMAL_VOTES):
    """The normals of a scan without a sensor origin, oriented like the templates' where the scan lies on them.

    A partial scan's normals can be oriented consistently with one another, but their global sign is a guess without
    the sensor (pointing away from the scan's own centroid fails for about half the views of an open, flat part),
    and the propagation along the scan (``estimate_normals``) flips whole patches beyond a crease or a gap (up to 15 %
    of a built-in bracket's test scan, docs/results.md#training-from-4-complete-templates); the complete templates'
    normals are reliable. When the scan lies on the templates (its median distance to them is at most
    ``max_offset`` template spacings: it is in their frame), the sign that agrees with the nearest template normal at
    most points is applied to the whole scan first; then each point within ``max_offset`` spacings of the templates
    takes the sign of the sum of its ``votes`` nearest template normals (projected on its own normal), so a flipped
    patch is turned back. Points farther off (a foreign object, the floor of a deep pit) keep the scan's sign. A scan
    in another pose is left as it is.

    Parameters
    ----------
    points, normals : (N, 3) float arrays
        The scan, file units; unit normals.
    templates : (cKDTree, (M, 3) float array, float)
        KD-tree over the templates' points, their unit normals, their median point spacing.
    max_offset : float
        In template spacings.
    votes : int >= 1
        Template normals that decide a point's sign.

    Returns
    -------
    normals : (N, 3) float array
    on_templates : bool
        Whether the scan lay on the templates (and its signs were decided by them).
    """
    d, j = _surface_neighbours(points, templates, votes)
    if not np.median(d[:, 0]) <= max_offset * templates[2]:
        return normals, False
    return _signed_like(normals, templates, d, j, max_offset), True


def orient_by_surface(points, normals, surface, max_offset=3.0, votes=TEMPLATE_NORMAL_VOTES):
    """The normals of a scan without a sensor origin signed by a good surface, whatever signs they come with.

    :func:`orient_like_templates`'s rule, made independent of the signs the normals arrive with: the result depends
    on the points, the normals' lines and the surface only. Where the surface decides every point (each lies within
    ``max_offset`` spacings of it), its votes alone set the signs. Otherwise the scan's own signs are first made
    :func:`datasets.normals.orient_consistently`'s (a consistent orientation and a global sign decided afresh), then
    the rule applies; a scan that does not lie on the surface (or no surface) keeps those. So a scan imported with
    its normals signed by the templates and the same file read with the estimator's signs end the same (what
    inspection applies when it scores a scan without a sensor origin, :mod:`datasets.reading`).

    Parameters
    ----------
    points : (N, 3) float array
    normals : (N, 3) float array
        Unit normals, any signs.
    surface : (index, (M, 3) float array, float) or None
        A nearest-neighbour index over the good surface's points (``query(x, k)`` -> (distances, indices), ``n``;
        a scipy ``cKDTree`` or :class:`datasets.neighbours.NearestNeighbours`), their unit outward normals, their
        median point spacing; in the scan's frame and units. None: no surface (consistent orientation only).
    max_offset, votes :
        As :func:`orient_like_templates`.

    Returns
    -------
    normals : (N, 3) float64 array
    on_surface : bool
        Whether the scan lay on the surface (and its signs were decided by it).
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if surface is None:
        return orient_consistently(points, normals), False
    d, j = _surface_neighbours(points, surface, votes)
    near = d[:, 0] <= max_offset * surface[2]
    if not near.all():  # points the surface leaves to the scan's own signs: make those independent of the input's
        normals = orient_consistently(points, normals)
    if not np.median(d[:, 0]) <= max_offset * surface[2]:
        return normals, False
    return _signed_like(normals, surface, d, j, max_offset), True


def _surface_neighbours(points, surface, votes):
    """(distances, indices), each (N, k), of the k = min(votes, M) nearest surface points of each point."""
    tree = surface[0]
    votes = min(int(votes), tree.n)
    d, j = tree.query(points, k=votes)
    return np.asarray(d).reshape(len(points), votes), np.asarray(j).reshape(len(points), votes)


def _signed_like(normals, surface, d, j, max_offset):
    """:func:`orient_like_templates`'s signs from the surface neighbours (d, j) of a scan on the surface."""
    _, surface_normals, spacing = surface
    normals = np.asarray(normals, dtype=np.float64)
    agree = np.einsum("ij,ij->i", normals, surface_normals[j[:, 0]]) > 0
    normals = normals if agree.mean() >= 0.5 else -normals
    vote = np.einsum("ij,ikj->i", normals, surface_normals[j])
    flip = (d[:, 0] <= max_offset * spacing) & (vote < 0)
    return np.where(flip[:, None], -normals, normals)


def import_public(root, out, layout, views=DEFAULT_VIEWS, validation_views=DEFAULT_VALIDATION_VIEWS,
                  keep_plane=False, max_points=DEFAULT_MAX_POINTS, voxel=None, n_points=None, seed=0,
                  overwrite=False, progress=None):
    """Import one class folder of a public layout into a new collection at ``out`` (the user's files are only read).

    Parameters
    ----------
    root, out : str or Path
    layout : {'real3d-ad', 'anomaly-shapenet', 'mvtec3d'}
    views, validation_views : int
        Partial views rendered per template (Real3D-AD, Anomaly-ShapeNet): ``views`` for training (split 'train'),
        ``validation_views`` held back for calibration (split 'validation'). ``views`` >= 1.
    keep_plane : bool
        MVTec 3D-AD: keep the table plane (default: removed).
    max_points : int or None
        Target points per scan of the automatic voxel size (:func:`auto_voxel`); None or 0: no automatic
        downsampling. Ignored when ``voxel`` or ``n_points`` is given.
    voxel : float, optional
        Voxel side in file units (overrides the automatic one).
    n_points : int, optional
        Seeded random subset of this many points per file instead of a voxel grid.
    seed : int
        Seeds the views' sensor positions, MVTec's RANSAC and cluster subset, and the random subsets.
    overwrite : bool
    progress : bool or None

    Returns
    -------
    dict
        :func:`datasets.importer.import_tree`'s summary plus ``layout``, ``units``, ``voxel`` (used, file units) and
        ``voxel_auto``.
    """
    from tqdm import tqdm

    from .ingest import write_scans
    from .normals import estimate_normals
    from .reading import SIGNS_FROM_SURFACE, Reading, downsample
    from .scan import Scan
    from .templates import render_views

    root, out = Path(root), Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (use --overwrite to replace it)")
    if int(views) != views or views < 1 or int(validation_views) != validation_views or validation_views < 0:
        raise ValueError(f"views must be >= 1 and validation_views >= 0, got {views!r} and {validation_views!r}")
    if voxel is not None and n_points is not None:
        raise ValueError("give --voxel or --points, not both")
    sources = find_public_sources(root, layout)
    voxel_auto = voxel is None and n_points is None and bool(max_points)
    if voxel_auto:
        voxel = auto_voxel(sources, max_points, keep_plane, seed)
        if voxel is not None:
            log.info("%s: voxel size %.4g %s from the training clouds' spacing (target %d points a scan)", root,
                     voxel, UNITS[layout], max_points)
    from scipy.spatial import cKDTree

    from .sidecar import read_sensor_origin

    # the rules every scan is read by, recorded so that a file scored later reads the same (datasets.reading): the
    # files' own normals are not read (the layouts' loaders read xyz only) and normals come after downsampling
    # (estimating them on the full cloud would cost more and be averaged away); the signs of a scan without a sensor
    # origin are decided by the good surface (here the templates, at scoring the calibration's good scans)
    reading = Reading(voxel=voxel, points=None if voxel is not None else n_points, seed=seed, file_normals="ignored",
                      normals="after downsampling", signs="estimated" if layout == "mvtec3d" else SIGNS_FROM_SURFACE)
    scans, n_dropped, template_clouds, templates, n_oriented = [], 0, [], None, 0
    for src in tqdm(sources, desc=f"import {layout}", unit="file", disable=None if progress is None else not progress):
        points, labels, origin, dropped = read_public_source(src, keep_plane, seed)
        n_dropped += dropped
        if src.role == "cloud":  # a sidecar's sensor origin, as for any scanner file (datasets.importer)
            origin = read_sensor_origin(src.path, points)
        points, _, labels = downsample(points, np.zeros_like(points), labels, reading)
        if src.role == "template":  # the sources list templates first
            normals = estimate_normals(points)
            template_clouds.append((points, normals))
            scans += render_views(src.name, points, normals, views, validation_views, seed)
            continue
        normals = estimate_normals(points, origin)
        if origin is None and template_clouds:
            if templates is None:
                tp = np.concatenate([p for p, _ in template_clouds])
                templates = (cKDTree(tp), np.concatenate([n for _, n in template_clouds]),
                             max(cloud_spacing(p, seed) for p, _ in template_clouds))
            normals, on = orient_like_templates(points, normals, templates)
            n_oriented += on
        scan = Scan(name=src.name, points=points, normals=normals, split=src.split,
                    label=src.label, defect=src.defect, point_labels=labels, sensor_origin=origin)
        scan.points = points  # keep file-unit precision until the frame is applied
        scans.append(scan)
    provenance = {"source": "import", "layout": layout, "units": UNITS[layout], "root": str(root.resolve()),
                  "files": len(sources), "voxel": voxel, "voxel_auto": voxel_auto, "max_points": max_points,
                  "points": n_points, "seed": seed, "dropped_nonfinite": n_dropped, "reading": reading.as_dict()}
    if layout == "mvtec3d":
        provenance["table_plane"] = "kept" if keep_plane else "removed"
    else:
        provenance.update(template_views=views, template_validation_views=validation_views,
                          scans_oriented_by_templates=n_oriented)
    summary = write_scans(scans, out, provenance, overwrite)
    summary.update(n_dropped=n_dropped, layout=layout, units=UNITS[layout], voxel=voxel, voxel_auto=voxel_auto,
                   oriented_by_templates=n_oriented,
                   n_without_origin=sum(s.sensor_origin is None and s.split == "test" for s in scans))
    log.info("imported %d scans (%s layout) from %s into %s", len(scans), layout, root, out)
    return summary
