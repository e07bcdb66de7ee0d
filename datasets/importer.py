"""Turning a folder of scanner files (MVTec-3D-AD / Real3D-AD style tree, or flat) into a scan collection, and back.

Tree layout (split, label and defect come from the folders)::

    ROOT/train/good/*.{ply,pcd,xyz,pts,txt,npy,npz}
    ROOT/validation/good/*            (optional)
    ROOT/test/good/*
    ROOT/test/<defect>/*              label 'defective', defect '<defect>'
    ROOT/ground_truth/<defect>/<stem>.txt   (optional) one 0/1 per point of test/<defect>/<stem>.*; with several
                                            columns (Real3D-AD: x y z label) the last one is the label
    ROOT/ground_truth/<defect>/<stem>.deviation.txt   (optional) one number per point, in the file's units: how far
                                            the point lies off the good part's surface (``Scan.point_deviation``:
                                            positive outside, 0 where no defect is); never a label file (a cloud
                                            ``<stem>.deviation.*`` beside ``<stem>.*`` with that file is an error);
                                            in a tree that has any, the good test parts' are 0 everywhere
    ROOT/<split>/*.{ply,...}          files directly in a split folder: 'good' for train/validation, 'unknown' in test

A flat folder of clouds (no train/validation/test folder) becomes split 'test', label 'unknown', or the split and
label given (``split='train'``: a folder of good scans to train on). Files that are not point clouds (a README, a
scanner's ``.conf``, hidden files) are skipped and listed (:func:`list_folder`), never read.
Sensor origin (optional, file units): an npz key ``sensor_origin`` or a sidecar ``<stem>.json`` holding
``{"sensor_origin": [x, y, z]}`` beside the cloud, or only the direction the sensor looked from,
``{"view_direction": [x, y, z]}`` (from the part toward the sensor, any length: a line scanner's sweep, a sensor
whose stand-off nobody wrote down): the origin is then put ``VIEW_DIRECTION_DISTANCE`` bounding-box diagonals from
the cloud's centre along it, where its rays to the part are parallel within a third of a degree.
How each file was read (voxel side or subset, stray points, normals) is recorded in the collection's provenance
(``reading``, :mod:`datasets.reading`), so that a file scored later from a folder is read the same.
"""
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .atomic import check_writable
from .cloud_io import CLOUD_SUFFIXES, is_cloud_file, read_cloud, write_cloud
from .ingest import group_counts, write_scans
from .layouts import LAYOUT_SIGNS, import_public, resolve_layout
from .normals import estimate_normals
from .reading import Reading
from .scan import LABELS, SPLITS, Scan
from .sidecar import SIDECAR_SUFFIX as _SIDECAR_SUFFIX
from .sidecar import VIEW_DIRECTION_DISTANCE  # noqa: F401 - where the importer's module docstring and users find it
from .sidecar import read_sensor_origin as _read_sensor_origin

log = logging.getLogger(__name__)

MIN_POINTS = 3  # fewer finite points cannot define a tangent plane, let alone a surface
DEVIATION_SUFFIX = ".deviation.txt"  # ground_truth/<defect>/<stem> + this: a scan's per-point deviations


@dataclass(frozen=True)
class ScanSource:
    """One scanner file and what its place in the tree says about it."""

    path: Path
    name: str
    split: str
    label: str
    defect: str
    ground_truth: Optional[Path] = None
    all_good: bool = False  # a good test part in a tree that has ground truth: every point labelled 0
    deviation: Optional[Path] = None  # ground_truth/<defect>/<stem>.deviation.txt (DEVIATION_SUFFIX)
    zero_deviation: bool = False  # a good test part in a tree that records deviations: every point's is 0


# ---- finding files ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FolderListing:
    """What a folder of scanner files holds: the clouds to read and the files that are not clouds."""

    sources: list  # ScanSource, in a fixed order (split, class folder, file name)
    skipped: list  # Path of every file skipped as not a point cloud (README, .conf, hidden files...), sorted


