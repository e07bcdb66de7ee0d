"""Training from 4 complete templates (the Real3D-AD / Anomaly-ShapeNet regime) on parts of ours, next to a
nearest-neighbour baseline computed in the same run.

Run by hand from the repository root (not a test):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/four_templates.py [--parts builtin,fandisk] [--epochs N]

For each part, in one run:
1. 4 complete clouds sampled from the part's mesh surface (``--template-points`` each, seeded, depth noise 0.002 x the
   diagonal along the normal) and partial test scans from the virtual scanner (``datasets.synth``: ``--test-good``
   good, ``--per-defect`` of each defect type), written as a Real3D-AD class folder in WORK/<part>/tree
   (``train/<k>_template.pcd``, ``test/<i>_good.pcd``, ``test/<i>_<defect>.pcd`` and ``gt/<stem>.txt`` = x y z label);
2. imported with ``python -m datasets import`` (layout detected: the templates become ``--views`` partial training
   views and ``--validation-views`` held-back views each);
3. trained with ``train_latent.py``, calibrated with ``python -m inspection calibrate`` (on the validation views) and
   scored with ``python -m inspection score``; the per-point scores for the per-defect point AUROC come from the
   public ``inspection.Inspector`` with the model's stored calibration (checked against the CLI's scan scores);
4. the nearest-neighbour baseline of ``benchmarks/inspect_fandisk.py``: distance from each test point to the nearest
   point of all training views, scan score = mean of the top 5 % distances.
Prints object AUROC and point AUROC per defect type for both. Everything is cached in WORK by its parameters.
"""
import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np

from baselines import nn_baseline

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"
PARTS = {"builtin": "builtin", "fandisk": str(SHARED / "fandisk.obj")}


def _write_pcd(path, points):
    import open3d as o3d

    path.parent.mkdir(parents=True, exist_ok=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if not o3d.io.write_point_cloud(str(path), pcd):
        raise RuntimeError(f"{path}: open3d could not write it")


def make_tree(mesh, tree, args):
    """Write the Real3D-AD-like class folder (file units = the mesh's)."""
    import trimesh

    from datasets.synth import synthesise

    diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    for k in range(4):
        rng = np.random.default_rng([args.seed, 1000 + k])
        pts, faces = trimesh.sample.sample_surface(mesh, args.template_points, seed=int(rng.integers(2**31)))
        pts = pts + mesh.face_normals[faces] * rng.normal(0, 0.002 * diag, (len(pts), 1))
        _write_pcd(tree / "train" / f"{k + 1}_template.pcd", pts)
    scans, frame = synthesise(mesh, n_train=0, n_test_good=args.test_good, n_test_defective=args.per_defect,
                              n_points=args.points, seed=args.seed, progress=False)
    for i, s in enumerate(scans):
        pts = frame.to_file(s.points)
        stem = f"{i + 1}_{'good' if s.label == 'good' else s.defect}"
        _write_pcd(tree / "test" / f"{stem}.pcd", pts)
        if s.label == "defective":
            (tree / "gt").mkdir(exist_ok=True)
            np.savetxt(tree / "gt" / f"{stem}.txt", np.column_stack([pts, s.point_labels]),
                       fmt=["%.6f"] * 3 + ["%d"])


def run(cmd, log):
    t0 = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"$ {' '.join(map(str, cmd))}\n")
        f.flush()
        subprocess.run([str(c) for c in cmd], check=True, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)
    return time.perf_counter() - t0


def per_defect(scans, scan_scores, point_scores):
    """Object and point AUROC per defect type (good test scans against that type's scans), and overall."""
    from sklearn.metrics import roc_auc_score

    labels = np.array([s.label for s in scans])
    defects = np.array([s.defect for s in scans])
    y = (labels == "defective").astype(int)
    res = {}
    for d in sorted(set(defects[y == 1])) + ["all"]:
        sel = (y == 0) | (defects == d) if d != "all" else np.ones(len(y), bool)
        idx = np.flatnonzero(sel)
        pl = np.concatenate([scans[i].point_labels for i in idx])
        ps = np.concatenate([point_scores[i] for i in idx])
        res[d] = (roc_auc_score(y[sel], np.asarray(scan_scores)[sel]), roc_auc_score(pl, ps))
    return res


