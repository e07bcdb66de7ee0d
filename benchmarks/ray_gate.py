"""The gated-log combination's gate, re-evaluated offline on scored runs: with and without its ceiling bound.

Run by hand from the repository root (not a test), after runs of benchmarks/verdicts.py (and, for the real bunny,
``python -m inspection calibrate`` + ``score`` on benchmarks/real_bunny.py's models):

    .venv/bin/python benchmarks/ray_gate.py [RUN ...]     # default: every results/verdicts/*/defaults

A run folder holds the calibrated ``model.pt`` (its calibration stores the calibration scans' point and ray scores
and their roles) and ``results/scores.csv`` (every test scan's ``score_points`` and ``score_rays``). For each run
and each gate, :class:`inspection.combine.Combination` is rebuilt from the stored calibration components, the test
scans are combined, and the threshold is refitted on the leave-one-out calibration scores exactly as
:class:`inspection.Inspector` does (``fit_threshold`` with the scans' roles, alpha 0.02). Printed: the gate in nats,
object AUROC overall and per defect type, the fraction of defective test scans flagged and the good ones flagged.

Gates: ``no bound`` (the rule before: the 90 % quantile + 2 sd of the log ray scores), and the same bounded at
log(1 + 690.8 / F) for F = 2, 4 (the default, ``LOG_GATE_CEILING_FACTOR``) and 8. The ray scores are those the run
computed; only the combination changes, so this takes seconds.
"""
import argparse
import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
from sklearn.metrics import roc_auc_score

from inspection.combine import LOG_GATE_CEILING_FACTOR, Combination
from autodecoder.scanning.free_space import MAX_SURPRISAL
from inspection.threshold import fit_threshold

ALPHA = 0.02
FACTORS = (None, 2.0, 4.0, 8.0)


def load_run(run):
    """(calibration components dict, roles, test rows [(label, defect, points, rays)]) of a scored run folder."""
    state = torch.load(run / "model.pt", map_location="cpu", weights_only=False)
    calibration = state.get("calibration") or {}
    rays = (calibration.get("extra") or {}).get("rays")
    if not rays:
        raise SystemExit(f"{run}: not calibrated with the ray score")
    comps = {k: rays["components"][k] for k in ("points", "rays")}
    with open(run / "results" / "scores.csv", newline="") as f:
        rows = [(r["label"], r["defect"], float(r["score_points"]), float(r["score_rays"])) for r in csv.DictReader(f)]
    return comps, calibration["roles"], rows


def evaluate(comps, roles, rows, factor):
    """Object AUROC per type, flagged fractions and the gate (nats) of the gated-log rule with this bound."""
    # the bound is log(1 + ceiling / LOG_GATE_CEILING_FACTOR): a ceiling scaled by that factor / F puts it at
    # log(1 + MAX_SURPRISAL / F)
    ceiling = None if factor is None else MAX_SURPRISAL * LOG_GATE_CEILING_FACTOR / factor
    comb = Combination(comps, names=("points", "rays"), rule="gated-log", ceiling=ceiling)
    scores = comb.score({"points": [r[2] for r in rows], "rays": [r[3] for r in rows]})
    threshold = fit_threshold(comb.calibration_scores(), ALPHA, roles).value
    defective = np.array([r[0] != "good" for r in rows])
    kind = np.array([r[1] for r in rows])
    out = {"gate": float(np.expm1(comb.mean[1] + comb.sd[1] * comb.gate[1])),
           "overall": roc_auc_score(defective, scores)}
    for k in sorted(set(kind[defective])):
        keep = ~defective | (kind == k)
        out[k] = roc_auc_score(defective[keep], scores[keep])
    out["flagged"] = float((scores[defective] > threshold).mean())
    out["good_flagged"] = int((scores[~defective] > threshold).sum())
    out["n_good"] = int((~defective).sum())
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", type=Path, help="scored run folders (default: results/verdicts/*/defaults)")
    args = p.parse_args(argv)
    runs = args.runs or sorted(Path("results/verdicts").glob("*/defaults"))
    for run in runs:
        comps, roles, rows = load_run(run)
        print(f"{run}: calibration ray scores {np.min(comps['rays']):.0f}-{np.max(comps['rays']):.0f} nats")
        for factor in FACTORS:
            o = evaluate(comps, roles, rows, factor)
            types = "  ".join(f"{k} {o[k]:.3f}" for k in ("bump", "dent", "foreign", "missing") if k in o)
            label = "no bound" if factor is None else f"F = {factor:g}"
            print(f"  {label:9s} gate {o['gate']:7.1f} nats  overall {o['overall']:.3f}  {types}  "
                  f"flagged {o['flagged']:.3f}  good {o['good_flagged']} of {o['n_good']}")


if __name__ == "__main__":
    main()
