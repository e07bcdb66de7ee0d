"""One model for several part types: a two-part collection trained with the defaults, each part next to its own model.

Run by hand from the repository root (not a test):

    .venv/bin/python benchmarks/multi_part.py --single results/verdicts [--parts fandisk,builtin] [--tag defaults]

The single-part collections of benchmarks/verdicts.py (32 good training scans, 16 good test scans, 16 per defect
type, seed 0; made or reused in ``--single`` by its ``synth``) are merged into one collection: the same scans, each
named ``<part>/<name>`` with ``part_id`` = the part. Frame: each single-part collection holds its scans in its own
unit-cube frame (its file -> collection transform); the merged collection keeps those coordinates as they are and
records the identity frame, i.e. every part sits in its own fixture frame, centred in the same unit cube, and the
latent code (and the part id, where known) tells them apart. Placing the parts side by side instead would halve each
part's share of the box the field covers.

The merged collection is trained with the defaults (``train_collection``, as ``train_latent.py``), then scored the
README's way (``inspection.run.score`` on an uncalibrated copy, which calibrates on the held-back scans by itself).
Printed per part: object AUROC overall and per defect type within the part's scans, the fraction of defective and of
good test scans flagged (the verdicts ``score`` wrote: one pooled threshold, or one per part), next to the part's single-part model (its cached ``defaults/results/scores.csv`` from
benchmarks/verdicts.py, scored the same way) and the nearest-neighbour baseline of benchmarks/verdicts.py; and the
training times (the two-part run measured here, the single-part ones as their checkpoints record them).
"""
import argparse
import csv
import hashlib
import os
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from verdicts import baseline, main_args as verdicts_args, rates, synth


def merge(parts, work):
    """The merged collection of the single-part collections ``parts`` {part: path} (cached by their fingerprints).
    Returns its path."""
    from dataclasses import replace

    from datasets import ScanCollection
    from datasets.frame import Frame

    fingerprints = []
    for path in parts.values():
        with ScanCollection(path) as c:
            fingerprints.append(c.fingerprint())
    key = hashlib.sha256("\n".join([*parts, *fingerprints]).encode()).hexdigest()[:10]
    path = work / f"{'+'.join(parts)}_{key}" / "tree.h5"
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    scans = []
    for part, source in parts.items():
        with ScanCollection(source) as c:
            scans += [replace(s, name=f"{part}/{s.name}", part_id=part) for s in c.read_many(range(len(c)))]
    ScanCollection.create(path, scans, frame=Frame.identity(),
                          provenance={"benchmark": "multi_part", "parts": {p: str(s) for p, s in parts.items()},
                                      "frame": "each part in its own collection's unit-cube frame"})
    print(f"merged {len(scans)} scans of {', '.join(parts)} -> {path}")
    return path


def train(data, tag, seed, quiet, epochs=None):
    """train_collection with its defaults (``epochs`` None: its own; cached as ``model_<tag>.pt`` beside the data).
    Returns (path, seconds)."""
    from autodecoder.latent.train import train_collection

    model = data.parent / f"model_{tag}.pt"
    if model.is_file():
        return model, None
    t0 = time.perf_counter()
    train_collection(data, model, seed=seed, quiet=quiet, **({} if epochs is None else {"epochs": epochs}))
    return model, time.perf_counter() - t0


def read_scores(path):
    """(names, labels, defects, scores, flagged) of a scores.csv that ``python -m inspection score`` wrote."""
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return (np.array([r["name"] for r in rows]), np.array([r["label"] for r in rows]),
            np.array([r["defect"] for r in rows]), np.array([float(r["score"]) for r in rows]),
            np.array([r["verdict"] == "defective" for r in rows]))


