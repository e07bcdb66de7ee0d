"""Real range scans: a benchmark built from the Stanford bunny's ten Cyberware views, scored at the defaults.

The tree (built once, cached by its parameters: ``benchmarks.cache``) comes from ``../shared/realscans/bunny/`` (ten
real range images in metres, ``bun.conf`` aligning them), in the layout the datasets importer reads:

    train/good/*.ply, test/good/*.ply, test/{bump,dent,foreign,missing}/*.ply    points only (no normals), metres
    <same stem>.json    {"sensor_origin": [x, y, z], "view": ..., "stray_points": [...], "rotation_deg": ...}
    ground_truth/<defect>/<stem>.txt    one 0/1 per point

Every scan is one real view, a fresh random subset of its points (4,000 by default) with the scanner's own stray
points kept, a few synthetic spurious returns on half the scans (points on the sensor's ray, 5-30 mm in front of
the surface: what a real scanner's multipath and mixed pixels give; labelled 0, listed in the sidecar), and a
random pose change of up to ``--jitter`` degrees about the part's centre (and a shift of up to ``--shift`` of its diagonal:
parts placed by hand). Defects are made in the real points
(the full-resolution view, before subsampling), so everything outside them is real data:

- dent / bump: the points of the patch (radius ``RADIUS_RANGE`` x the part's diagonal, ``datasets.defects``'
  sizes) moved along the site's normal by the same profile ``(1 - (r/R)^2)^2 * height`` as the mesh defects;
- missing: a ball of radius R centred on the surface removed; each point inside it is replaced by where its
  sensor ray leaves the ball (the pit's back wall as the sensor sees it) plus the scan's own range noise;
- foreign: a small sphere or box (1.6 R across, partly sunk, as ``datasets.defects``) put on the surface; every
  point whose sensor ray meets it first is replaced by the hit plus the scan's range noise (its visible side, and
  the surface it hides).

The range grid's conventions, worked out from the data (printed when the tree is built): ``bun.conf`` line
``bmesh FILE tx ty tz qx qy qz qw`` maps a view's points by p_world = R(q)^-1 p + t with q scalar-last (the other
readings leave the views apart; this one puts 89-99 % of each view within 0.5 mm of another view), and the scanner
looks down -z of each view's own coordinates: 99.6-100 % of the range grid's outward normals have n_z > 0. The
Cyberware 3030 sweeps linearly (orthographic along x), so the sensor origin stored is a point 1 m along the view's
+z axis from the view's centre, mapped to the world like the points.

The run: the tree imported (``datasets.importer.import_tree``, as ``python -m datasets import``), a model trained
with the trainer's defaults (``benchmarks.cache.trained_model``), scored the README's way on an uncalibrated copy
(``benchmarks.inspect_api.calibrate_and_score``, ``--maps all``). Printed: object AUROC per defect type and overall
next to the nearest-neighbour baseline, and that of the default's two terms alone (the point score, the ray score,
from the same run's scores.csv), the fractions of good and defective test scans flagged at the calibrated
default, seconds per scan. ``--diagnose`` then reads the run's per-point scores (the inspection API, as ``score``
computes them) and prints what the worst points of the good scans are (border, grazing, sparse, stray, rarely
covered by training), with pictures in the run's ``diagnosis/``.
"""
import json
import time
from pathlib import Path

import numpy as np

from benchmarks import baselines, cache, inspect_api, metrics
from benchmarks.table import format_table

DESCRIPTION = ("real range scans: a benchmark tree from the Stanford bunny's ten Cyberware views with defects made "
               "in the real points, trained and scored at the defaults, next to the nearest-neighbour baseline")
BUNNY = cache.REAL_SCANS / "bunny"
WORK = "results/real"
KINDS = ("bump", "dent", "foreign", "missing")
SENSOR_DISTANCE = 1.0  # metres along a view's +z from its centre: the Cyberware 3030's sweep is nearly orthographic


