"""Command line of the inspection package: calibrate a model on good scans, score scans, run the demo.

    python -m inspection calibrate --model model.pt --data good.h5 [--alpha 0.02] [--no-rays] [--[no-]align]
                                   [--coverage auto|off|L]
    python -m inspection score --model model.pt --data tree.h5 --out results/ [--split test] [--align] [--jobs 4]
    python -m inspection watch --model model.pt --data drop_folder/ --out results/ [--once] [--settle 1]
                               [--report-every 10] [--report-seconds 60]
    python -m inspection coverage --model model.pt [--data scans/] [--n 4] [--out coverage/]
    python -m inspection demo --out demo_output

Heavy libraries are imported inside the commands, so --help is fast.
"""
import logging
import os
import sys

# Before torch loads: OpenMP threads that spin while waiting make torch many times slower on a shared, oversubscribed
# CPU (docs/results.md#threads). An explicit setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _parser():
    from .config import DEFAULT_AGGREGATE, DEFAULT_PROJECTION, InspectionConfig
    from .scores import POINT_SCORES
    from .batch_check import DEFAULT_MAX_DEFECTIVE_SHARE
    from .watch import DEFAULT_WINDOW, REPORT_EVERY, REPORT_SECONDS

    defaults = InspectionConfig()
    from datasets.cli import OneLineParser

    p = OneLineParser(prog="python -m inspection", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("calibrate", help="calibrate a model's threshold on good scans it did not train on; the "
                                         "calibration is stored in the model file")
    c.add_argument("--model", required=True, help="model checkpoint (.pt), rewritten atomically")
    c.add_argument("--data", required=True, help="collection (.h5), folder of scans or cloud file with good scans")
    c.add_argument("--split", default=None, help="use this split's good scans (default: the model's held-back "
                                                 "scans when DATA is its training collection, else every good scan "
                                                 "the model did not train on)")
    c.add_argument("--alpha", type=float, default=defaults.alpha,
                   help="false-alarm rate stored with it (default %(default)s; with fewer than 1/alpha - 1 good "
                        "scans the threshold is extrapolated from a log-normal fit of their scores, and says so)")
    c.add_argument("--aggregate", default=DEFAULT_AGGREGATE,
                   help="per-scan aggregate: top1 (default), mean, max, median, top<P>, q<P>")
    c.add_argument("--point-score", choices=("auto", *POINT_SCORES), default=defaults.point_score,
                   help="per-point score (default auto: joint when DATA is the model's training collection, whose "
                        "training scans give the per-location reference, else residual). "
                        + "; ".join(f"{s.name}: {s.summary}" for s in POINT_SCORES.values()))
    c.add_argument("--noise", type=float, default=None, help="noise floor (model frame units; default the model's)")
    c.add_argument("--projection", default="default",
                   help="latent projection options as KEY=VALUE,... (fields of "
                        "autodecoder.latent.projection.ProjectionOptions), 'default' (inspection's: "
                        + ",".join(f"{k}={v}" for k, v in DEFAULT_PROJECTION.items()) + ") or 'model' (the "
                        "projector's own)")
    rays = c.add_mutually_exclusive_group()
    rays.add_argument("--rays", dest="rays", action="store_const", const=True, default=defaults.rays,
                      help="add the ray score (material the model expects where the sensor saw free space, e.g. a "
                           "hole in a thin wall), combined with the point score; every scan needs a sensor origin")
    rays.add_argument("--rays-auto", dest="rays", action="store_const", const="auto",
                      help="the ray score when DATA is the model's training collection and every scan has a sensor "
                           "origin (the default)")
    rays.add_argument("--no-rays", dest="rays", action="store_const", const=False,
                      help="point score only")
    c.add_argument("--ray-options", default="", help="ray score settings as KEY=VALUE,... (n_rays=384, "
                                                      "n_empty=128, gap=2.0, aggregate=top1, seed=0, band=0.5 (kernel "
                                                      "lengthscales), clearance=WORLD UNITS; default: the field's "
                                                      "lengthscale)")
    align = c.add_mutually_exclusive_group()
    align.add_argument("--align", dest="align", action="store_const", const=True, default=defaults.align,
                       help="parts not held in a fixture: register every scan (these and the ones scored later) onto "
                            "the good training scans first (ICP)")
    align.add_argument("--no-align", dest="align", action="store_const", const=False,
                       help="never register (default: register when the training scans' poses spread; one line "
                            "says so)")
    c.add_argument("--coverage", default="auto", metavar="auto|off|L",
                   help="score each scan over its points on surface the good training scans covered (within L "
                        "kernel lengthscales; a scan whose evidence lies elsewhere is 'uncertain'): auto (default: "
                        "when the held-back good scans show uncovered surface), off, or L (docs/inspection.md)")
    c.add_argument("--quiet", action="store_true")

    s = sub.add_parser("score", help="score scans, write scores.csv, summary.json, roc.png, scores.png, maps/")
    s.add_argument("--model", required=True)
    s.add_argument("--data", required=True, help="collection (.h5), folder of scanner files, or one cloud file")
    s.add_argument("--out", required=True, help="results folder (an earlier results folder is overwritten)")
    s.add_argument("--split", default="test", help="split to score (default test; 'all' for every scan)")
    s.add_argument("--alpha", type=float, default=None, help="false-alarm rate (default: the calibration's)")
    s.add_argument("--maps", choices=("flagged", "all", "none"), default="flagged",
                   help="which scans get a coloured PLY in OUT/maps (default flagged)")
    s.add_argument("--align", action="store_true",
                   help="register each scan onto the good training scans first (ICP); a setting of the calibration: "
                        "an uncalibrated model is calibrated with it (without it: registered when the training "
                        "scans' poses spread), a model calibrated with `calibrate --align` aligns without it, as "
                        "does a model trained in one common pose or a family's size (one line says it is not "
                        "needed); refused for a model calibrated without registration")
    s.add_argument("--two-class", action="store_true",
                   help="good or defective only (default: a scan whose score lies within the threshold's own "
                        "uncertainty is 'uncertain': rescan it)")
    s.add_argument("--tolerance", default=None, metavar="DEV[,AREA]",
                   help="also call a scan defective when one of its defect regions departs from where good parts "
                        "put the surface by more than DEV over more than AREA, in the scans' units (e.g. "
                        "0.2mm,4mm2); defects.csv and scores.csv say which decided")
    s.add_argument("--features", default=None, metavar="CSV",
                   help="named features of the part (a CSV file with a header name,x,y,z in the part's frame, the "
                        "scans' units): defects.csv names each region's nearest")
    s.add_argument("--overwrite", action="store_true", help="write into an existing folder that is not a results "
                                                            "folder")
    s.add_argument("--jobs", type=_positive_int, default=1,
                   help="score in this many processes (default 1); the results are the same, in the same order")
    s.add_argument("--max-defective-share", type=_share, default=DEFAULT_MAX_DEFECTIVE_SHARE,
                   help="the largest share of defective scans a batch may hold (default %(default)s): the batch check (docs/inspection.md) warns when the scans do not look like the calibration's good ones, and then tells a scan above the threshold but within the batch's shift 'uncertain', not 'defective'; a line with few defective parts says so with a smaller share (0.2), which makes the check sensitive on small batches")
    s.add_argument("--quiet", action="store_true")

    w = sub.add_parser("watch", help="score each scan file as it lands in a folder (a scanner's drop folder), once; "
                                     "verdicts appended to OUT/verdicts.jsonl and OUT/verdicts.csv, maps to OUT/maps, "
                                     "the page of `score` kept in OUT/report.html")
    w.add_argument("--model", required=True, help="a calibrated model")
    w.add_argument("--data", required=True, help="the folder the scanner writes cloud files into (not recursive; "
                                                 "hidden files and other suffixes, e.g. .part, are ignored)")
    w.add_argument("--out", required=True, help="results folder: verdicts.jsonl (the journal: a restarted watcher "
                                                "skips what it records), verdicts.csv, maps/, report.html")
    w.add_argument("--once", action="store_true", help="score the files present (waiting for any still being "
                                                       "written) and exit; default: keep watching until Ctrl-C")
    w.add_argument("--settle", type=_seconds, default=1.0,
                   help="a file is read once its size and time have not changed for this many seconds (default "
                        "%(default)s; 0 for scanners that write under a temporary name and rename)")
    w.add_argument("--interval", type=_seconds, default=1.0, help="seconds between looks (default %(default)s)")
    w.add_argument("--alpha", type=float, default=None, help="false-alarm rate (default: the calibration's)")
    w.add_argument("--maps", choices=("all", "flagged", "none"), default="all",
                   help="which scans get a coloured PLY in OUT/maps (default all)")
    w.add_argument("--two-class", action="store_true", help="good or defective only (no 'uncertain')")
    w.add_argument("--report-every", type=_whole, default=REPORT_EVERY, metavar="N",
                   help="rewrite OUT/report.html after every N scans (default %(default)s; 0: only by time and at "
                        "the end) ...")
    w.add_argument("--report-seconds", type=_seconds, default=REPORT_SECONDS, metavar="S",
                   help="... or S seconds after it was last written, whichever comes first, and when the watcher "
                        "stops (default %(default)s)")
    w.add_argument("--max-defective-share", type=_share, default=DEFAULT_MAX_DEFECTIVE_SHARE,
                   help="the largest share of defective scans the last --window scans may hold (default %(default)s): the batch check (docs/inspection.md) warns when the scans do not look like the calibration's good ones, and then tells a scan above the threshold but within the batch's shift 'uncertain', not 'defective'; a line with few defective parts says so with a smaller share (0.2), which makes the check sensitive on small batches")
    w.add_argument("--window", type=_positive_int, default=DEFAULT_WINDOW, metavar="N",
                   help="the batch check looks at the last N scans (default %(default)s)")
    w.add_argument("--quiet", action="store_true", help="no line per scan (the summary line stays)")

    v = sub.add_parser("coverage", help="where the good scans cover the part, and the good scans to take next: "
                                        "OUT/coverage.png, coverage.ply, coverage.json")
    v.add_argument("--model", required=True, help="a calibrated model")
    v.add_argument("--data", default=None, help="scans whose surface should be covered (e.g. those told 'uncertain "
                                                "- not covered'; default: the model's mean shape)")
    v.add_argument("--split", default=None, help="only this split of DATA (default: every scan)")
    v.add_argument("--n", type=_positive_int, default=4, help="views to propose (default %(default)s)")
    v.add_argument("--out", default="coverage", help="output folder (default %(default)s)")
    v.add_argument("--quiet", action="store_true")

    d = sub.add_parser("demo", help="the whole pipeline on the built-in part: synthesise, train, calibrate, score")
    d.add_argument("--out", default="demo_output")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--quick", action="store_true", help="smaller sizes (a smoke test, not a measurement)")
    d.add_argument("--quiet", action="store_true")
    return p


def _positive_int(text):
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def _whole(text):
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def _share(text):
    import argparse

    from .batch_check import check_max_defective_share

    try:
        return check_max_defective_share(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _seconds(text):
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return value


def config_from_args(args):
    """The :class:`inspection.config.InspectionConfig` of ``calibrate``'s options, validated (a ValueError naming
    the option before any file is read)."""
    from .config import InspectionConfig, parse_key_values

    projection = args.projection
    if projection == "model":
        projection = None
    elif projection != "default":
        projection = parse_key_values(projection, "--projection")
    ray_options = parse_key_values(args.ray_options, "--ray-options") or None
    if ray_options and args.rays is False:
        raise ValueError("--ray-options needs --rays (or --rays-auto, the default), not --no-rays")
    coverage = {"off": 0.0}.get(args.coverage, args.coverage)
    return InspectionConfig(alpha=args.alpha, aggregate=args.aggregate, point_score=args.point_score,
                            noise=args.noise, projection=projection, rays=args.rays,
                            ray_options=ray_options, align=args.align, coverage=coverage).validated()


def main(argv=None):
    """Run the command line; returns the exit status (0 ok, 1 some scans could not be scored, 2 bad input)."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    from .errors import InspectionError

    try:
        if args.command == "calibrate":
            from .job import calibrate, describe_calibration

            config = config_from_args(args)
            insp, info = calibrate(args.model, args.data, config, split=args.split, progress=not args.quiet,
                                   echo=print)
            print(f"{args.model}: " + "\n".join(describe_calibration(insp, info)))
        elif args.command == "score":
            from .run import score

            summary = score(args.model, args.data, args.out, split=None if args.split == "all" else args.split,
                            alpha=args.alpha, maps=args.maps, align=args.align,
                            progress=not args.quiet, overwrite=args.overwrite, uncertain=not args.two_class,
                            jobs=args.jobs, max_defective_share=args.max_defective_share, tolerance=args.tolerance,
                            features=args.features)
            if summary.get("n_errors"):
                print(f"error: {summary['n_errors']} scan(s) could not be scored (verdict 'error' in "
                      f"{args.out}/scores.csv)", file=sys.stderr)
                return 1
        elif args.command == "watch":
            return _watch(args)
        elif args.command == "coverage":
            from .coverage_job import coverage_plan, describe_plan, write_coverage

            plan = coverage_plan(args.model, args.data, args.n, args.split, progress=not args.quiet)
            write_coverage(plan, args.out)
            print("\n".join(describe_plan(plan)) + f"\nwritten to {args.out}/ (coverage.png, coverage.ply, "
                                                   f"coverage.json)")
        else:
            from .demo import run_demo

            run_demo(args.out, seed=args.seed, quick=args.quick, progress=not args.quiet)
    except (InspectionError, OSError, ValueError, KeyError) as exc:
        return _report_error(exc)
    return 0


def _watch(args):
    """``watch``: until Ctrl-C or SIGTERM (exit 0, with a summary line), or with --once until the files present are
    scored (exit 1 when some could not be)."""
    import signal

    from .watch import watch

    def stop(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)  # a service manager's stop: a clean exit like Ctrl-C
    try:
        watcher = watch(args.model, args.data, args.out, once=args.once, settle=args.settle, interval=args.interval,
                        maps=args.maps, alpha=args.alpha, uncertain=not args.two_class, quiet=args.quiet,
                        report_every=args.report_every, report_seconds=args.report_seconds,
                        max_defective_share=args.max_defective_share, window=args.window)
    except KeyboardInterrupt:
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 1 if args.once and watcher.counts.get("error") else 0


def _report_error(exc):
    """One line on stderr for a user's mistake (bad option values, missing or unwritable files, bad data); exit 2."""
    from datasets.cli import one_line

    print(f"error: {one_line(exc)}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
