"""Scans as data: the HDF5 scan collection's input and output, and a gallery of the synthetic defects.

Modes (``--mode``):

``io`` (default)
    Per compression (``--compression``, the first also for the rest of the run): the write throughput of
    ``--scans`` synthetic partial scans of ``--points`` points (a noisy, randomly placed hemisphere each, smooth like
    real surfaces), the file's size, and the latency of random single-scan reads (wall and CPU time: on a shared
    machine the wall time mostly measures the other users' load); the peak RSS while streaming every scan of two
    collection sizes (``--small-scans`` and ``--scans``, each in a fresh interpreter so that its peak belongs to one
    size only); the import throughput of a tree of PLY files with normals and without (normals estimated). Writes
    nothing outside ``--out`` (a temporary folder, removed at the end, by default).
``gallery``
    A PNG of one good and one defective virtual scan per defect type of the built-in part and of fandisk, each seen
    from its own sensor: per part a row shaded by the angle between normal and ray with the labelled defect points
    in red, and a row coloured by each point's distance to the undamaged part (the defect where it really is,
    whatever the labels say); and, unless ``--no-timing``, the time to synthesise fandisk's default collection
    (``benchmarks.cache.COLLECTION_DEFAULTS``, not cached: the synthesis is what is timed).
``views``
    Which template points a rendered template view keeps (:func:`datasets.templates.visible_points`, what the
    Real3D-AD importer trains and calibrates on) against what a ray caster on the true mesh sees, per part of
    ``--parts`` and template seed of ``--seeds``: a template of ``--template-points`` points sampled on the part's
    mesh with depth noise ``--noise`` x its diagonal along the normal, normals estimated as the importer does, 8
    sensors at 2 diagonals; a point is truly visible when its true face looks at the sensor and the mesh's first hit
    on the ray to it lies within 3 % of the diagonal of it. Precision and recall per view (mean and minimum), beside
    open3d's hidden-point removal (radius 1000 template diameters, back faces removed), the rule before.
"""
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DESCRIPTION = "scan collections: HDF5 write/read/stream/import throughput; the gallery of synthetic defects"
MODES = ("io", "gallery", "views")
COMPRESSIONS = {"gzip": ("gzip", 1), "gzip4": ("gzip", 4), "lzf": ("lzf", None), "none": (None, None)}
POINTS = {"io": 20_000, "gallery": 4000}

# run in a fresh interpreter (from the repository root) so that its peak RSS (VmHWM) belongs to one collection only
_ITERATE = r"""
from datasets import ScanCollection
def hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
with ScanCollection({path!r}) as c:
    before = hwm()
    total = 0
    for s in c:
        total += len(s)
print(before, hwm(), total)
"""


def add_arguments(parser):
    parser.add_argument("--mode", choices=MODES, default="io", help="what to measure (default: %(default)s)")
    parser.add_argument("--points", type=int, default=None, help=f"points per scan (default: {POINTS})")
    parser.add_argument("--out", type=Path, default=None,
                        help="io: work folder (default: a temporary one, removed); gallery: the PNG (default: "
                             "results/defect_gallery.png)")
    io = parser.add_argument_group("io")
    io.add_argument("--scans", type=int, default=2000)
    io.add_argument("--compression", default="gzip,lzf,none",
                    help="comma list among gzip (level 1, the default), gzip4, lzf, none (first: rest of run)")
    io.add_argument("--small-scans", type=int, default=500, help="second collection size for the RSS comparison")
    io.add_argument("--import-files", type=int, default=200)
    io.add_argument("--import-points", type=int, default=20000)
    gallery = parser.add_argument_group("gallery")
    gallery.add_argument("--noise", type=float, default=0.002, help="depth noise of the scans")
    gallery.add_argument("--seed", type=int, default=0)
    gallery.add_argument("--no-timing", action="store_true", help="skip timing the default fandisk collection")
    views = parser.add_argument_group("views")
    views.add_argument("--parts", default="builtin,fandisk", help="views: comma-separated parts (default: %(default)s)")
    views.add_argument("--seeds", default="0,1", help="views: template seeds (default: %(default)s)")
    views.add_argument("--template-points", type=int, default=10000, help="views: points per template")


def run(args):
    return {"io": _io, "gallery": _gallery, "views": _views}[args.mode](args)


# --- io --------------------------------------------------------------------------------------------------------