def add_arguments(p):
    p.add_argument("--source", default=str(BUNNY), help="the range scans and bun.conf (default: %(default)s)")
    p.add_argument("--train", type=int, default=32, help="good training scans (default: %(default)s)")
    p.add_argument("--test-good", type=int, default=16, help="good test scans (default: %(default)s)")
    p.add_argument("--per-defect", type=int, default=16, help="test scans per defect type (default: %(default)s)")
    p.add_argument("--points", type=int, default=4000, help="points per scan (default: %(default)s)")
    p.add_argument("--jitter", type=float, default=2.0, help="pose change, degrees (default: %(default)s)")
    p.add_argument("--shift", type=float, default=0.0, help="and a shift of up to this fraction of the part's "
                                                            "diagonal, per scan (parts placed by hand; default none)")
    inspect_api.add_align_options(p)
    p.add_argument("--standoff", type=float, default=SENSOR_DISTANCE,
                   help="the sensor origin the sidecars record: this many metres along the view's axis from the "
                        "view's centre, as a user writes a nominal stand-off (default %(default)s: the sweep's "
                        "near-orthographic rays; the defects are made with that one either way)")
    p.add_argument("--origin-tilt", type=float, default=0.0, metavar="DEG",
                   help="and the recorded axis turned by up to DEG degrees per scan (default: none)")
    p.add_argument("--strays", type=int, default=4, help="up to this many spurious returns on half the scans "
                                                         "(default: %(default)s)")
    p.add_argument("--size", type=float, default=1.0, help="defect size factor on datasets.defects' ranges")
    p.add_argument("--seed", type=int, default=0, help="the tree's seed (default: %(default)s)")
    p.add_argument("--train-seed", type=int, default=0, help="the training's seed (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: the trainer's)")
    p.add_argument("--representation", choices=("siren", "grid"), default=None,
                   help="the latent model's representation (default: the trainer's)")
    p.add_argument("--no-rays", action="store_true", help="calibrate without the ray score (default: the "
                                                          "inspection's choice: with it, the scans have sensor origins)")
    p.add_argument("--diagnose", action="store_true", help="also the per-point analysis and pictures of the run")
    p.add_argument("--folds", choices=("on", "off", "both"), default="off",
                   help="calibrate without fold models (off: the default), with 2 fold models trained into the cached "
                        "model (on: train_latent.py --calibration-folds 2), or both")
    p.add_argument("--point-scores", default=None, metavar="LIST",
                   help="also each of these point scores alone (NAME[:AGGREGATE],...; no ray score, one calibration "
                        "each), a row each: the ablation suite's --trees")
    p.add_argument("--cache", default=cache.CACHE, help="tree, collection and model (default: %(default)s)")
    p.add_argument("--work", default=WORK, help="scored runs (default: %(default)s)")
    p.add_argument("--progress", action="store_true", help="progress bars")


def run(args):
    data = real_collection(args)
    from autodecoder.latent.folds import SUGGESTED_FOLDS

    model = cache.trained_model(data, root=args.cache, seed=args.train_seed, epochs=args.epochs,
                                representation=args.representation,
                                calibration_folds=None if args.folds == "off" else SUGGESTED_FOLDS)
    run_dir = Path(args.work) / data.parent.name / ("defaults" + (f"_e{args.epochs}" if args.epochs else "")
                                                    + (f"_{args.representation}" if args.representation else "")
                                                    + (f"_t{args.train_seed}" if args.train_seed else "")
                                                    + ("_norays" if args.no_rays else "")
                                                    + {True: "_aligned", False: "_noalign", None: ""}[args.align])
    figures = score(data, model, run_dir, args)
    if args.diagnose:
        diagnose(data, Path(figures["run"]))
    return figures


# ---- reading the Stanford range data ---------------------------------------------------------------------------------
def read_range_ply(path):
    """Points (N, 3) in the view's own metres and the range grid (rows, cols) of point indices (-1: no return)."""
    with open(path) as f:
        header = []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: no end_header")
            header.append(line.strip())
            if line.strip() == "end_header":
                break
        info = {h.split()[1]: h.split()[2] for h in header if h.startswith("obj_info")}
        n_vertex = int(next(h for h in header if h.startswith("element vertex")).split()[2])
        n_grid = int(next(h for h in header if h.startswith("element range_grid")).split()[2])
        lines = f.read().split("\n")
    points = np.array([r.split()[:3] for r in lines[:n_vertex]], dtype=np.float64)
    grid = np.full(n_grid, -1, dtype=np.int64)
    for i, r in enumerate(lines[n_vertex:n_vertex + n_grid]):
        if r and r[0] != "0":
            grid[i] = int(r.split()[1])
    return points, grid.reshape(int(info["num_rows"]), int(info["num_cols"]))


