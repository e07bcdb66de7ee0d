"""Inspection on fandisk: object- and point-level AUROC of the NLL scores next to a nearest-neighbour baseline.

Run by hand from the repository root (not a test):

    .venv/bin/python benchmarks/inspect_fandisk.py [--work results/inspect_fandisk] [--jitter 5 --align]

One run: synthesises a fandisk collection (32 train, 16 good test, 16 per defect type, 4,000 points, seed 0; cached
in WORK by its parameters), trains the latent model with train_latent.py (cached likewise; ``--model`` to score an
existing one), calibrates on the model's held-back good training scans, projects and scores every test scan once,
and prints for several per-point scores x aggregates: object-level AUROC overall and per defect type, the point-level
AUROC, and the false-alarm rate of the good test scans at ``--alpha``; beside them a nearest-neighbour baseline
computed in the same run (distance from each test point to the nearest point of all training scans, scan score =
mean of the top 5 % distances) and the inspection seconds per scan. ``--jitter 5 --align``: every scan (training
ones too) gets up to 5 degrees of random pose and is registered (point-to-plane ICP) onto the CAD surface first.
Writes WORK/<run>/pointscores_<scan>.png pictures of the per-point scores of the weakest defect type.
"""
import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from baselines import nn_baseline

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"
AGGREGATES = ("mean", "top1", "top2", "top5", "top10", "q99", "max")
POINT_KINDS = ("distance", "local", "residual", "nll", "absmean")


def _synth(args, work):
    from datasets import ScanCollection
    from datasets.parts import load_part
    from datasets.synth import synthesise

    params = dict(mesh=str(args.mesh), n_train=args.train, n_test_good=args.test_good,
                  n_test_defective=args.per_defect, n_points=args.points, seed=args.seed, jitter_deg=args.jitter)
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]
    path = work / f"tree_{key}.h5"
    if not path.is_file():
        t0 = time.perf_counter()
        mesh = load_part(args.mesh)
        scans, frame = synthesise(mesh, n_train=args.train, n_test_good=args.test_good,
                                  n_test_defective=args.per_defect, n_points=args.points, seed=args.seed,
                                  jitter_deg=args.jitter, progress=True)
        ScanCollection.create(path, scans, frame=frame, provenance={"benchmark": "inspect_fandisk", **params})
        print(f"synthesised {len(scans)} scans in {time.perf_counter() - t0:.0f} s -> {path}")
    return path, key


def _aligned_copy(path, args):
    """The collection with every scan registered onto the CAD surface (ICP), cached beside it."""
    from datasets import ScanCollection
    from datasets.parts import load_part
    import trimesh

    from inspection.align import Aligner

    out = path.with_name(path.stem + "_aligned.h5")
    if out.is_file():
        return out, None
    t0 = time.perf_counter()
    with ScanCollection(path) as c:
        frame = c.frame
        scans = c.read_many(range(len(c)))
    mesh = load_part(args.mesh)
    pts, faces = trimesh.sample.sample_surface(mesh, 40000, seed=args.seed)
    aligner = Aligner(frame.to_collection(pts), mesh.face_normals[faces], seed=args.seed)
    aligned = [aligner.align_scan(s) for s in scans]
    for s in aligned:
        s.extra = {}
    ScanCollection.create(out, aligned, frame=frame, provenance={"benchmark": "inspect_fandisk", "aligned": True})
    per = (time.perf_counter() - t0) / len(scans)
    print(f"aligned {len(scans)} scans onto the CAD surface: {per:.3f} s per scan -> {out}")
    return out, per


def _train(data, args, work, key):
    tag = f"_e{args.epochs}" if args.epochs else ""
    model = Path(args.model) if args.model else work / f"model_{key}{'_al' if args.align else ''}{tag}.pt"
    if model.is_file():
        return model
    from inspection.training import train_model

    t0 = time.perf_counter()
    train_model(data, model, calibration_fraction=args.calibration_fraction, seed=args.seed, epochs=args.epochs,
                quiet=False)
    print(f"trained {model} in {time.perf_counter() - t0:.0f} s")
    return model


def _metrics(scores, labels, defects, cal_scores, alpha, good_test):
    from sklearn.metrics import roc_auc_score

    from inspection.threshold import conformal_threshold

    y = (labels == "defective").astype(int)
    res = {"auroc": roc_auc_score(y, scores)}
    for d in sorted(set(defects[y == 1])):
        sel = (y == 0) | (defects == d)
        res[d] = roc_auc_score(y[sel], scores[sel])
    t = conformal_threshold(cal_scores, alpha)
    res["far"] = float(np.mean(scores[good_test] > t))
    res["det"] = float(np.mean(scores[y == 1] > t))
    # at the smallest alpha the calibration set supports, 1/(n+1) (threshold = the largest calibration score)
    t_min = conformal_threshold(cal_scores, max(alpha, 1.0 / (len(cal_scores) + 1)))
    res["far_min"] = float(np.mean(scores[good_test] > t_min))
    res["det_min"] = float(np.mean(scores[y == 1] > t_min))
    return res


