"""The score study behind the default scan score: several point scores x aggregates on one part, each thresholded
at the default alpha on the held-back scans. Used by ``verdicts.py --variants``; also runnable alone:

    .venv/bin/python benchmarks/variants.py --data results/verdicts/<part>_<key>/tree.h5 --model .../model.pt

Every scan is projected once (the inspection's projection options); the per-point ingredients (E f, Var f,
|grad E f|, the per-location reference of good training scans) are cached beside the model as ``ingredients.npz``.
"""
import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

AGGREGATES = ("top1", "top2", "top5", "mean", "q99")


def ingredients(data, model):
    """Per scan: points, labels, E f, Var f, |grad E f| under its projected field; cached. Returns dict of lists."""
    cache = Path(model).with_suffix(".ingredients.npz")
    if cache.is_file():
        z = np.load(cache, allow_pickle=True)
        return {k: list(z[k]) if z[k].dtype == object else z[k] for k in z.files}
    from datasets import ScanCollection

    from inspection.estimator import DEFAULT_PROJECTION, field_for
    from inspection.model_io import load_model
    from inspection.run import reference_scans

    handle = load_model(model)
    held = set(handle.heldback_names)
    with ScanCollection(data) as c:
        names = c.names
        cal = c.read_many([i for i, n in enumerate(names) if n in held])
        test = c.read_many(c.select(split="test"))
    ref = reference_scans(handle, data, {"same_as_training": True})
    out = {k: [] for k in ("role", "name", "label", "defect", "points", "normals", "origin", "point_labels", "mean",
                           "var", "grad")}
    seconds = []
    for role, scans in (("reference", ref), ("calibration", cal), ("test", test)):
        for s in scans:
            t0 = time.perf_counter()
            field = field_for(handle.model, s.points, s.normals, DEFAULT_PROJECTION)
            out["mean"].append(np.asarray(field.mean(s.points), np.float64))
            out["var"].append(np.asarray(field.variance(s.points), np.float64))
            out["grad"].append(np.linalg.norm(np.asarray(field.mean_gradient(s.points), np.float64), axis=1))
            seconds.append(time.perf_counter() - t0)
            out["role"].append(role)
            out["name"].append(s.name)
            out["label"].append(s.label)
            out["defect"].append(s.defect)
            out["points"].append(np.asarray(s.points, np.float64))
            out["normals"].append(np.asarray(s.normals, np.float64))
            out["origin"].append(None if s.sensor_origin is None else np.asarray(s.sensor_origin, np.float64))
            out["point_labels"].append(s.point_labels)
    out["noise"] = np.array(handle.model.noise)
    out["lengthscale"] = np.array(handle.model.lengthscale)
    out["seconds"] = np.array(np.mean(seconds))
    arrays = {k: (np.array(v + [None], dtype=object)[:-1] if isinstance(v, list) else v) for k, v in out.items()}
    np.savez(cache, **arrays)
    return {k: list(v) if isinstance(v, np.ndarray) and v.dtype == object else v for k, v in arrays.items()}


class Reference:
    """Per-location statistics of a quantity over good training scans (k nearest points), as LocalReference, plus
    the distance to the nearest reference point."""

    def __init__(self, points, values, k=16, max_points=60000, seed=0):
        from scipy.spatial import cKDTree

        if len(points) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
            points, values = points[keep], values[keep]
        self.points, self.values, self.k = points, values, k
        self.tree = cKDTree(points)

    def stats(self, x):
        dist, idx = self.tree.query(x, self.k)
        v = self.values[idx]
        return v.mean(1), v.std(1), dist[:, 0], dist[:, -1]


