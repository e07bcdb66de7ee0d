"""The real suite's tree: scans made from the bunny's aligned views, with defects made in the real points, written
as the datasets importer reads them and imported (cached by its parameters: ``benchmarks.cache``).

    train/good/*.ply, test/good/*.ply, test/{bump,dent,foreign,missing}/*.ply    points only (no normals), metres
    <same stem>.json    {"sensor_origin": [x, y, z], "view": ..., "stray_points": [...], "rotation_deg": ...}
    ground_truth/<defect>/<stem>.txt    one 0/1 per point
    ground_truth/<defect>/<stem>.deviation.txt    one number per point, metres: how far it lies off the good surface
        (``defect_in_points``' deviation: positive outside, 0 off the defect and on the spurious returns)

Every scan is one real view, a fresh random subset of its points (4,000 by default) with the scanner's own stray
points kept, a few synthetic spurious returns on half the scans (points on the sensor's ray, 5-30 mm in front of
the surface: what a real scanner's multipath and mixed pixels give; labelled 0, listed in the sidecar), and a
random pose change of up to ``--jitter`` degrees about the part's centre (and a shift of up to ``--shift`` of its
diagonal: parts placed by hand). Defects are made in the real points (the full-resolution view, before
subsampling) by :func:`datasets.point_defects.defect_in_points`, so everything outside them is real data: dent / bump
(the disc moved along the site's normal), missing (a ball removed, its back wall seen along the sensor's rays),
foreign (a small sphere or box put on the surface), sized as ``datasets.defects``' mesh defects times ``--size``.
"""
import json
import time
from pathlib import Path

import numpy as np

from benchmarks import cache
from benchmarks.suites.real.reading import SENSOR_DISTANCE, check_views, load_views

KINDS = ("bump", "dent", "foreign", "missing")


def range_noise(points, normals, k=16):
    """The scan's own noise (metres): 1.4826 x the median |distance to the local plane| of each point's k neighbours
    (curvature adds a little, so this is an upper bound on a smooth part)."""
    from scipy.spatial import cKDTree

    _, idx = cKDTree(points).query(points, k)
    nb = points[idx]
    centred = nb - nb.mean(1, keepdims=True)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    plane_n = vt[:, 2]
    res = np.abs(np.einsum("ij,ij->i", points - nb.mean(1), plane_n))
    return 1.4826 * float(np.median(res))


def spurious_returns(points, sensor, count, rng):
    """``count`` stray points on the sensor's rays to random scan points, 5-30 mm in front of the surface."""
    if count == 0:
        return np.empty((0, 3))
    p = points[rng.choice(len(points), count, replace=False)]
    d = p - sensor
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return p - rng.uniform(0.005, 0.03, (count, 1)) * d


def random_rotation(max_deg, rng):
    """A (3, 3) rotation about a random axis by an angle drawn uniformly in [0, ``max_deg``] degrees."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * np.radians(rng.uniform(0, max_deg))).as_matrix()


def real_collection(args):
    """The bunny tree built and imported (cached by its parameters). Returns the collection's path."""
    params = {k: getattr(args, k) for k in ("train", "test_good", "per_defect", "points", "jitter", "strays",
                                            "size", "seed")}
    params["source"] = str(Path(args.source).resolve())
    if args.shift:  # only when set, so that the trees built before the option keep their cache keys
        params["shift"] = args.shift
    if args.standoff != SENSOR_DISTANCE or args.origin_tilt:  # likewise
        params["sidecar_origin"] = [args.standoff, args.origin_tilt]

    def build(folder):
        from datasets.importer import import_tree

        build_tree(folder / "tree", args)
        import_tree(folder / "tree", folder / "bunny.h5", progress=False)

    return cache.cached_path("real", params, build, args.cache, label="bunny") / "bunny.h5"