def bench_part(part, args, work):
    from datasets import ScanCollection
    from datasets.parts import load_part
    from inspection import Inspector, load_model

    params = dict(part=part, template_points=args.template_points, test_good=args.test_good,
                  per_defect=args.per_defect, points=args.points, seed=args.seed, views=args.views,
                  validation_views=args.validation_views)
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]
    pdir = work / f"{part}_{key}"
    pdir.mkdir(parents=True, exist_ok=True)
    log = pdir / "log.txt"
    py = sys.executable
    tree, data = pdir / "tree", pdir / "data.h5"
    model = pdir / f"model_e{args.epochs or 'default'}.pt"
    timings = {}
    if not (tree / "gt").is_dir():
        t0 = time.perf_counter()
        make_tree(load_part(PARTS[part]), tree, args)
        timings["tree"] = time.perf_counter() - t0
    if not data.is_file():
        timings["import"] = run([py, "-m", "datasets", "import", tree, "--out", data, "--views", args.views,
                                 "--validation-views", args.validation_views, "--seed", args.seed], log)
    if not model.is_file():
        cmd = [py, "train_latent.py", "--data", data, "--out", model, "--seed", args.seed, "--quiet"]
        timings["train"] = run(cmd + (["--epochs", args.epochs] if args.epochs else []), log)
        timings["calibrate"] = run([py, "-m", "inspection", "calibrate", "--model", model, "--data", data], log)
    out = pdir / f"scores_e{args.epochs or 'default'}"
    timings["score"] = run([py, "-m", "inspection", "score", "--model", model, "--data", data, "--out", out,
                            "--maps", "none", "--overwrite"], log)
    summary = json.loads((out / "summary.json").read_text())

    with ScanCollection(data) as c:
        names = c.names
        test = c.read_many(c.select(split="test"))
        train = c.read_many(c.select(split="train"))
        n_val = len(c.select(split="validation"))
        imported = c.provenance
    handle = load_model(model)
    insp = Inspector(handle.model, alpha=handle.calibration.alpha).set_calibration(handle.calibration)
    t0 = time.perf_counter()
    results = [insp.inspect(s) for s in test]
    timings["api_rescore"] = time.perf_counter() - t0
    cli_scores = {r["name"]: r["score"] for r in _read_csv(out / "scores.csv")}
    api_scores = np.array([r.score for r in results])
    drift = max(abs(cli_scores[s.name] - a) for s, a in zip(test, api_scores))
    model_res = per_defect(test, api_scores, [r.point_scores for r in results])
    t0 = time.perf_counter()
    nn = nn_baseline(np.concatenate([s.points for s in train]), test)
    timings["nn"] = time.perf_counter() - t0
    nn_res = per_defect(test, [a for a, _ in nn], [d for _, d in nn])

    print(f"\n== {part}: {len(train)} training views, {n_val} validation views (calibration) from 4 templates of "
          f"{args.template_points} points; {len(test)} test scans of {args.points} points; voxel "
          f"{imported.get('voxel')}; epochs {args.epochs or 'train_latent default'}")
    print(f"   CLI summary: AUROC {summary['metrics'].get('auroc', float('nan')):.3f}, point AUROC "
          f"{summary['metrics'].get('point_auroc', float('nan')):.3f}, point score {summary['point_score']}/"
          f"{summary['aggregate']}, false-alarm rate {summary['metrics'].get('false_alarm_rate', float('nan')):.3f} "
          f"at alpha {summary['alpha']}; API re-score max |difference| from scores.csv {drift:.2g}")
    print(f"   {'defect':<10} {'model obj':>9} {'NN obj':>7} {'model pt':>9} {'NN pt':>7}")
    for d in model_res:
        (mo, mp), (no, npt) = model_res[d], nn_res[d]
        print(f"   {d:<10} {mo:9.3f} {no:7.3f} {mp:9.3f} {npt:7.3f}")
    print("   seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items()) + f"; load {os.getloadavg()}")
    return {"part": part, "model": model_res, "nn": nn_res, "summary_metrics": summary["metrics"],
            "timings": timings, "names": len(names)}


def view_check(part, args, work, per_template=2):
    """How well the rendered views match what a ray caster sees of the part: for the first ``per_template`` training
    views of each template, the share of the view's points that the mesh leaves visible from the view's sensor
    (precision) and the share of the template's visible points that the view kept (recall). A template point counts
    as visible when the first hit along the ray from the sensor lies within 1 % of the diagonal of it and the
    surface faces the sensor there."""
    import open3d as o3d
    import trimesh
    from scipy.spatial import cKDTree

    from datasets import ScanCollection, read_cloud
    from datasets.parts import load_part

    pdir = next(work.glob(f"{part}_*"), None)
    if pdir is None or not (pdir / "data.h5").is_file():
        raise SystemExit(f"{part}: no imported collection in {work}; run the benchmark first")
    mesh = load_part(PARTS[part])
    diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    scene = o3d.t.geometry.RaycastingScene()  # (trimesh's pure-numpy caster needs tens of GB on fandisk)
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    rows = []
    with ScanCollection(pdir / "data.h5") as c:
        frame = c.frame
        for k in range(1, 5):
            template = read_cloud(pdir / "tree" / "train" / f"{k}_template.pcd")[0]
            face = trimesh.proximity.closest_point(mesh, template)[2]
            normals = mesh.face_normals[face]
            for i in range(per_template):
                view = c[c.names.index(f"train/{k}_template/view_{i:03d}")]
                origin = frame.to_file(view.sensor_origin)
                d_view, kept = cKDTree(template).query(frame.to_file(view.points))
                assert d_view.max() < 1e-3 * diag, "a view point is not a template point"
                dirs = template - origin
                dist = np.linalg.norm(dirs, axis=1)
                rays = np.hstack([np.repeat(origin[None], len(template), 0), dirs / dist[:, None]])
                first = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
                visible = (first >= dist - 0.01 * diag) & (np.einsum("ij,ij->i", normals, origin - template) > 0)
                rows.append((visible[kept].mean(), np.isin(np.flatnonzero(visible), kept).mean(), len(kept),
                             int(visible.sum())))
    r = np.array(rows)
    print(f"{part}: {len(rows)} views: precision {r[:, 0].mean():.3f} (min {r[:, 0].min():.3f}), recall "
          f"{r[:, 1].mean():.3f} (min {r[:, 1].min():.3f}), points a view {r[:, 2].mean():.0f} of "
          f"{r[:, 3].mean():.0f} visible")


def _read_csv(path):
    import csv

    with open(path) as f:
        return [dict(r, score=float(r["score"])) for r in csv.DictReader(f)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="builtin,fandisk", help="comma-separated: builtin, fandisk")
    parser.add_argument("--template-points", type=int, default=10000)
    parser.add_argument("--test-good", type=int, default=16)
    parser.add_argument("--per-defect", type=int, default=8)
    parser.add_argument("--points", type=int, default=4000, help="points per test scan")
    parser.add_argument("--views", type=int, default=16, help="training views per template")
    parser.add_argument("--validation-views", type=int, default=4, help="calibration views per template")
    parser.add_argument("--epochs", type=int, default=None, help="train_latent epochs (default: its own)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", default="results/four_templates")
    parser.add_argument("--view-check", action="store_true",
                        help="only compare the imported views with ray-cast visibility (after a run)")
    args = parser.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {os.getloadavg()}")
    for part in args.parts.split(","):
        if part not in PARTS:
            parser.error(f"unknown part {part!r}; known: {', '.join(PARTS)}")
        if args.view_check:
            view_check(part, args, work)
        else:
            bench_part(part, args, work)


if __name__ == "__main__":
    main()