def study(data, model, alpha, floor=0.2):
    """Rows (name, rates, Threshold, seconds per scan) of the score variants."""
    from inspection.scores import aggregate
    from inspection.threshold import fit_threshold
    from verdicts import rates

    z = ingredients(data, model)
    role = np.array(z["role"])
    noise = float(z["noise"])
    dist = [m / np.maximum(g, floor) for m, g in zip(z["mean"], z["grad"])]
    var_d = [v / np.maximum(g, floor) ** 2 for v, g in zip(z["var"], z["grad"])]
    ref_idx = np.flatnonzero(role == "reference")
    ref = Reference(np.concatenate([z["points"][i] for i in ref_idx]), np.concatenate([dist[i] for i in ref_idx]))

    def per_point(i, kind):
        p = z["points"][i]
        if kind in ("residual", "nll"):
            total = np.maximum(z["var"][i], 0) + noise**2
            r2 = z["mean"][i] ** 2 / total
            return np.sqrt(r2) if kind == "residual" else 0.5 * (r2 + np.log(2 * np.pi * total))
        d_ref, s_ref, _, _ = ref.stats(p)
        r = dist[i] - d_ref
        if kind == "distance":
            return np.abs(r) / np.sqrt(s_ref**2 + noise**2)
        total = s_ref**2 + np.maximum(var_d[i], 0) + noise**2  # + the field's own variance, in distance units
        if kind == "distance+var":
            return np.abs(r) / np.sqrt(total)
        if kind == "nll-cal":
            return 0.5 * (r**2 / total + np.log(2 * np.pi * total))
        raise ValueError(kind)

    cal_idx, test_idx = np.flatnonzero(role == "calibration"), np.flatnonzero(role == "test")
    labels = np.array([z["label"][i] for i in test_idx])
    defects = np.array([z["defect"][i] for i in test_idx])
    rows = []
    for kind in ("distance", "distance+var", "nll-cal", "residual", "nll"):
        cal_maps = [per_point(i, kind) for i in cal_idx]
        test_maps = [per_point(i, kind) for i in test_idx]
        for agg in AGGREGATES:
            cs = np.array([aggregate(v, agg) for v in cal_maps])
            ts = np.array([aggregate(v, agg) for v in test_maps])
            shift = 0.0
            if cs.min() <= 0:  # NLLs can be negative: the log-normal tail needs positive scores
                shift = 1.0 - min(cs.min(), ts.min())
            decision = fit_threshold(cs + shift, alpha)
            rows.append((f"{kind}/{agg}", rates(ts + shift, labels, defects, decision.value), decision,
                         float(z["seconds"])))
    return rows


def diagnose(data, model, floor=0.2, show=6):
    """Where the worst points of the highest-scoring good test scans and of the lowest-scoring defective ones lie:
    the share of each scan's top-1 % points (old ``distance`` score, no variance, no grazing term) at the scan's
    border (fewer than 0.6 x the median number of neighbours within 4 point spacings), at grazing incidence
    (|cos| of the sensor ray and the scan's normal < 0.3), and on the defect. Printed, one row per scan."""
    from scipy.spatial import cKDTree

    from inspection.scores import aggregate

    z = ingredients(data, model)
    role = np.array(z["role"])
    noise = float(z["noise"])
    dist = [m / np.maximum(g, floor) for m, g in zip(z["mean"], z["grad"])]
    ref_idx = np.flatnonzero(role == "reference")
    ref = Reference(np.concatenate([z["points"][i] for i in ref_idx]), np.concatenate([dist[i] for i in ref_idx]))
    rows = []
    for i in np.flatnonzero(role == "test"):
        p = z["points"][i]
        d_ref, s_ref, _, _ = ref.stats(p)
        v = np.abs(dist[i] - d_ref) / np.sqrt(s_ref**2 + noise**2)
        top = np.argsort(v)[-max(1, int(np.ceil(0.01 * len(v)))):]
        tree = cKDTree(p)
        spacing = np.median(tree.query(p, 2)[0][:, 1])
        count = np.array([len(x) for x in tree.query_ball_point(p, 4 * spacing)])
        border = count < 0.6 * np.median(count)
        rays = p - z["origin"][i]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        grazing = np.abs(np.sum(rays * z["normals"][i], axis=1)) < 0.3
        on_defect = z["point_labels"][i] is not None and np.any(z["point_labels"][i])
        rows.append((aggregate(v, "top1"), z["name"][i], border[top].mean(), grazing[top].mean(),
                     (z["point_labels"][i][top] > 0).mean() if on_defect else 0.0, border.mean(), grazing.mean()))
    good = sorted((r for r in rows if r[1].startswith("test/good")), key=lambda r: -r[0])[:show]
    bad = sorted((r for r in rows if not r[1].startswith("test/good")), key=lambda r: r[0])[:show]
    print(f"{'scan':<18} {'score':>6}  top-1 % points: {'border':>6} {'grazing':>7} {'defect':>6}  all points: "
          f"{'border':>6} {'grazing':>7}")
    for r in good + bad:
        print(f"{r[1]:<18} {r[0]:6.2f}  {'':16}{r[2]:6.2f} {r[3]:7.2f} {r[4]:6.2f}  {'':12}{r[5]:6.2f} {r[6]:7.2f}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--model", required=True)
    p.add_argument("--alpha", type=float, default=0.01)
    p.add_argument("--diagnose", action="store_true", help="where the worst points of good and defective scans lie")
    args = p.parse_args(argv)
    from verdicts import _print_rows

    if args.diagnose:
        diagnose(args.data, args.model)
        return

    rows = study(args.data, args.model, args.alpha)
    kinds = sorted(k for k in rows[0][1] if k not in ("auroc", "flag_def", "flag_good", "n_good"))
    _print_rows([("", *r) for r in rows], kinds)


if __name__ == "__main__":
    main()
