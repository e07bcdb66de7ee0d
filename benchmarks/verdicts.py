"""Verdicts at the defaults: what a new user's first run flags, per part, next to a nearest-neighbour baseline.

Run by hand from the repository root (not a test):

    .venv/bin/python benchmarks/verdicts.py [--parts fandisk,builtin,enclosure] [--work results/verdicts]
    .venv/bin/python benchmarks/verdicts.py --variants      # + the score study (several point scores x aggregates)

Per part, in one run: synthesise a collection (32 good training scans, 16 good test scans, 16 per defect type,
4,000 points, seed 0; cached in WORK by its parameters), train with ``train_latent.py``'s defaults (cached), then the
README's shortest path on an uncalibrated copy of the model: ``python -m inspection score`` (which calibrates on the
held-back scans by itself). Printed per part: object AUROC overall and per defect type, the fraction of defective
and of good test scans flagged at the defaults, the threshold's basis and predicted false-alarm rate with its
interval, seconds per scan; beside it the nearest-neighbour baseline (each test point's distance to the nearest point
of the training scans, scan score = mean of the worst 5 %) thresholded the same way (``fit_threshold`` on the
held-back scans' baseline scores at the same alpha). ``--no-origins`` strips the scans' sensor origins (a scanner that
does not record them): a collection and model of their own, no rays, and the grazing term's viewpoint estimated from
the normals (``inspection.scores.view_origin_from_normals``).

``--variants`` projects every scan once more and prints, for several point scores and aggregates, the same columns
at the default alpha: the evidence behind the default score.
"""
import argparse
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from baselines import nn_baseline

SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"
PART_SOURCES = {"fandisk": str(SHARED / "fandisk.obj"), "bunny": str(SHARED / "stanford-bunny.obj")}


def _part_mesh(name):
    from datasets.parts import load_part

    return load_part(PART_SOURCES.get(name, name))


def synth(part, args, work):
    """The part's collection (cached by its parameters). Returns its path."""
    from datasets import ScanCollection
    from datasets.synth import synthesise

    params = dict(part=part, n_train=args.train, n_test_good=args.test_good, n_test_defective=args.per_defect,
                  n_points=args.points, seed=args.seed, jitter_deg=args.jitter)
    if args.no_origins:  # a scanner that does not record where it stood (the same scans otherwise)
        params["sensor_origins"] = False
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]
    path = work / f"{part}_{key}" / "tree.h5"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        scans, frame = synthesise(_part_mesh(part), n_train=args.train, n_test_good=args.test_good,
                                  n_test_defective=args.per_defect, n_points=args.points, seed=args.seed,
                                  jitter_deg=args.jitter, progress=not args.quiet)
        if args.no_origins:
            for scan in scans:
                scan.sensor_origin = None
        ScanCollection.create(path, scans, frame=frame, provenance={"benchmark": "verdicts", **params})
        print(f"{part}: synthesised {len(scans)} scans in {time.perf_counter() - t0:.0f} s -> {path}")
    return path


def train(data, args):
    """train_latent.py with its defaults (cached beside the data). Returns (model path, seconds or None)."""
    model = data.parent / (f"model{_suffix(args)}.pt")
    if model.is_file():
        return model, None
    import train_latent

    argv = ["--data", str(data), "--out", str(model), "--seed", str(args.seed)]
    if args.epochs:
        argv += ["--epochs", str(args.epochs)]
    if args.representation:
        argv += ["--representation", args.representation]
    if args.quiet:
        argv.append("--quiet")
    t0 = time.perf_counter()
    if train_latent.main(argv) not in (0, None):
        raise SystemExit(f"training {data} failed")
    return model, time.perf_counter() - t0


def _suffix(args):
    """What tells this run's model (and scoring folder) apart from the defaults': '_e<epochs>', '_<representation>'."""
    return (f"_e{args.epochs}" if args.epochs else "") + (f"_{args.representation}" if args.representation else "")


def rates(scores, labels, defects, threshold):
    """AUROC overall and per defect type; fractions flagged of defective and good scans at ``threshold``."""
    from sklearn.metrics import roc_auc_score

    y = (labels == "defective").astype(int)
    out = {"auroc": roc_auc_score(y, scores)}
    for d in sorted(set(defects[y == 1])):
        sel = (y == 0) | (defects == d)
        out[d] = roc_auc_score(y[sel], scores[sel])
    out["flag_def"] = float(np.mean(scores[y == 1] > threshold))
    out["flag_good"] = float(np.mean(scores[y == 0] > threshold))
    out["n_good"] = int((y == 0).sum())
    return out


def default_pipeline(part, data, model, args, work):
    """The README's shortest path on an uncalibrated copy: ``python -m inspection score``. Returns the summary."""
    from inspection.run import calibrate, score

    run = work / ("defaults" + _suffix(args) + ("_aligned" if args.align else "") + ("_rays" if args.rays else "")
                  + ("_norays" if args.no_rays else ""))
    run.mkdir(parents=True, exist_ok=True)
    copy = run / "model.pt"
    shutil.copyfile(model, copy)  # uncalibrated: score calibrates on the held-back scans by itself
    if args.rays or args.no_rays:  # `python -m inspection calibrate --rays / --no-rays` first (default: auto)
        calibrate(copy, data, rays=bool(args.rays), progress=not args.quiet)
    lines = []
    summary = score(copy, data, run / "results", split="test", progress=not args.quiet, maps="flagged",
                    echo=lines.append, overwrite=True, align=args.align)
    for line in lines:
        if line.startswith(("note:", "threshold basis", "calibrated on")) or "not calibrated" in line:
            print(f"  {part}: {line}")
    return summary