def build_tree(tree, args):
    """Write the tree of PLY + JSON files (see the module docstring)."""
    from datasets.cloud_io import write_cloud
    from datasets.point_defects import defect_in_points
    from datasets.normals import estimate_normals

    t0 = time.perf_counter()
    views = load_views(Path(args.source))
    print(f"read {len(views)} views from {args.source} in {time.perf_counter() - t0:.0f} s; checks of the conventions:")
    check_views(views)
    every = np.concatenate([v["points"] for v in views])
    centre = (every.min(0) + every.max(0)) / 2
    diagonal = float(np.linalg.norm(np.ptp(every, axis=0)))
    for v in views:  # full-resolution normals toward the sensor, for the defect sites and their normals
        v["normals"] = estimate_normals(v["points"], v["sensor"])
        v["noise"] = range_noise(v["points"], v["normals"])
    print(f"part diagonal {diagonal * 1000:.1f} mm; range noise per view (mm): "
          + ", ".join(f"{v['name']} {v['noise'] * 1000:.3f}" for v in views))
    plan = [("train", "good", i) for i in range(args.train)] + [("test", "good", i) for i in range(args.test_good)]
    plan += [("test", k, i) for k in KINDS for i in range(args.per_defect)]
    offsets = {"train": 0, "test": 3}  # test scans start at another view so each split cycles through all views
    for n, (split, kind, i) in enumerate(plan):
        rng = np.random.default_rng([args.seed, n])
        v = views[(i + offsets[split] + (KINDS.index(kind) if kind in KINDS else 0)) % len(views)]
        pts, labels, info = v["points"], np.zeros(len(v["points"]), np.uint8), {}
        deviation = np.zeros(len(pts))
        if kind in KINDS:  # the deviation draws nothing: the scans are those of the trees built before it
            pts, labels, info, deviation = defect_in_points(pts, v["normals"], v["sensor"], kind, diagonal,
                                                            v["noise"], rng, args.size, with_deviation=True)
        keep = np.sort(rng.choice(len(pts), min(args.points, len(pts)), replace=False))
        pts, labels, deviation = pts[keep], labels[keep], deviation[keep]
        n_stray = int(rng.integers(1, args.strays + 1)) if args.strays and rng.random() < 0.5 else 0
        stray = spurious_returns(pts, v["sensor"], n_stray, rng)
        at = np.sort(rng.choice(len(pts) + n_stray, n_stray, replace=False))
        order = np.setdiff1d(np.arange(len(pts) + n_stray), at)
        merged = np.empty((len(pts) + n_stray, 3))
        merged[order], merged[at] = pts, stray
        lab = np.zeros(len(merged), np.uint8)
        lab[order] = labels
        dev = np.zeros(len(merged))  # a length: the pose change below leaves it as it is
        dev[order] = deviation
        rot = random_rotation(args.jitter, rng)
        shift = np.zeros(3)
        if args.shift:
            shift = rng.normal(size=3)
            shift *= rng.uniform(0, args.shift) * diagonal / np.linalg.norm(shift)
        merged = (merged - centre) @ rot.T + centre + shift
        sensor = (_written_sensor(v, args, rng) - centre) @ rot.T + centre + shift
        stem = f"{n:03d}_{v['name']}"
        folder = tree / split / kind
        write_cloud(folder / f"{stem}.ply", merged)
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))))
        side = {"sensor_origin": [float(x) for x in sensor], "view": v["name"], "stray_points": at.tolist(),
                "rotation_deg": angle, "shift": shift.tolist(),
                "defect": info}
        _write_text(folder / f"{stem}.json", json.dumps(side))
        if kind in KINDS:
            gt = tree / "ground_truth" / kind / f"{stem}.txt"
            _write_text(gt, "\n".join(str(int(x)) for x in lab) + "\n")
            _write_text(gt.with_name(f"{stem}.deviation.txt"), "\n".join(f"{x:.9g}" for x in dev) + "\n")
    print(f"wrote {len(plan)} scans in {time.perf_counter() - t0:.0f} s")


def _written_sensor(view, args, rng):
    """The sensor origin a sidecar records for ``view`` (world frame): ``--standoff`` metres along the view's axis
    from its centre, the axis turned by up to ``--origin-tilt`` degrees (the view's own, drawn after every other draw
    of the scan, so that the scans do not change with it)."""
    if args.standoff == SENSOR_DISTANCE and not args.origin_tilt:
        return view["sensor"]
    from datasets.scanner import written_origin

    centre = view["R"] @ view["local_centre"] + view["t"]
    factor = args.standoff / SENSOR_DISTANCE
    return written_origin(view["sensor"], centre, (factor, factor), args.origin_tilt, rng)


def _write_text(path, text):
    from datasets.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)