def _scan_stream(n_scans, n_points, seed=0):
    """Synthetic partial scans, one at a time (writing never holds the collection): a noisy, randomly placed
    hemisphere each, what one view of a ball sees."""
    import numpy as np

    from datasets import Scan

    rng = np.random.default_rng(seed)
    for i in range(n_scans):
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[:, 2] = np.abs(d[:, 2])
        points = 0.3 * d + rng.uniform(-0.1, 0.1, 3) + rng.normal(scale=1e-3, size=(n_points, 3))
        yield Scan(name=f"train/good/{i:06d}", points=points, normals=d, split="train")


def _write(path, n_scans, n_points, compression):
    """Seconds to write the collection, and its size in bytes."""
    from datasets import ScanCollection

    t = time.perf_counter()
    ScanCollection.create(path, _scan_stream(n_scans, n_points), compression=compression, overwrite=True)
    return time.perf_counter() - t, path.stat().st_size


def _reads(path, n_reads=200, seed=1):
    """Random single-scan reads: (wall median, wall p95, CPU median, CPU p95) in ms, the page cache warm."""
    import numpy as np

    from datasets import ScanCollection

    rng = np.random.default_rng(seed)
    with ScanCollection(path) as c:
        idx = rng.integers(0, len(c), n_reads)
        c[0]  # the first read pays for the chunk-index B-tree pages
        wall, cpu = [], []
        for i in idx:
            t, t_cpu = time.perf_counter(), time.process_time()
            c[int(i)]
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - t_cpu)
    wall, cpu = np.array(wall) * 1e3, np.array(cpu) * 1e3
    return (float(np.median(wall)), float(np.percentile(wall, 95)), float(np.median(cpu)),
            float(np.percentile(cpu, 95)))


def _stream_rss(path):
    """(RSS after opening, peak RSS, points streamed) of iterating over every scan, in a fresh interpreter."""
    from benchmarks.cache import ROOT

    out = subprocess.run([sys.executable, "-c", _ITERATE.format(path=str(Path(path).resolve()))], check=True,
                         capture_output=True, text=True, cwd=ROOT).stdout.split()
    return float(out[0]), float(out[1]), int(out[2])


def _import(folder, n_files, n_points, normals):
    """Seconds to import a tree of ``n_files`` PLY sphere scans (half train/good, half test/good)."""
    import numpy as np

    from datasets import write_cloud
    from datasets.importer import import_tree

    rng = np.random.default_rng(2)
    src = folder / ("tree_normals" if normals else "tree_no_normals")
    for i in range(n_files):
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        split = "train/good" if i < n_files // 2 else "test/good"
        write_cloud(src / split / f"{i:04d}.ply", 25.0 * d + [100.0, 50.0, 0.0], d if normals else None)
    t = time.perf_counter()
    import_tree(src, folder / "imported.h5", overwrite=True, progress=False)
    return time.perf_counter() - t