def read_conf(path):
    """``[(file name, R (3, 3), t (3,))]`` of a scanalyze ``.conf``: p_world = R @ p_view + t (see the module doc)."""
    from scipy.spatial.transform import Rotation

    views = []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts or parts[0] != "bmesh":
            continue
        if len(parts) != 9:
            raise ValueError(f"{path}: expected 'bmesh FILE tx ty tz qx qy qz qw', got {line!r}")
        t = np.array(parts[2:5], dtype=np.float64)
        rot = Rotation.from_quat(np.array(parts[5:9], dtype=np.float64)).inv()
        views.append((parts[1], rot.as_matrix(), t))
    if not views:
        raise ValueError(f"{path}: no 'bmesh' lines")
    return views


def grid_normals(points, grid):
    """Per-point normals from the range grid's own neighbours (cross product of the row and column steps), signed so
    that +z (toward the scanner) is positive; NaN where a point has no right and lower neighbour."""
    n = np.full(points.shape, np.nan)
    ok = (grid[:-1, :-1] >= 0) & (grid[1:, :-1] >= 0) & (grid[:-1, 1:] >= 0)
    r, c = np.nonzero(ok)
    a = points[grid[r, c]]
    cross = np.cross(points[grid[r, c + 1]] - a, points[grid[r + 1, c]] - a)
    cross /= np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-15)
    cross *= np.sign(np.median(cross[:, 2]))
    n[grid[r, c]] = cross
    return n


def load_views(root=BUNNY):
    """Every view aligned into the world frame: list of dicts name, points (N, 3), sensor (3,), grid_normals, R, t."""
    views = []
    for name, rot, t in read_conf(root / "bun.conf"):
        local, grid = read_range_ply(root / name)
        sensor_local = local.mean(0) + np.array([0.0, 0.0, SENSOR_DISTANCE])
        views.append(dict(name=Path(name).stem, points=local @ rot.T + t, sensor=rot @ sensor_local + t,
                          grid_normals=grid_normals(local, grid) @ rot.T, R=rot, t=t, local_centre=local.mean(0)))
    return views


def check_views(views):
    """Print the two checks of the conventions: overlap of each aligned view with the others, and the fraction of
    its range-grid normals facing its sensor origin. Returns {view: (overlap, facing)}."""
    from scipy.spatial import cKDTree

    out = {}
    for v in views:
        others = np.concatenate([w["points"] for w in views if w is not v])
        d = cKDTree(others).query(v["points"][::10])[0]
        n = v["grid_normals"]
        ok = np.all(np.isfinite(n), axis=1)
        facing = np.mean(np.einsum("ij,ij->i", n[ok], v["sensor"] - v["points"][ok]) > 0)
        out[v["name"]] = (float(np.mean(d < 5e-4)), float(facing))
        print(f"  {v['name']:<9} {len(v['points']):6d} points; within 0.5 mm of another view {out[v['name']][0]:.2f}; "
              f"grid normals facing the sensor origin {facing:.4f}")
    return out


# ---- defects in real points ------------------------------------------------------------------------------------------
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


def pick_site(points, normals, sensor, radius, rng, max_normal_deg=35.0, min_facing=0.6):
    """A defect site the sensor sees well on a smooth patch: (index, unit normal). Like
    ``datasets.defects.pick_spot`` but on real points with estimated normals."""
    from scipy.spatial import cKDTree

    to_eye = sensor - points
    facing = np.einsum("ij,ij->i", normals, to_eye) / np.linalg.norm(to_eye, axis=1)
    cand = rng.permutation(len(points))[:256]
    tree = cKDTree(points)
    flat, counts = np.empty(len(cand)), np.empty(len(cand))
    for k, (i, near) in enumerate(zip(cand, tree.query_ball_point(points[cand], radius))):
        flat[k] = np.min(normals[near] @ normals[i])
        counts[k] = len(near)
    good = (flat >= np.cos(np.radians(max_normal_deg))) & (facing[cand] >= min_facing) & (counts >= 0.6 * counts.max())
    i = cand[rng.choice(np.flatnonzero(good))] if good.any() else \
        cand[np.argmax(flat + facing[cand] + counts / counts.max())]
    # the site normal: the mean over the patch's inner half, less noisy than one point's
    near = tree.query_ball_point(points[i], 0.5 * radius)
    n = normals[near].mean(0)
    return i, n / np.linalg.norm(n)