def baseline(data, model, alpha):
    """The nearest-neighbour baseline with a threshold fitted like the toolkit's: on the held-back scans and the
    training scans cross-fitted (each against the other training scans' points)."""
    from datasets import ScanCollection

    from inspection.model_io import load_model
    from inspection.threshold import fit_threshold

    handle = load_model(model)
    held = set(handle.heldback_names)
    with ScanCollection(data) as c:
        names = c.names
        train = c.read_many([i for i in c.select(split="train") if names[i] not in held])
        cal = c.read_many([i for i, n in enumerate(names) if n in held])
        test = c.read_many(c.select(split="test"))
    train_points = np.concatenate([s.points for s in train])
    t0 = time.perf_counter()
    test_scores = np.array([v for v, _ in nn_baseline(train_points, test)])
    seconds = (time.perf_counter() - t0) / len(test)
    cal_scores = np.array([v for v, _ in nn_baseline(train_points, cal)])
    crossed = [nn_baseline(np.concatenate([t.points for j, t in enumerate(train) if j != i]), [s])[0][0]
               for i, s in enumerate(train)]
    decision = fit_threshold(np.r_[cal_scores, crossed], alpha,
                             ["held-back"] * len(cal_scores) + ["cross-fitted"] * len(crossed))
    labels = np.array([s.label for s in test])
    defects = np.array([s.defect for s in test])
    return rates(test_scores, labels, defects, decision.value), decision, seconds


def _print_rows(rows, kinds):
    head = (f"{'part':<10} {'method':<26} {'AUROC':>6} " + " ".join(f"{k:>8}" for k in kinds)
            + f" {'def flagged':>11} {'good flagged':>12} {'basis':>10} {'pred. FAR (90% int.)':>22} {'s/scan':>7}")
    print(head)
    from inspection.threshold import format_rate

    for part, method, r, decision, sec in rows:
        lo, hi = decision.far_interval
        far = f"{format_rate(decision.predicted_far)} ({format_rate(lo)}-{format_rate(hi)})".replace(" %", "%")
        print(f"{part:<10} {method:<26} {r['auroc']:6.3f} " + " ".join(f"{r.get(k, float('nan')):8.3f}" for k in kinds)
              + f" {r['flag_def']:11.3f} {round(r['flag_good'] * r['n_good']):>5d} of {r['n_good']:<4d}"
              + f" {decision.basis:>10} {far:>22} {sec:7.3f}")


def main_args(argv=None):
    """The parsed command line (also what benchmarks/latent_budget.py passes to :func:`synth`)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--parts", default="fandisk,builtin", help="comma-separated: fandisk, bunny, builtin, or any "
                                                              "name datasets.parts.load_part knows, or a mesh file")
    p.add_argument("--train", type=int, default=32)
    p.add_argument("--test-good", type=int, default=16)
    p.add_argument("--per-defect", type=int, default=16)
    p.add_argument("--points", type=int, default=4000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jitter", type=float, default=0.0, help="pose jitter in degrees on every scan")
    p.add_argument("--align", action="store_true", help="score with --align (ICP onto the training scans first)")
    rays = p.add_mutually_exclusive_group()
    rays.add_argument("--rays", action="store_true", help="calibrate with the ray score (sensor origins) first")
    rays.add_argument("--no-rays", action="store_true", help="calibrate without the ray score first (default: "
                                                             "score's own, the rays when every scan has a sensor "
                                                             "origin)")
    p.add_argument("--no-origins", action="store_true", help="scans without sensor origins (the same synthetic scans, "
                                                             "a collection and model of their own): no rays, and the "
                                                             "grazing term's viewpoint estimated from the normals")
    p.add_argument("--epochs", type=int, default=None, help="train_latent epochs (default: its own)")
    p.add_argument("--representation", choices=("siren", "grid"), default=None,
                   help="train_latent.py --representation (default: its own); the model is cached per representation")
    p.add_argument("--variants", action="store_true", help="also the score study (point scores x aggregates)")
    p.add_argument("--work", default="results/verdicts")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None):
    args = main_args(argv)
    work = Path(args.work)
    print(f"load average at start: {os.getloadavg()}")
    rows, kinds = [], set()
    for part in args.parts.split(","):
        data = synth(part, args, work)
        model, seconds = train(data, args)
        if seconds is not None:
            print(f"{part}: trained in {seconds:.0f} s -> {model}")
        summary = default_pipeline(part, data, model, args, data.parent)
        from inspection.threshold import Threshold

        decision = Threshold(**{k: (tuple(v) if k == "far_interval" else (np.inf if v is None and k == "value" else v))
                                for k, v in summary["decision"].items() if k != "far_interval_level"})
        metrics = summary["metrics"]
        labels_ok = metrics.get("confusion_matrix", {})
        n_good = labels_ok.get("tn", 0) + labels_ok.get("fp", 0)
        r = {"auroc": metrics["auroc"], **metrics["auroc_per_defect"], "flag_def": metrics["detection_rate"],
             "flag_good": metrics["false_alarm_rate"], "n_good": n_good}
        kinds |= set(metrics["auroc_per_defect"])
        rays = summary.get("rays") is not None
        method = f"toolkit {summary['point_score']}/{summary['aggregate']}" + (" +rays" if rays else "")
        rows.append((part, method + (f" {args.representation}" if args.representation else ""), r, decision,
                     summary["seconds_per_scan"]))
        nn, nn_decision, nn_sec = baseline(data, model, summary["alpha"])
        rows.append((part, "nearest-neighbour top5%", nn, nn_decision, nn_sec))
        if args.variants:
            from variants import study  # noqa: E402  (benchmarks/variants.py, beside this script)

            for name, r, decision, sec in study(data, model, summary["alpha"]):
                rows.append((part, name, r, decision, sec))
    print()
    _print_rows(rows, sorted(kinds))
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