def _io(args):
    from benchmarks.table import format_table

    names = args.compression.split(",")
    unknown = [n for n in names if n not in COMPRESSIONS]
    if unknown:
        raise SystemExit(f"--compression: unknown {', '.join(unknown)} (known: {', '.join(COMPRESSIONS)})")
    n_points = args.points or POINTS["io"]
    work = args.out or Path(tempfile.mkdtemp(prefix="collection_io_"))
    work.mkdir(parents=True, exist_ok=True)
    raw_mb = args.scans * n_points * 24 / 2**20  # float64 points and normals
    print(f"work folder {work}; {args.scans} scans x {n_points} points, raw {raw_mb:.0f} MB")
    try:
        writes = []
        for name in names:
            path = work / f"big_{name}.h5"
            seconds, size = _write(path, args.scans, n_points, COMPRESSIONS[name])
            med, p95, cmed, cp95 = _reads(path)
            writes.append({"compression": name, "write_s": seconds, "scans_per_s": args.scans / seconds,
                           "mb_per_s": raw_mb / seconds, "file_mb": size / 2**20, "read_ms": med, "read_p95_ms": p95,
                           "read_cpu_ms": cmed, "read_cpu_p95_ms": cp95})
        print("write, and random single-scan reads over 200 (page cache warm):")
        print(format_table(writes, [("compression", "compression", ""), ("write_s", "write s", ".1f"),
                                    ("scans_per_s", "scans/s", ".0f"), ("mb_per_s", "MB/s", ".0f"),
                                    ("file_mb", "file MB", ".1f"), ("read_ms", "read ms", ".2f"),
                                    ("read_p95_ms", "p95", ".2f"), ("read_cpu_ms", "CPU ms", ".2f"),
                                    ("read_cpu_p95_ms", "CPU p95", ".2f")]))
        main = names[0]
        small = work / f"small_{main}.h5"
        _write(small, args.small_scans, n_points, COMPRESSIONS[main])
        streams = []
        for n, path in ((args.small_scans, small), (args.scans, work / f"big_{main}.h5")):
            base, peak, total = _stream_rss(path)
            streams.append({"scans": n, "points": total, "peak_rss_mb": peak, "open_rss_mb": base,
                            "streaming_mb": peak - base})
            print(f"[{main}] iterate {n} scans ({total} points): peak RSS {peak:.0f} MB (after open {base:.0f} MB, "
                  f"+{peak - base:.0f} MB while streaming)")
        imports = []
        for normals in (True, False):
            seconds = _import(work, args.import_files, args.import_points, normals)
            imports.append({"normals": "given" if normals else "estimated", "seconds": seconds,
                            "files_per_s": args.import_files / seconds})
            print(f"import {args.import_files} PLY files x {args.import_points} points "
                  f"({'with normals' if normals else 'normals estimated'}): {seconds:.1f} s = "
                  f"{args.import_files / seconds:.1f} files/s")
    finally:
        if args.out is None:
            shutil.rmtree(work, ignore_errors=True)
    return {"scans": args.scans, "points": n_points, "raw_mb": raw_mb, "writes": writes, "streaming": streams,
            "imports": imports, "cpus": os.cpu_count()}


# --- gallery ---------------------------------------------------------------------------------------------------

def _project(scan):
    """(n, 2) image-plane coordinates and (n,) shading of a scan's points, seen from its sensor."""
    import numpy as np

    eye = scan.sensor_origin.astype(np.float64)
    forward = np.mean(scan.points, axis=0) - eye
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rays = scan.points - eye
    xy = np.stack([rays @ right, rays @ up], axis=1) / (rays @ forward)[:, None]
    shade = np.abs(np.sum(scan.normals * rays, axis=1)) / np.linalg.norm(rays, axis=1)
    return xy, shade


def _gallery(args):
    import matplotlib
    import numpy as np
    import trimesh

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.cache import COLLECTION_DEFAULTS, MESH_FILES, part_mesh
    from datasets.defects import DEFECT_KINDS
    from datasets.synth import synthesise

    n_points = args.points or POINTS["gallery"]
    parts = [("builtin bracket", part_mesh("builtin"))]
    if MESH_FILES["fandisk"].is_file():
        parts.append(("fandisk", part_mesh("fandisk")))
    else:
        print(f"{MESH_FILES['fandisk']} not found: gallery of the built-in part only")
    fig, axes = plt.subplots(2 * len(parts), 1 + len(DEFECT_KINDS),
                             figsize=(4 * (1 + len(DEFECT_KINDS)), 8 * len(parts)), squeeze=False)
    panels = []
    for row, (title, mesh) in enumerate(parts):
        scans, frame = synthesise(mesh, n_train=0, n_test_good=1, n_test_defective=1, n_points=n_points,
                                  noise=args.noise, seed=args.seed, progress=False)
        diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        for col, scan in enumerate(scans):
            xy, shade = _project(scan)
            labels = np.zeros(len(scan), bool) if scan.point_labels is None else scan.point_labels.astype(bool)
            panels.append({"part": title, "defect": scan.defect or "good", "defect_points": int(labels.sum()),
                           "points": len(scan)})
            ax = axes[2 * row, col]
            ax.scatter(xy[~labels, 0], xy[~labels, 1], s=2, c=shade[~labels], cmap="Greys_r", vmin=-0.3, vmax=1.2)
            ax.scatter(xy[labels, 0], xy[labels, 1], s=3, c="red")
            ax.set_title(f"{title}: {scan.defect or 'good'} ({labels.sum()} / {len(scan)} defect pts)", fontsize=9)
            ax = axes[2 * row + 1, col]
            distance = trimesh.proximity.closest_point(mesh, frame.to_file(scan.points))[1] / diagonal
            image = ax.scatter(xy[:, 0], xy[:, 1], s=2, c=distance, cmap="viridis", vmin=0, vmax=0.02)
            ax.set_title(f"distance to undamaged part / diagonal (noise std {args.noise})", fontsize=9)
            for a in axes[2 * row: 2 * row + 2, col]:
                a.set_aspect("equal")
                a.set_xticks([])
                a.set_yticks([])
        fig.colorbar(image, ax=axes[2 * row + 1, -1], fraction=0.05)
    fig.tight_layout()
    out = Path(args.out or "results/defect_gallery.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")
    figures = {"png": str(out), "panels": panels}
    if not args.no_timing and MESH_FILES["fandisk"].is_file():
        start = time.perf_counter()
        scans, _ = synthesise(part_mesh("fandisk"), **COLLECTION_DEFAULTS, noise=0.002, seed=args.seed,
                              progress=True)
        figures["fandisk_synthesis_seconds"] = time.perf_counter() - start
        print(f"default fandisk collection: {len(scans)} scans x {COLLECTION_DEFAULTS['n_points']} points "
              f"synthesised in {figures['fandisk_synthesis_seconds']:.1f} s")
    return figures