def _ray_sphere(origin, dirs, center, radius):
    """Entry and exit distances (m,) of rays origin + t dirs (unit) through a sphere (NaN where missed)."""
    oc = origin - center
    b = dirs @ oc
    disc = b * b - (oc @ oc - radius * radius)
    s = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return -b - s, -b + s


def _ray_box(origin, dirs, center, axes, half):
    """Entry distance (m,) of rays into an oriented box (axes rows = its unit axes, half extents), NaN where missed."""
    o = axes @ (origin - center)
    d = dirs @ axes.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((t_near <= t_far) & (t_far > 0), t_near, np.nan)


def inject(kind, points, normals, sensor, diagonal, noise, rng, size=1.0):
    """A defect made in a real view's points. Returns (new points (N, 3), labels (N,) uint8, info dict).

    Sizes follow ``datasets.defects`` (RADIUS_RANGE, HEIGHT_RANGE as fractions of the diagonal) times ``size``.
    """
    from datasets.defects import HEIGHT_RANGE, RADIUS_RANGE

    radius = rng.uniform(*RADIUS_RANGE) * diagonal * size
    height = rng.uniform(*HEIGHT_RANGE) * diagonal * size
    i, n0 = pick_site(points, normals, sensor, radius, rng)
    c = points[i]
    out = points.copy()
    labels = np.zeros(len(points), np.uint8)
    info = {"kind": kind, "center": c.tolist(), "normal": n0.tolist(), "radius": radius}
    if kind in ("dent", "bump"):
        r = np.linalg.norm(points - c, axis=1)
        moving = (r < radius) & (normals @ n0 > 0.5)
        profile = (1.0 - (r[moving] / radius) ** 2) ** 2
        out[moving] += ((height if kind == "bump" else -height) * profile)[:, None] * n0
        labels[moving] = 1
        info["height"] = height
        return out, labels, info
    dirs = points - sensor
    dist = np.linalg.norm(dirs, axis=1)
    dirs /= dist[:, None]
    if kind == "missing":
        inside = np.linalg.norm(points - c, axis=1) < radius
        _, t_exit = _ray_sphere(sensor, dirs[inside], c, radius)
        hit = np.isfinite(t_exit)
        idx = np.flatnonzero(inside)[hit]
        t = t_exit[hit] + rng.normal(0.0, noise, len(idx))
        out[idx] = sensor + t[:, None] * dirs[idx]
        labels[idx] = 1
        info["depth"] = radius
        return out, labels, info
    # foreign: a sphere or box about 1.6 R across, sunk into the surface as datasets.defects does
    shape = ("sphere", "box")[rng.integers(2)]
    if shape == "sphere":
        r_obj, sink = 0.8 * radius, 0.4 * radius
        center = c + n0 * (r_obj - sink)
        t_hit, _ = _ray_sphere(sensor, dirs, center, r_obj)
    else:
        half = np.array([0.8, 0.65, 0.65]) * radius
        a = np.cross(n0, rng.normal(size=3))
        a /= np.linalg.norm(a)
        axes = np.stack([a, np.cross(n0, a), n0])  # local z along the normal, a random turn about it
        center = c + n0 * (half[2] - 0.35 * radius)
        t_hit = _ray_box(sensor, dirs, center, axes, half)
    hit = np.isfinite(t_hit) & (t_hit < dist)
    t = t_hit[hit] + rng.normal(0.0, noise, hit.sum())
    out[hit] = sensor + t[:, None] * dirs[hit]
    labels[hit] = 1
    info["shape"] = shape
    return out, labels, info


