"""The real suite's run: the tree scored at the defaults through the inspection API, next to the nearest-neighbour
baseline, and the table printed."""
import time

import numpy as np

from benchmarks import baselines, inspect_api, metrics, options
from benchmarks.suites.real.tree import KINDS
from benchmarks.table import format_table


def score(data, model, run_dir, args):
    """Score the run at the defaults, print the table next to the baseline. Returns the figures."""
    from datasets import ScanCollection

    from benchmarks.table import verdicts_table

    verdict_rows = []
    for folds in options.fold_settings(args.folds):
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