# --- views -----------------------------------------------------------------------------------------------------

def _views(args):
    """Precision and recall of rendered template views against ray casting the true mesh (module docstring)."""
    import numpy as np
    import open3d as o3d
    import trimesh

    from benchmarks import cache
    from benchmarks.table import format_table
    from datasets.normals import estimate_normals
    from datasets.templates import TemplateSurface, sensor_positions, visible_points

    rows = []
    for part in args.parts.split(","):
        mesh = cache.part_mesh(part)
        diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        truth = o3d.t.geometry.RaycastingScene()
        truth.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
        for seed in (int(x) for x in args.seeds.split(",")):
            rng = np.random.default_rng([seed, 1000])
            pts, faces = trimesh.sample.sample_surface(mesh, args.template_points, seed=int(rng.integers(2**31)))
            pts = pts + mesh.face_normals[faces] * rng.normal(0, args.noise * diag, (len(pts), 1))
            normals = estimate_normals(pts)
            t0 = time.perf_counter()
            surface = TemplateSurface(pts, normals)
            build = time.perf_counter() - t0
            lo, hi = pts.min(0), pts.max(0)
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            flip_radius = 1000 * float(np.linalg.norm(hi - lo))
            found = {"ray-cast": [], "hidden-point removal": []}
            for origin in sensor_positions((lo + hi) / 2, float(np.linalg.norm(hi - lo)), 8, seed):
                d = pts - origin
                dist = np.linalg.norm(d, axis=1)
                rays = np.hstack([np.broadcast_to(origin, d.shape), d / dist[:, None]]).astype(np.float32)
                t_hit = truth.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
                seen = (np.einsum("ij,ij->i", mesh.face_normals[faces], origin - pts) > 0) & \
                    (np.abs(t_hit - dist) < 0.03 * diag)
                _, hpr = cloud.hidden_point_removal(origin, flip_radius)
                hpr = np.unique(np.asarray(hpr))
                hpr = hpr[np.einsum("ij,ij->i", normals[hpr], origin - pts[hpr]) > 0]
                for rule, idx in (("ray-cast", visible_points(pts, normals, origin, surface)),
                                  ("hidden-point removal", hpr)):
                    kept = np.zeros(len(pts), dtype=bool)
                    kept[idx] = True
                    hit = np.count_nonzero(kept & seen)
                    found[rule].append((hit / max(kept.sum(), 1), hit / max(seen.sum(), 1), kept.sum(), seen.sum()))
            for rule, values in found.items():
                v = np.array(values)
                rows.append({"part": part, "seed": seed, "rule": rule, "precision": v[:, 0].mean(),
                             "precision_min": v[:, 0].min(), "recall": v[:, 1].mean(), "recall_min": v[:, 1].min(),
                             "kept": v[:, 2].mean(), "visible": v[:, 3].mean(),
                             "sigma": surface.sigma / diag if rule == "ray-cast" else float("nan"),
                             "seconds": build if rule == "ray-cast" else float("nan")})
    print(format_table(rows, [("part", "part", ""), ("seed", "seed", "d"), ("rule", "rule", ""),
                              ("precision", "precision", ".3f"), ("precision_min", "min", ".3f"),
                              ("recall", "recall", ".3f"), ("recall_min", "min", ".3f"), ("kept", "points kept", ".0f"),
                              ("visible", "visible", ".0f"), ("sigma", "noise / diag", ".4f"),
                              ("seconds", "surface s", ".2f")]))
    return {"views": rows}