def spurious_returns(points, sensor, count, rng):
    """``count`` stray points on the sensor's rays to random scan points, 5-30 mm in front of the surface."""
    if count == 0:
        return np.empty((0, 3))
    p = points[rng.choice(len(points), count, replace=False)]
    d = p - sensor
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return p - rng.uniform(0.005, 0.03, (count, 1)) * d


def random_rotation(max_deg, rng):
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * np.radians(rng.uniform(0, max_deg))).as_matrix()


# ---- the tree ----------------------------------------------------------------------------------------------------
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
        if kind in KINDS:
            pts, labels, info = inject(kind, pts, v["normals"], v["sensor"], diagonal, v["noise"], rng, args.size)
        keep = np.sort(rng.choice(len(pts), min(args.points, len(pts)), replace=False))
        pts, labels = pts[keep], labels[keep]
        n_stray = int(rng.integers(1, args.strays + 1)) if args.strays and rng.random() < 0.5 else 0
        stray = spurious_returns(pts, v["sensor"], n_stray, rng)
        at = np.sort(rng.choice(len(pts) + n_stray, n_stray, replace=False))
        order = np.setdiff1d(np.arange(len(pts) + n_stray), at)
        merged = np.empty((len(pts) + n_stray, 3))
        merged[order], merged[at] = pts, stray
        lab = np.zeros(len(merged), np.uint8)
        lab[order] = labels
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


# ---- the run -----------------------------------------------------------------------------------------------------
def score(data, model, run_dir, args):
    """Score the run at the defaults, print the table next to the baseline. Returns the figures."""
    from datasets import ScanCollection

    from benchmarks.table import verdicts_table

    verdict_rows = []
    for folds in {"on": (True,), "off": (False,), "both": (False, True)}[args.folds]:
        one_dir = run_dir if folds else run_dir.with_name(run_dir.name + "_nofolds")
        t0 = time.perf_counter()
        summary = inspect_api.calibrate_and_score(model, data, one_dir, rays=False if args.no_rays else None,
                                                  maps="all", align=args.align, progress=args.progress, folds=folds,
                                                  echo=lambda line: print(f"  real: {line}"))
        t_score = time.perf_counter() - t0
        scored = inspect_api.read_scores(one_dir / "results")
        figures = inspect_api.summary_figures(summary)
        verdict_rows.append(dict(part="bunny", **figures, oracle=metrics.oracle_flagged(scored["score"],
                                                                                        scored["label"]),
                                 exact_alpha=metrics.exact_alpha_flagged(scored["score"], scored["label"],
                                                                         figures["alpha"]),
                                 method="toolkit" + ("" if folds else ", no folds")))
    print(verdicts_table(verdict_rows))
    info = inspect_api.model_info(model)
    held = set(info["heldback_names"])
    with ScanCollection(data) as c:
        train = c.read_many([i for i in c.select(split="train") if c.names[i] not in held])
        test = c.read_many([c.index_of(n) for n in scored["name"]])
    # the baseline registered as the toolkit registers: onto the model's common pose (training scans placed by
    # hand), or, where the calibration registered, each scan onto the training scans; timed per test scan
    framed = inspect_api.in_common_frame(model, train)
    train = train if framed is None else framed
    t0 = time.perf_counter()
    if framed is not None:
        test = inspect_api.in_common_frame(model, test)
    elif summary.get("aligned"):
        test = inspect_api.registered_onto(test, train)
    registered = framed is not None or bool(summary.get("aligned"))
    nn = np.array([v for v, _ in baselines.nn_baseline(np.concatenate([s.points for s in train]), test)])
    t_nn = (time.perf_counter() - t0) / len(test)
    ours = metrics.auroc_per_defect(scored["score"], scored["label"], scored["defect"])
    base = metrics.auroc_per_defect(nn, scored["label"], scored["defect"])
    bad = scored["label"] != metrics.GOOD
    flagged = {"good": float(scored["flagged"][~bad].mean()), "defective": float(scored["flagged"][bad].mean())}
    cols = [k for k in (*KINDS, "overall") if k in ours]
    print(f"\nreal bunny ({len(train)} training scans for the NN baseline, {int((~bad).sum())} good and "
          f"{int(bad.sum())} defective test scans); object AUROC")
    nn_name = "nearest-neighbour top5%" + (" (ICP)" if registered else "")
    # the default's two terms alone (issue 29: rays must not cost the point score anything on real parts)
    terms = {name: metrics.auroc_per_defect(scored[key], scored["label"], scored["defect"])
             for name, key in (("point score alone", "score_points"), ("ray score alone", "score_rays"))
             if key in scored and np.isfinite(scored[key]).all()}
    alone = {}
    if args.point_scores:
        alone = inspect_api.point_score_runs(model, data, run_dir.parent, inspect_api.parse_point_scores(
            args.point_scores), align=args.align, progress=args.progress)
        terms.update({f"{spec} alone (calibrated)": figures["auroc"] for spec, figures in alone.items()})
    print(format_table([{"method": nn_name, **base}, {"method": "toolkit (defaults)", **ours}]
                       + [{"method": f"toolkit, {name}", **one} for name, one in terms.items()],
                       [("method", "", "")] + [(k, k, ".3f") for k in cols]))
    print(f"flagged at the calibrated default (alpha {summary.get('alpha')}): good {flagged['good']:.3f}, "
          f"defective {flagged['defective']:.3f}")
    print(f"seconds per scan: toolkit {summary.get('seconds_per_scan', float('nan')):.2f} (calibration and scoring "
          f"wall {t_score / len(test):.2f}); NN baseline {t_nn:.3f}; training {info['train_seconds'] or 0:.0f} s")
    return {"collection": str(data), "model": str(model), "run": str(one_dir), "toolkit": ours, "nn": base,
            "terms": terms, "point_scores": alone,
            "flagged": flagged, "seconds_per_scan": summary.get("seconds_per_scan"), "nn_seconds_per_scan": t_nn,
            "train_seconds": info["train_seconds"], "summary": inspect_api.summary_figures(summary),
            "verdicts": verdict_rows}