def cloud_files(folder, exclude=None):
    """(cloud files, skipped files) of ``folder``, each sorted by name: the clouds are the files
    :func:`datasets.cloud_io.is_cloud_file` accepts; skipped are all other files but the clouds' ``<stem>.json``
    sidecars and ``exclude`` (the collection being written). Sub-folders are neither."""
    clouds, others = [], []
    for p in sorted(Path(folder).iterdir()):
        if p.is_dir() or (exclude is not None and p.resolve() == exclude):
            continue
        (clouds if is_cloud_file(p) else others).append(p)
    stems = {p.stem for p in clouds}
    return clouds, [p for p in others if not (p.suffix.lower() == _SIDECAR_SUFFIX and p.stem in stems)]


def list_folder(root, exclude=None, split=None, label=None):
    """The scanner files of a tree or flat folder, and the files in it that are not point clouds.

    A folder as a scanner or a colleague leaves it holds more than clouds (a README, the scanner's alignment
    ``.conf``, a desktop's hidden files): those are skipped, never read and never an error, and listed so that a
    command can say in one line which (:func:`skipped_line`). A file with a cloud's suffix that cannot be read stays
    an error naming it (:func:`load_source`).

    Parameters
    ----------
    root : str or Path
    exclude : Path, optional
        A file to skip (the output collection, when it is written into the folder being imported).
    split : {'train', 'validation', 'test'}, optional
        A flat folder's scans go to this split (default 'test'), as the files directly in a tree's ``<split>/``
        folder do: a flat folder of good scans imported with ``split='train'`` is a training collection.
    label : {'good', 'defective', 'unknown'}, optional
        A flat folder's scans get this label (default: 'unknown' in split 'test', else 'good').

    Returns
    -------
    FolderListing

    Raises
    ------
    ValueError
        ``root`` is not a folder, holds no cloud, holds two clouds of one name, or is a tree and ``split`` /
        ``label`` are given (its folders say them).
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such folder")
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder")
    exclude = None if exclude is None else Path(exclude).resolve()
    split_dirs = [root / s for s in SPLITS if (root / s).is_dir()]
    sources, skipped = [], []
    if split is not None or label is not None:
        if split_dirs:
            raise ValueError(f"{root}: a split and label are given for a flat folder's scans, but this folder is a "
                             f"tree ({', '.join(d.name + '/' for d in split_dirs)}) whose folders say them")
        split = "test" if split is None else split
        if split not in SPLITS:
            raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
        label = ("unknown" if split == "test" else "good") if label is None else label
        if label not in LABELS:
            raise ValueError(f"label must be one of {', '.join(LABELS)}, got {label!r}")
    if not split_dirs:
        clouds, skipped = cloud_files(root, exclude)
        sources = [ScanSource(p, p.stem, split or "test", label or "unknown", "") for p in clouds]
    records_deviation = any((root / "ground_truth").glob(f"*/*{DEVIATION_SUFFIX}"))
    for sdir in split_dirs:
        split_here = sdir.name
        clouds, other = cloud_files(sdir)
        skipped += other
        for p in clouds:
            label_here = "unknown" if split_here == "test" else "good"
            sources.append(ScanSource(p, f"{split_here}/{p.stem}", split_here, label_here, ""))
        for cdir in sorted(d for d in sdir.iterdir() if d.is_dir() and not d.name.startswith(".")):
            good = cdir.name == "good"
            defect = "" if good else cdir.name
            clouds, other = cloud_files(cdir)
            skipped += other
            for p in clouds:
                gt, dev = _truth_files(root / "ground_truth" / cdir.name, p, clouds)
                all_good = good and split_here == "test" and (root / "ground_truth").is_dir()
                sources.append(ScanSource(p, f"{split_here}/{cdir.name}/{p.stem}", split_here,
                                          "good" if good else "defective", defect, gt, all_good, dev,
                                          all_good and records_deviation))
    if not sources:
        also = f" (skipped {len(skipped)} other files)" if skipped else ""
        raise ValueError(f"{root}: no point-cloud files found (looked for {', '.join(CLOUD_SUFFIXES)} "
                         f"in {'train/ validation/ test/' if split_dirs else 'the folder itself'}{also}; nor is it a "
                         f"class folder of a known layout: {', '.join(_public_layouts())})")
    seen = {}
    for s in sources:
        if s.name in seen:
            raise ValueError(f"{s.path}: same scan name {s.name!r} as {seen[s.name]} (one cloud per file stem)")
        seen[s.name] = s.path
    return FolderListing(sources, sorted(skipped))


def _truth_files(truth, cloud, clouds):
    """(label file or None, deviation file or None) of ``cloud`` in the ground-truth folder ``truth``.

    ``<stem>.deviation.txt`` is the deviation file of the cloud ``<stem>``, never the label file of a cloud named
    ``<stem>.deviation``: such a cloud beside ``<stem>`` is an error when that file exists (its name says both).
    """
    gt, dev = truth / f"{cloud.stem}.txt", truth / f"{cloud.stem}{DEVIATION_SUFFIX}"
    base = cloud.stem[:-len(".deviation")] if cloud.stem.endswith(".deviation") else None
    if base is not None and gt.is_file() and any(p.stem == base for p in clouds):
        raise ValueError(f"{gt}: the per-point deviations of the cloud {base!r} or the labels of {cloud}? Rename "
                         f"{cloud.name} (a cloud's stem must not end in '.deviation' beside the cloud it names)")
    return (gt if gt.is_file() else None), (dev if dev.is_file() else None)


def find_sources(root, exclude=None, split=None, label=None):
    """The scanner files of a tree or flat folder (list of ScanSource), in a fixed order (split, class folder, file
    name); files that are not point clouds are skipped (:func:`list_folder`, which also lists those)."""
    return list_folder(root, exclude, split, label).sources


def skipped_line(skipped, root=None, shown=8):
    """The one line a command says about the files of a folder it skipped as not point clouds ('' when none):
    ``skipped 3 files that are not point clouds: README, bun.conf, .DS_Store``, each named relative to ``root``."""
    if not skipped:
        return ""
    names = [str(Path(p).relative_to(root)) if root is not None and Path(root) in Path(p).parents else str(p)
             for p in skipped]
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    what = "1 file that is not a point cloud" if len(names) == 1 else f"{len(names)} files that are not point clouds"
    return f"skipped {what}: {', '.join(names[:shown])}{more}"


def _public_layouts():
    return [f"{name} ({sign})" for name, sign in LAYOUT_SIGNS.items()]


# ---- per-file processing ---------------------------------------------------------------------------------------------
def _read_ground_truth(gt, n, cloud):
    try:
        table = np.loadtxt(gt, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{gt}: not a table of numbers ({e})") from None
    if table.shape[0] != n:
        raise ValueError(f"{gt}: {table.shape[0]} labels for the {n} points of {cloud}")
    labels = table[:, -1]
    if not np.all(np.isin(labels, (0, 1))):
        raise ValueError(f"{gt}: per-point labels must be 0 or 1")
    return labels.astype(np.uint8)


def _read_deviation(path, n, cloud):
    """A ``<stem>.deviation.txt``: one finite number per point of ``cloud`` (n of them), as (n,) float64."""
    try:
        table = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{path}: not a column of numbers ({e})") from None
    if table.shape[1] != 1 and len(table):
        raise ValueError(f"{path}: {table.shape[1]} columns, expected one deviation per line")
    if table.shape[0] != n:
        raise ValueError(f"{path}: {table.shape[0]} deviations for the {n} points of {cloud}")
    if not np.all(np.isfinite(table)):
        raise ValueError(f"{path}: deviations must be finite numbers (NaN or Inf found)")
    return table[:, 0] if len(table) else np.zeros(0)


def load_source(src, voxel=None, n_points=None, seed=0, reading=None):
    """Read one scanner file into a Scan in file units, cleaned, with normals, optionally downsampled.

    The one reading of a file (:mod:`datasets.reading`): an import and a file read later for scoring call this with
    the same :class:`~datasets.reading.Reading` and get the same points and normals.

    Parameters
    ----------
    src : ScanSource
    voxel : float, optional
        Voxel side for downsampling, in file units.
    n_points : int, optional
        Keep a random subset of this many points (all points when there are fewer).
    seed : int
        Seeds the subset together with the file's points (:func:`datasets.reading.subset`), so a scan's subset does
        not depend on which other files are imported, in which order, or where in a tree the file lies.
    reading : datasets.reading.Reading, optional
        All the rules at once (then ``voxel``, ``n_points`` and ``seed`` must be left at their defaults). A scan
        without a sensor origin whose normal signs the reading leaves to the good surface is marked so
        (:func:`datasets.reading.mark_signs`).

    Returns
    -------
    scan : Scan
        In file units (the collection frame is applied later).
    n_dropped : int
        Non-finite points (or points with non-finite or zero normals, when the file's normals are used) that were
        removed.

    Raises
    ------
    ValueError
        Naming the file: no or too few finite points, all points identical, a bad sidecar, ground truth or
        deviation file (:data:`DEVIATION_SUFFIX`: a count that is not the cloud's, a value that is not a number).
    """
    from .reading import Reading, downsample, downsample_values, mark_signs

    if reading is None:
        reading = Reading(voxel=voxel, points=n_points, seed=seed)
    elif voxel is not None or n_points is not None or seed != 0:
        raise ValueError("load_source: give a reading or voxel / n_points / seed, not both")
    points, normals = read_cloud(src.path)
    if reading.file_normals == "ignored":
        normals = None
    n_raw = len(points)
    labels = _read_ground_truth(src.ground_truth, n_raw, src.path) if src.ground_truth is not None else None
    deviation = _read_deviation(src.deviation, n_raw, src.path) if src.deviation is not None else None
    ok = np.all(np.isfinite(points), axis=1)
    if normals is not None:
        lengths = np.linalg.norm(normals, axis=1)
        ok &= np.isfinite(lengths) & (lengths > 1e-12)
    n_dropped = int(n_raw - ok.sum())
    if ok.sum() == 0:
        raise ValueError(f"{src.path}: no finite points (all {n_raw} are NaN/Inf)")
    if ok.sum() < MIN_POINTS:
        raise ValueError(f"{src.path}: {int(ok.sum())} finite point(s), need at least {MIN_POINTS}")
    if n_dropped:
        log.info("%s: dropped %d of %d points (NaN/Inf or zero normal)", src.path, n_dropped, n_raw)
        points = points[ok]
        normals = normals[ok] if normals is not None else None
        labels = labels[ok] if labels is not None else None
        deviation = deviation[ok] if deviation is not None else None
    if np.ptp(points, axis=0).max() == 0:
        raise ValueError(f"{src.path}: all {len(points)} points are identical")
    origin = _read_sensor_origin(src.path, points)
    if normals is not None:
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    elif reading.normals == "before downsampling":
        normals = estimate_normals(points, origin)
    if deviation is not None:  # a length, in file units like the points (the collection's frame scales both)
        deviation = downsample_values(points, deviation, reading)
    if normals is not None:
        points, normals, labels = downsample(points, normals, labels, reading)
    else:  # normals estimated on the downsampled points (the public layouts)
        points, _, labels = downsample(points, np.zeros_like(points), labels, reading)
        if len(points) < MIN_POINTS:
            raise ValueError(f"{src.path}: {len(points)} point(s) left after downsampling, need at least "
                             f"{MIN_POINTS}")
        normals = estimate_normals(points, origin)
    if labels is None and src.all_good:
        labels = np.zeros(len(points), np.uint8)
    if deviation is None and src.zero_deviation:
        deviation = np.zeros(len(points))
    scan = Scan(name=src.name, points=points, normals=normals, split=src.split, label=src.label, defect=src.defect,
                point_labels=labels, sensor_origin=origin, point_deviation=deviation)
    scan.points = np.asarray(points, dtype=np.float64)  # keep file-unit precision until the frame is applied
    return mark_signs(scan, reading), n_dropped


# ---- whole folders ---------------------------------------------------------------------------------------------------
def import_tree(root, out, voxel=None, n_points=None, seed=0, overwrite=False, progress=None, drop_strays=False,
                layout="auto", split=None, label=None, **public_options):
    """Import a tree or flat folder of scanner files into a new collection at ``out``.

    A class folder of a public benchmark (Real3D-AD, Anomaly-ShapeNet, MVTec 3D-AD) is recognised (``layout='auto'``)
    or named (``layout``) and read by :mod:`datasets.layouts` as its own loaders read it; ``public_options`` go there.

    The frame is fitted to the bounding box of all training points (of all points when there is no train split)
    and applied to every scan; stray points (:func:`datasets.outliers.stray_points`, found per scan after
    downsampling) are counted in the provenance (``stray_points``, shown by ``python -m datasets info``) and left out
    of the frame's fit, so a few isolated returns far from the part do not shrink it; they stay in the scans unless
    ``drop_strays``. Everything is read and checked before anything is written, so any bad file raises
    one ValueError naming it and leaves ``out`` untouched. The preprocessed scans are held in memory until written
    (use --voxel / --points for large trees).

    Parameters
    ----------
    root, out : str or Path
    voxel : float, optional
        Voxel side in file units.
    n_points : int, optional
        Points per scan (seeded random subset).
    seed : int
    overwrite : bool
    progress : bool or None
        tqdm bar over files; None shows it only on a terminal.
    drop_strays : bool
        Remove the stray points from the scans (default: keep them; they are only counted).
    layout : {'auto', 'tree', 'real3d-ad', 'anomaly-shapenet', 'mvtec3d'}
        'tree': this module's own layout (above); 'auto': detected from the folder.
    split, label : str, optional
        The split and label of a flat folder's scans (:func:`list_folder`): ``split='train'`` makes a folder of
        good scans a training collection. A tree's folders and a public layout say them: an error there.

    Returns
    -------
    dict
        Summary: out, n_scans, counts per split/label/defect, n_dropped, n_stray, frame, points per scan
        min/median/max, ``skipped`` (the files that are not point clouds, :func:`list_folder`).
    """
    from tqdm import tqdm

    root, out = Path(root), Path(out)
    if voxel is not None and n_points is not None:
        raise ValueError("give --voxel or --points, not both")
    if voxel is not None and not voxel > 0:
        raise ValueError(f"voxel size must be > 0, got {voxel}")
    if n_points is not None and n_points < MIN_POINTS:
        raise ValueError(f"--points must be >= {MIN_POINTS}, got {n_points}")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (use --overwrite to replace it)")
    check_writable(out)  # say so now, not after reading every file
    layout = resolve_layout(root, layout)
    if layout != "tree":
        if split is not None or label is not None:
            raise ValueError(f"{root}: a split and label apply to a flat folder of scans, not to a {layout} class "
                             f"folder, whose files say them")
        return import_public(root, out, layout, voxel=voxel, n_points=n_points, seed=seed, overwrite=overwrite,
                             progress=progress, **public_options)
    if public_options:
        raise ValueError(f"{root}: options {sorted(public_options)} apply to the public layouts only, not 'tree'")
    listing = list_folder(root, exclude=out, split=split, label=label)
    sources = listing.sources
    # the rules every file is read by, recorded so that a file scored later reads the same (datasets.reading); the
    # stray points are dropped by write_scans, after the frame's fit has left them out
    reading = Reading(voxel=voxel, points=n_points, seed=seed, strays="dropped" if drop_strays else "kept")
    scans, n_dropped = [], 0
    for src in tqdm(sources, desc="import", unit="file", disable=None if progress is None else not progress):
        scan, dropped = load_source(src, reading=reading)
        scans.append(scan)
        n_dropped += dropped
    provenance = {"source": "import", "root": str(root.resolve()), "files": len(sources), "voxel": voxel,
                  "points": n_points, "seed": seed, "dropped_nonfinite": n_dropped, "reading": reading.as_dict()}
    summary = write_scans(scans, out, provenance, overwrite, drop_strays=drop_strays)
    summary.update(n_dropped=n_dropped, skipped=[str(p) for p in listing.skipped])
    log.info("imported %d scans from %s into %s", len(scans), root, out)
    return summary


def export_collection(path, out_dir, file_frame=False, overwrite=False):
    """Write each scan of a collection as ``out_dir/<name>.ply`` (the tree layout its names spell).

    Scans with per-point labels are coloured (defect points red, others grey) and, when defective, also get
    ``out_dir/ground_truth/<defect>/<stem>.txt`` (and ``<stem>.deviation.txt`` when their deviations are known, in
    the units of the points written); a known sensor origin goes to a ``<stem>.json`` sidecar. So an exported tree
    imports back with the same structure.

    Parameters
    ----------
    path : str or Path
        A collection.
    out_dir : str or Path
        Created if missing; must be empty unless ``overwrite``.
    file_frame : bool
        Write coordinates in the original file units (the collection's frame inverted) instead of the collection's.

    Returns
    -------
    int
        Number of scans written.
    """
    from .collection import ScanCollection

    out_dir = Path(out_dir)
    with ScanCollection(path) as c:
        if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
            raise FileExistsError(f"{out_dir}: not empty (use --overwrite to write into it)")
        base = out_dir.resolve()
        for scan in c:
            target = (out_dir / f"{scan.name}.ply")
            if base not in target.resolve().parents:
                raise ValueError(f"{path}: scan name {scan.name!r} would be written outside {out_dir}")
            points, origin = scan.points, scan.sensor_origin
            if file_frame:
                points = c.frame.to_file(points)
                origin = None if origin is None else c.frame.to_file(origin)
            colors = None
            if scan.point_labels is not None:
                colors = np.where(scan.point_labels[:, None] > 0, [[1.0, 0.0, 0.0]], [[0.7, 0.7, 0.7]])
                if scan.label == "defective":
                    gt = out_dir / "ground_truth" / (scan.defect or "defect") / f"{target.stem}.txt"
                    gt.parent.mkdir(parents=True, exist_ok=True)
                    np.savetxt(gt, scan.point_labels, fmt="%d")
            if scan.point_deviation is not None and scan.label == "defective":
                deviation = scan.point_deviation / (c.frame.scale if file_frame else 1.0)
                dev = out_dir / "ground_truth" / (scan.defect or "defect") / f"{target.stem}{DEVIATION_SUFFIX}"
                dev.parent.mkdir(parents=True, exist_ok=True)
                np.savetxt(dev, deviation.astype(np.float64), fmt="%.9g")
            write_cloud(target, points, scan.normals, colors)
            if origin is not None:
                target.with_suffix(_SIDECAR_SUFFIX).write_text(
                    json.dumps({"sensor_origin": [float(x) for x in origin]}))
        return len(c)


def collection_info(path):
    """A human-readable summary of a collection (str): counts per split/label/defect, points per scan, frame,
    provenance, fingerprint."""
    from .collection import ScanCollection

    with ScanCollection(path) as c:
        meta = c.metadata()
        lines = [f"{path}: {len(c)} scans, format version 1, written by toolkit {c.toolkit_version or '?'}"]
        if meta:
            groups = group_counts((m["split"], m["label"], m["defect"] or "-") for m in meta)
            lines.append(f"{'split':<12}{'label':<12}{'defect':<16}{'scans':>7}")
            lines += [f"{s:<12}{lab:<12}{d:<16}{n:>7}" for (s, lab, d), n in groups.items()]
            n = c.n_points
            lines.append(f"points per scan: min {n.min()}, median {np.median(n):g}, max {n.max()}, total {n.sum()}")
            lines.append(f"with point labels: {sum(m['has_labels'] for m in meta)}, with sensor origin: "
                         f"{sum(m['sensor_origin'] is not None for m in meta)}, with point deviations: "
                         f"{sum(m['has_deviation'] for m in meta)}")
        stray = c.provenance.get("stray_points")
        if stray is not None:
            worst = ", ".join(f"{n} {k}" for n, k in stray["worst"])
            lines.append(f"stray points at import ({stray['rule']}): {stray['total']} in {stray['scans_with']} scans, "
                         f"at most {stray['max_per_scan']} in one"
                         + (f" ({worst})" if worst else "")
                         + ("; removed" if stray["dropped"] else "; kept in the scans, left out of the frame's fit"))
        lines.append(f"frame: center {c.frame.as_dict()['center']}, scale {c.frame.scale:.6g} "
                     f"(x_collection = scale * (x_file - center))")
        lines.append(f"provenance: {json.dumps(c.provenance, sort_keys=True)}")
        lines.append(f"fingerprint: {c.fingerprint()}")
    return "\n".join(lines)


def read_scan(src, reading=None):
    """One scanner file read by ``reading``'s rules, as the import that recorded it read its files.

    :func:`datasets.importer.load_source` (points, sensor origin, normals, downsampling, the mark of normals whose
    signs the good surface decides), then the stray points dropped when the reading says so (as the import's
    :func:`datasets.ingest.write_scans` drops them).

    Parameters
    ----------
    src : datasets.importer.ScanSource
    reading : Reading, dict or None
        None: the default reading (a folder imported without options).

    Returns
    -------
    scan : Scan
        In file units.
    n_dropped : int
        Non-finite rows removed (as :func:`datasets.importer.load_source` counts them).

    Raises
    ------
    ValueError, OSError
        The file cannot be read as a scan (the message names it).
    """
    from .ingest import _without
    from .outliers import stray_points

    reading = Reading.from_dict(reading)
    scan, n_dropped = load_source(src, reading=reading)
    if reading.strays == "dropped":
        mask = stray_points(scan.points)
        if mask.any():
            scan = _without(scan, mask)
    return scan, n_dropped