def per_part(scores_csv, part=None):
    """:func:`verdicts.rates` of the scans of ``part`` (names ``<part>/...``; None: all) in a scores.csv, the
    flagged fractions from its verdicts (which may come from per-part thresholds)."""
    names, labels, defects, scores, flagged = read_scores(scores_csv)
    sel = np.ones(len(names), bool) if part is None else np.char.startswith(names.astype(str), f"{part}/")
    out = rates(scores[sel], labels[sel], defects[sel], np.inf)
    bad = labels[sel] == "defective"
    out.update(flag_def=float(flagged[sel][bad].mean()), flag_good=float(flagged[sel][~bad].mean()))
    return out


def score(data, model, tag, quiet):
    """The README's shortest path on an uncalibrated copy of ``model``. Returns (summary, results folder, s)."""
    from inspection.run import score as run_score

    run = data.parent / tag
    run.mkdir(parents=True, exist_ok=True)
    copy = run / "model.pt"
    shutil.copyfile(model, copy)
    lines = []
    t0 = time.perf_counter()
    summary = run_score(copy, data, run / "results", split="test", progress=not quiet, maps="none",
                        echo=lines.append, overwrite=True)
    for line in lines:
        if line.startswith(("note:", "threshold basis", "calibrated on")) or "not calibrated" in line:
            print(f"  {line}")
    return summary, run / "results", time.perf_counter() - t0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--parts", default="fandisk,builtin")
    p.add_argument("--single", default="results/verdicts", help="benchmarks/verdicts.py's work folder (its "
                                                                "collections and default models; read only)")
    p.add_argument("--work", default="results/multi_part")
    p.add_argument("--tag", default="defaults", help="names the model and the scoring run (model_<tag>.pt)")
    p.add_argument("--run", default=None, help="names the scoring run's folder (default: the tag); another name "
                                                "re-scores a cached model with the current code")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: train_collection's own)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    # benchmarks/verdicts.py's collection parameters (its defaults): the same scans as its single-part runs
    vargs = verdicts_args(["--seed", str(args.seed)] + (["--quiet"] if args.quiet else []))
    single, work = Path(args.single), Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {os.getloadavg()}")
    names = args.parts.split(",")
    sources = {part: synth(part, vargs, single) for part in names}
    data = merge(sources, work)
    model, seconds = train(data, args.tag, args.seed, args.quiet, args.epochs)
    import torch

    info = torch.load(model, map_location="cpu", weights_only=False)
    print(f"two-part model {model}: {info['epoch']} epochs, train_seconds {info['info']['train_seconds']:.0f}"
          + (f", wall {seconds:.0f} s" if seconds is not None else " (cached)"))
    summary, results, score_seconds = score(data, model, args.run or args.tag, args.quiet)
    print(f"scored in {score_seconds:.0f} s")
    rows, kinds = [], set()
    for part in names:
        single_model = sources[part].parent / "model.pt"
        single_summary = sources[part].parent / "defaults" / "results" / "summary.json"
        import json

        s_summary = json.loads(single_summary.read_text())
        s_info = torch.load(single_model, map_location="cpu", weights_only=False)
        r_two = per_part(results / "scores.csv", part)
        r_one = per_part(single_summary.parent / "scores.csv")
        r_nn, _, _ = baseline(sources[part], single_model, s_summary["alpha"])
        kinds |= {k for k in r_one if k not in ("auroc", "flag_def", "flag_good", "n_good")}
        rows += [(part, f"two-part ({args.run or args.tag})", r_two, info["info"]["train_seconds"]),
                 (part, "single-part", r_one, s_info["info"]["train_seconds"]),
                 (part, "nearest-neighbour top5%", r_nn, 0.0)]
    kinds = sorted(kinds)
    print(f"\n{'part':<9} {'method':<26} {'AUROC':>6} " + " ".join(f"{k:>8}" for k in kinds)
          + f" {'def flagged':>11} {'good flagged':>12} {'train s':>8}")
    for part, method, r, sec in rows:
        print(f"{part:<9} {method:<26} {r['auroc']:6.3f} " + " ".join(f"{r.get(k, float('nan')):8.3f}" for k in kinds)
              + f" {r['flag_def']:11.3f} {round(r['flag_good'] * r['n_good']):>5d} of {r['n_good']:<4d} {sec:8.0f}")
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