# ---- diagnosis -------------------------------------------------------------------------------------------------------
def point_features(scan, train_tree, train_owner, n_train):
    """Per-point descriptors of a scan (collection frame): grazing cosine, border offset, local sparsity, stray flag,
    distance to the nearest training point and how many training scans cover the point, both in local spacings."""
    from scipy.spatial import cKDTree

    from datasets.outliers import stray_points

    p, n = np.asarray(scan.points, np.float64), np.asarray(scan.normals, np.float64)
    ray = scan.sensor_origin - p
    cos = np.abs(np.einsum("ij,ij->i", n, ray / np.linalg.norm(ray, axis=1, keepdims=True)))
    d, idx = cKDTree(p).query(p, 17)
    radius = d[:, -1]
    off = p[idx[:, 1:]].mean(1) - p
    off -= np.einsum("ij,ij->i", off, n)[:, None] * n
    border = np.linalg.norm(off, axis=1) / radius  # ~0 inside, ~0.4 or more at the scan's edge
    spacing = d[:, 1]
    sparse = d[:, 8] / np.median(d[:, 8])
    near, _ = train_tree.query(p, 1)
    owners = train_tree.query_ball_point(p, 2.0 * np.median(d[:, 8]))
    cover = np.array([len(set(train_owner[o])) for o in owners]) / n_train
    return dict(cos=cos, border=border, sparse=sparse, stray=stray_points(p).astype(float),
                nearest=near / np.median(spacing), cover=cover)


CATEGORIES = (("border", lambda f: f["border"] > 0.35), ("grazing", lambda f: f["cos"] < 0.3),
              ("sparse", lambda f: f["sparse"] > 2.0), ("stray", lambda f: f["stray"] > 0),
              ("rarely covered", lambda f: f["cover"] < 0.1), ("far from training", lambda f: f["nearest"] > 3.0))