def _picture(path, scan, values, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = scan.points
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    labels = scan.point_labels if scan.point_labels is not None else np.zeros(len(p))
    for ax, (i, j) in zip(axes[:2], ((0, 1), (0, 2))):
        sc = ax.scatter(p[:, i], p[:, j], c=values, s=3, cmap="turbo", vmin=0, vmax=np.quantile(values, 0.995))
        ax.scatter(p[labels == 1, i], p[labels == 1, j], s=12, facecolors="none", edgecolors="k", lw=0.3)
        ax.set_aspect("equal")
        fig.colorbar(sc, ax=ax, fraction=0.04)
    axes[2].hist([values[labels == 0], values[labels == 1]], bins=50, label=["good points", "defect points"],
                 density=True, alpha=0.7)
    axes[2].legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(SHARED / "fandisk.obj"))
    parser.add_argument("--train", type=int, default=32)
    parser.add_argument("--test-good", type=int, default=16)
    parser.add_argument("--per-defect", type=int, default=16)
    parser.add_argument("--points", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jitter", type=float, default=0.0, help="pose jitter in degrees on every scan")
    parser.add_argument("--align", action="store_true", help="register every scan onto the CAD surface first")
    parser.add_argument("--alpha", type=float, default=0.01)
    parser.add_argument("--calibration-fraction", type=float, default=0.2)
    parser.add_argument("--epochs", type=int, default=600, help="train_latent epochs (default %(default)s)")
    parser.add_argument("--projection", default="default", help="'default' (inspection's), 'model' (the "
                                                                 "projector's defaults) or a JSON dict")
    parser.add_argument("--model", default=None, help="score this model instead of training one")
    parser.add_argument("--work", default="results/inspect_fandisk")
    args = parser.parse_args(argv)

    from datasets import ScanCollection

    from inspection.estimator import DEFAULT_PROJECTION, field_for
    from inspection.model_io import load_model
    from inspection.scores import GRADIENT_FLOOR, aggregate, point_scores

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    print(f"load average at start: {os.getloadavg()}")
    data, key = _synth(args, work)
    align_seconds = None
    if args.align:
        data, align_seconds = _aligned_copy(data, args)
    model_path = _train(data, args, work, key)
    handle = load_model(model_path)

    with ScanCollection(data) as c:
        held = set(handle.heldback_names)
        names = c.names
        cal_idx = [i for i, n in enumerate(names) if n in held]
        test_idx = c.select(split="test")
        train_idx = [i for i in c.select(split="train") if names[i] not in held]
        cal_scans, test_scans = c.read_many(cal_idx), c.read_many(test_idx)
        train_scans = c.read_many(train_idx)
        train_points = np.concatenate([s.points for s in train_scans])
    print(f"{len(train_idx)} training scans, {len(cal_scans)} held-back calibration scans, {len(test_scans)} test "
          f"scans; model {model_path} ({handle.kind})")

    def project_all(scans, what):
        out, seconds = [], []
        for s in scans:
            t0 = time.perf_counter()
            field = field_for(handle.model, s.points, s.normals, projection)
            mean, var = field.mean(s.points), field.variance(s.points)
            grad = np.linalg.norm(field.mean_gradient(s.points), axis=1)
            seconds.append(time.perf_counter() - t0)
            out.append((mean, var, mean / np.maximum(grad, GRADIENT_FLOOR)))
        print(f"projected {len(scans)} {what} scans: {np.mean(seconds):.3f} s per scan")
        return out, float(np.mean(seconds))

    projection = None if args.projection == "model" else \
        (DEFAULT_PROJECTION if args.projection == "default" else json.loads(args.projection))
    print(f"projection options: {projection or 'the model defaults'}")
    t_ref = time.perf_counter()
    train_fields, _ = project_all(train_scans, "training (per-location reference)")
    from inspection.scores import LocalReference

    rp = np.concatenate([s.points for s in train_scans])
    keep = np.sort(np.random.default_rng(0).choice(len(rp), min(60000, len(rp)), replace=False))
    reference = LocalReference(rp[keep], np.concatenate([m for m, _, _ in train_fields])[keep])
    reference_d = LocalReference(rp[keep], np.concatenate([d for _, _, d in train_fields])[keep], quantity="distance")
    t_ref = time.perf_counter() - t_ref
    cal_fields, _ = project_all(cal_scans, "calibration")
    test_fields, sec = project_all(test_scans, "test")
    noise = handle.model.noise

    def per_point(kind, scan, mean, var, dist, noise_floor):
        if kind == "distance":
            d_ref, s_ref = reference_d.stats(scan.points)
            return np.abs(dist - d_ref) / np.sqrt(s_ref**2 + noise_floor**2)
        if kind == "local":
            m_ref, s_ref = reference.stats(scan.points)
            return np.abs(mean - m_ref) / np.sqrt(s_ref**2 + noise_floor**2)
        total = var + noise_floor**2
        if kind == "residual":
            return np.abs(mean) / np.sqrt(total)
        if kind == "nll":
            return 0.5 * (mean**2 / total + np.log(2 * np.pi * total))
        return np.abs(mean) / noise_floor  # absmean: distance to the expected surface in noise units (no variance)

    labels = np.array([s.label for s in test_scans])
    defects = np.array([s.defect for s in test_scans])
    good_test = labels == "good"
    pl = np.concatenate([s.point_labels for s in test_scans])
    rows = []
    kept = {}
    for kind in POINT_KINDS:
        test_pts = [per_point(kind, s, m, v, d, noise) for s, (m, v, d) in zip(test_scans, test_fields)]
        cal_pts = [per_point(kind, s, m, v, d, noise) for s, (m, v, d) in zip(cal_scans, cal_fields)]
        from sklearn.metrics import roc_auc_score

        point_auc = roc_auc_score(pl, np.concatenate(test_pts))
        kept[kind] = test_pts
        for agg in AGGREGATES:
            s = np.array([aggregate(v, agg) for v in test_pts])
            cs = np.array([aggregate(v, agg) for v in cal_pts])
            rows.append((f"{kind}/{agg}", _metrics(s, labels, defects, cs, args.alpha, good_test), point_auc))
    t0 = time.perf_counter()
    nn_test = nn_baseline(train_points, test_scans)
    nn_sec = (time.perf_counter() - t0) / len(test_scans)
    nn_cal = nn_baseline(train_points, cal_scans)
    nn_point_auc = roc_auc_score(pl, np.concatenate([d for _, d in nn_test]))
    nn = _metrics(np.array([s for s, _ in nn_test]), labels, defects, np.array([s for s, _ in nn_cal]), args.alpha,
                  good_test)
    rows.append(("NN baseline top5%", nn, nn_point_auc))

    kinds = sorted(set(defects[labels == "defective"]))
    head = f"{'score':<22} {'AUROC':>6} " + " ".join(f"{k:>8}" for k in kinds) + \
        f" {'pointAUC':>8} {'FAR@a':>6} {'det@a':>6} {'FAR@a*':>6} {'det@a*':>6}"
    print(f"\nfandisk: jitter {args.jitter} deg, align {args.align}, alpha {args.alpha}, "
          f"{len(cal_scans)} calibration scans (min p-value {1 / (len(cal_scans) + 1):.3f}; a* = "
          f"max(alpha, 1/(n+1)) = {max(args.alpha, 1 / (len(cal_scans) + 1)):.3f})")
    print(head)
    for name, m, pa in rows:
        print(f"{name:<22} {m['auroc']:6.3f} " + " ".join(f"{m[k]:8.3f}" for k in kinds) +
              f" {pa:8.3f} {m['far']:6.3f} {m['det']:6.3f} {m['far_min']:6.3f} {m['det_min']:6.3f}")
    print(f"per-location reference built once at calibration: {t_ref:.0f} s ({len(train_scans)} training scans "
          f"projected)")
    print(f"inspection seconds per scan: projection + scoring {sec:.3f}"
          + (f" + alignment {align_seconds:.3f}" if align_seconds else "") + f"; NN baseline {nn_sec:.3f}")
    print(f"load average at end: {os.getloadavg()}")

    # pictures: per-point standardized residual of the two lowest-scoring scans of the weakest defect type
    from inspection.estimator import DEFAULT_AGGREGATE

    DEFAULT_POINT_SCORE = "distance"  # what `python -m inspection calibrate` picks on the training collection

    default = next(m for n, m, _ in rows if n == f"{DEFAULT_POINT_SCORE}/{DEFAULT_AGGREGATE}")
    weakest = min(kinds, key=lambda k: default[k])
    idx = [i for i, s in enumerate(test_scans) if s.defect == weakest]
    s_def = np.array([aggregate(kept[DEFAULT_POINT_SCORE][i], DEFAULT_AGGREGATE) for i in idx])
    pics = work / f"pictures_{key}{'_al' if args.align else ''}"
    pics.mkdir(exist_ok=True)
    for j in np.argsort(s_def)[:2]:
        i = idx[j]
        _picture(pics / f"{test_scans[i].name.replace('/', '_')}.png", test_scans[i], kept[DEFAULT_POINT_SCORE][i],
                 f"{test_scans[i].name}: {DEFAULT_POINT_SCORE} per point (circles: defect points)")
    gi = int(np.argmax([aggregate(kept[DEFAULT_POINT_SCORE][i], DEFAULT_AGGREGATE) if good_test[i] else -1
                        for i in range(len(test_scans))]))
    _picture(pics / f"{test_scans[gi].name.replace('/', '_')}.png", test_scans[gi], kept[DEFAULT_POINT_SCORE][gi],
             f"{test_scans[gi].name} (worst good scan): {DEFAULT_POINT_SCORE} per point")
    print(f"pictures of the weakest defect type ({weakest}) and the worst good scan in {pics}")


if __name__ == "__main__":
    main()