def view_picture(path, scan, values, title, labels=None, vmax=None):
    """The scan seen from its sensor (orthographic), coloured by per-point score; defect points circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.asarray(scan.points, np.float64)
    c = p.mean(0)
    z = scan.sensor_origin - c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    q = (p - c) @ np.stack([x, np.cross(z, x), z]).T
    order = np.argsort(q[:, 2])  # far points first, near ones on top
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.4, 1]})
    vmax = vmax or max(np.quantile(values, 0.995), 1e-9)
    sc = axes[0].scatter(q[order, 0], q[order, 1], c=values[order], s=4, cmap="turbo", vmin=0, vmax=vmax)
    if labels is not None and labels.any():
        axes[0].scatter(q[labels > 0, 0], q[labels > 0, 1], s=14, facecolors="none", edgecolors="k", lw=0.3)
    top = np.argsort(values)[-max(1, len(values) // 100):]
    axes[0].scatter(q[top, 0], q[top, 1], s=40, marker="x", c="m", lw=0.8, label="top 1 % (the scan's score)")
    axes[0].legend(loc="lower right", fontsize=8)
    axes[0].set_aspect("equal")
    fig.colorbar(sc, ax=axes[0], fraction=0.04)
    bins = np.linspace(0, max(float(values.max()), vmax), 60)
    lab = np.zeros(len(values), bool) if labels is None else labels > 0
    axes[1].hist([values[~lab], values[lab]], bins=bins, label=["good points", "defect points"], log=True)
    axes[1].legend()
    axes[1].set_xlabel("point score (all values; the map's colours stop at the left panel's bar)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def diagnose(data, run_dir):
    """Per-point scores of the run's test scans (the calibrated model through the inspection API, as ``score``
    computes them), what the worst points of the good scans are, and pictures of the worst good and the missed
    defective scans."""
    from scipy.spatial import cKDTree
    from scipy.stats import spearmanr

    from datasets import ScanCollection

    model = Path(run_dir) / "model.pt"
    pics = Path(run_dir) / "diagnosis"
    pics.mkdir(exist_ok=True)
    info = inspect_api.model_info(model)
    held = set(info["heldback_names"])
    with ScanCollection(data) as c:
        train = [c[i] for i in c.select(split="train") if c.names[i] not in held]
    test, results = inspect_api.point_maps(model, data, fields=True)
    vals = [r["point_scores"] for r in results]
    score = np.array([r["score"] for r in results])
    owner = np.concatenate([np.full(len(s), k) for k, s in enumerate(train)])
    tree = cKDTree(np.concatenate([s.points for s in train]))
    good = np.array([s.label == metrics.GOOD for s in test])
    feats = [point_features(s, tree, owner, len(train)) for s in test]
    settings = inspect_api.calibration_settings(model)
    print(f"point score {settings['point_score']}, aggregate {settings['aggregate']}, noise floor "
          f"{settings['noise']:.4g} (model frame), kernel lengthscale {settings['lengthscale']:.4g}, median point "
          f"spacing of the test scans "
          f"{np.median([np.median(cKDTree(s.points).query(s.points, 2)[0][:, 1]) for s in test]):.4g}")
    print("\ngood test scans: the worst 1 % of each scan's points against all its points")
    print(f"{'scan':<26}{'score':>7}" + "".join(f"{k[:14]:>16}" for k, _ in CATEGORIES))
    for i in np.flatnonzero(good)[np.argsort(-score[good])]:
        v, f = vals[i], feats[i]
        top = np.argsort(v)[-max(1, len(v) // 100):]
        cells = [f"{rule(f)[top].mean():6.2f} / {rule(f).mean():5.2f}" for _, rule in CATEGORIES]
        print(f"{test[i].name[-24:]:<26}{score[i]:7.2f}" + "".join(f"{c:>16}" for c in cells))
    allv = np.concatenate([vals[i] for i in np.flatnonzero(good)])
    print("\nall good test points: median / 99th percentile of the point score, inside and outside each category")
    for k, rule in CATEGORIES:
        m = np.concatenate([rule(feats[i]) for i in np.flatnonzero(good)])
        if m.any():
            print(f"  {k:<18} in: {np.median(allv[m]):6.2f} / {np.quantile(allv[m], 0.99):6.2f}   out: "
                  f"{np.median(allv[~m]):6.2f} / {np.quantile(allv[~m], 0.99):6.2f}   ({m.mean():.3f} of the points)")
    print("  Spearman rank correlation of the point score with: " + ", ".join(
        f"{k} {spearmanr(allv, np.concatenate([feats[i][k] for i in np.flatnonzero(good)]))[0]:+.2f}"
        for k in ("cos", "border", "sparse", "nearest", "cover")))
    thr = score[good].max()
    print(f"\ndefective test scans below the worst good scan's score ({thr:.2f}):")
    for kind in KINDS:
        idx = [i for i, s in enumerate(test) if s.defect == kind]
        missed = [i for i in idx if score[i] <= thr]
        dp = np.concatenate([vals[i][test[i].point_labels > 0] for i in idx])
        print(f"  {kind:<8} {len(missed)}/{len(idx)} missed; defect points: median {np.median(dp):.2f}, "
              f"90th pct {np.quantile(dp, 0.9):.2f}; their scans' good points: 99th pct "
              f"{np.quantile(np.concatenate([vals[i][test[i].point_labels == 0] for i in idx]), 0.99):.2f}")
    vmax = float(np.quantile(allv, 0.999))
    for i in np.flatnonzero(good)[np.argsort(-score[good])][:3]:
        view_picture(pics / f"good_{test[i].name.split('/')[-1]}.png", test[i], vals[i],
                     f"{test[i].name}: worst good scans, score {score[i]:.2f} (threshold region)", vmax=vmax)
    for kind in KINDS:
        idx = [i for i, s in enumerate(test) if s.defect == kind]
        for i in sorted(idx, key=lambda i: score[i])[:2]:
            view_picture(pics / f"missed_{kind}_{test[i].name.split('/')[-1]}.png", test[i], vals[i],
                         f"{test[i].name}: lowest-scoring {kind}, score {score[i]:.2f} (worst good {thr:.2f})",
                         labels=test[i].point_labels, vmax=vmax)
    for i in [*np.flatnonzero(good)[np.argsort(-score[good])][:2],
              min((i for i, s in enumerate(test) if s.defect == "bump"), key=lambda i: score[i])]:
        section_picture(pics / f"section_{test[i].name.split('/')[-1]}.png", test[i], vals[i], results[i]["field"],
                        f"{test[i].name}: the projected mean surface (E f = 0) through the worst non-stray point (x), "
                        f"real points within 1 spacing of the section")
    print(f"pictures in {pics}")


def section_picture(path, scan, values, field, title):
    """A cross-section through the scan's worst point, in the plane holding the ray to the sensor: the projected
    mean surface (the zero level of E f) and the real points near the plane, coloured by score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import cKDTree

    from datasets.outliers import stray_points

    p = np.asarray(scan.points, np.float64)
    worst = int(np.argmax(np.where(stray_points(p), -np.inf, values)))  # the worst point on the surface
    w = p[worst]
    z = scan.sensor_origin - w
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(scan.normals[worst], np.float64))
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # the plane spanned by z (toward the sensor) and y; x is its normal
    half = 0.15
    u = np.linspace(-half, half, 160)
    gu, gv = np.meshgrid(u, u)
    grid = w + gu.reshape(-1, 1) * y + gv.reshape(-1, 1) * z
    mean = np.asarray(field.mean(grid)).reshape(gu.shape)
    spacing = float(np.median(cKDTree(p).query(p, 2)[0][:, 1]))
    near = np.abs((p - w) @ x) < spacing
    q = (p[near] - w) @ np.stack([y, z]).T
    fig, ax = plt.subplots(figsize=(7, 7))
    lim = float(np.quantile(np.abs(mean), 0.95))
    ax.contourf(gu, gv, mean, levels=21, cmap="RdBu_r", vmin=-lim, vmax=lim, alpha=0.5)
    ax.contour(gu, gv, mean, levels=[0.0], colors="k", linewidths=1.2)
    sc = ax.scatter(q[:, 0], q[:, 1], c=values[near], s=14, cmap="turbo", vmin=0,
                    vmax=max(float(np.quantile(values, 0.995)), 1e-9), edgecolors="none")
    ax.scatter([0], [0], marker="x", c="m", s=60)
    ax.annotate("to the sensor", xy=(-0.13, 0.14), xytext=(-0.13, 0.09), arrowprops=dict(arrowstyle="->"))
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    fig.colorbar(sc, ax=ax, fraction=0.04, label="point score")
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
