"""What a new user's first run decides, per part, next to the nearest-neighbour baseline.

Per part: a synthetic collection (:func:`benchmarks.cache.synth_collection`: 32 good training scans, 16 good test
scans, 16 per defect type, 4,000 points), a model trained with the trainer's defaults
(:func:`benchmarks.cache.trained_model`), then the README's shortest path on an uncalibrated copy of it:
``python -m inspection score``, which calibrates on the held-back scans and the cross-fitted training scans by itself
(:func:`benchmarks.inspect_api.calibrate_and_score`). Printed per part: object AUROC overall and per defect type,
the fractions of defective and of good test scans flagged, the threshold's basis and predicted false-alarm rate with
its 90 % interval, seconds per scan; beside it the nearest-neighbour baseline thresholded the same way
(:func:`benchmarks.baselines.nn_figures`).

Two other regimes, as options:

- ``--multi-part``: the parts' collections merged into one (each scan's ``part_id`` its part) and one model trained
  on it with the defaults; per part, its scans' figures under the two-part model next to its own model's.
- ``--templates``: the Real3D-AD / Anomaly-ShapeNet regime: 4 complete clouds sampled from the part's mesh (each
  ``--template-points``, depth noise 0.002 x the diagonal along the normal) and partial test scans with defects
  (the synthetic collection's test scans), written as a Real3D-AD class folder and imported by the datasets
  importer (the templates become ``--views`` partial training views and ``--validation-views`` held-back views
  each); trained, calibrated and scored as above; object and point AUROC per defect type next to the baseline.
- ``--family VALUE``: a product family (:func:`benchmarks.cache.family_collection`): the training scans show
  variants of the part, the test scans one variant that none showed; ``--family-kind stretch`` (the default):
  stretched along its longest axis (VALUE 1.0: the nominal part, inside the family's range of 0.8-0.9 and 1.1-1.2;
  1.3: outside it); ``bend``: bent along it (VALUE in degrees; 0: the nominal part, inside the range of 6-12 degrees
  either way; 18: outside it); ``hole``: the built-in bracket's bolt holes or the enclosure's top hole moved by VALUE
  mm (0 inside the range of 2-4 mm either way; 9 outside it); ``wall``: the cup's or the enclosure's sheet VALUE mm
  thick (1.5 inside the range of 1.0-1.25 and 1.75-2.0; 3.0 outside it); scored as above.
"""
import json
import time
from pathlib import Path

import numpy as np

from benchmarks import baselines, cache, inspect_api, metrics, options
from benchmarks.table import format_table, verdicts_table

DESCRIPTION = ("a new user's first run per part (synthesise, train, score at the defaults): object AUROC per defect "
               "type, flagged fractions, threshold, s/scan, next to the nearest-neighbour baseline; --multi-part, "
               "--templates")
WORK = "results/inspection"


def add_arguments(p):
    p.add_argument("--parts", default="fandisk,builtin",
                   help="comma-separated: fandisk, bunny, builtin, enclosure, cup, or a mesh file (default: %(default)s)")
    p.add_argument("--train", type=int, default=32, help="good training scans (default: %(default)s)")
    p.add_argument("--test-good", type=int, default=16, help="good test scans (default: %(default)s)")
    p.add_argument("--per-defect", type=int, default=None,
                   help="test scans per defect type (default: 16; 8 with --templates)")
    p.add_argument("--points", type=int, default=4000, help="points per scan (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="synthesis and training seed (default: %(default)s)")
    p.add_argument("--jitter", type=float, default=0.0, help="pose jitter of every scan, degrees (default: none)")
    p.add_argument("--sensor", choices=("pinhole", "line"), default="pinhole",
                   help="the virtual scanner: a pinhole depth camera (default) or a line scanner sweeping a laser fan "
                        "(datasets.scanner; its sidecar origin is the head at mid-sweep)")
    p.add_argument("--origin-standoff", default=None, metavar="LOW,HIGH",
                   help="the sensor origins the scans record as a user writes them: the stand-off times a factor "
                        "drawn log-uniformly in [LOW, HIGH] per scan (datasets.scanner.written_origin; default exact)")
    p.add_argument("--origin-tilt", type=float, default=0.0, metavar="DEG",
                   help="and the recorded axis turned by up to DEG degrees per scan (default: none)")
    p.add_argument("--defect-size", type=float, default=1.0, metavar="F",
                   help="every defect's width and depth times F (datasets.synth.synthesise's defect_size; default 1)")
    p.add_argument("--family-kind", choices=cache.FAMILY_KINDS, default="stretch",
                   help="--family: how the variants differ (default: %(default)s; bend: VALUE in degrees, the family "
                        "bent by 6-12 degrees either way, 0 the nominal part inside, 18 outside; hole: the holes "
                        "moved by VALUE mm, 2-4 either way, parts builtin and enclosure; wall: the sheet VALUE mm "
                        "thick, 1.0-1.25 and 1.75-2.0, parts cup and enclosure)")
    p.add_argument("--family-scale", type=float, default=1.0,
                   help="--family: the variants' spread about the nominal part times this (default 1; bend 4: "
                        "24-48 degrees either way)")
    p.add_argument("--family", type=float, default=None, metavar="VALUE",
                   help="a product family (issue 32): training scans of variants of each part (--family-kind; "
                        "benchmarks.cache.family_collection), test scans of the variant VALUE (stretch: 1.0 the "
                        "nominal part, inside the range of 0.8-0.9 and 1.1-1.2, never trained on; 1.3 just outside "
                        "it); compare with the same part without --family (its own model)")
    options.add_align_options(p)
    rays = p.add_mutually_exclusive_group()
    rays.add_argument("--rays", dest="rays", action="store_const", const=True, default=None,
                      help="calibrate with the ray score (default: the inspection's choice, the rays when every "
                           "scan has a sensor origin)")
    rays.add_argument("--no-rays", dest="rays", action="store_const", const=False, help="calibrate without it")
    p.add_argument("--no-origins", action="store_true",
                   help="the same scans without sensor origins (a collection and model of their own): no rays, the "
                        "grazing term's viewpoint estimated from the normals")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: the trainer's)")
    p.add_argument("--calibration-fraction", type=float, default=None,
                   help="share of the good training scans held back for calibration (default: the trainer's)")
    p.add_argument("--width", type=int, default=None,
                   help="hidden width of the SIREN networks (default: the trainer's, LatentOptions.width)")
    p.add_argument("--grid-mean", default=None, metavar="KEY=VALUE,...",
                   help="--representation grid: settings of the mean's grid net over the trainer's "
                        "(autodecoder.latent.options.LATENT_GRID_MEAN), e.g. shared_cells=160,finest=128")
    p.add_argument("--depth", type=int, default=None,
                   help="hidden layers of the SIREN networks (default: the trainer's, LatentOptions.depth)")
    p.add_argument("--lengthscale", type=float, default=None,
                   help="the GP kernel lengthscale, collection units (default: the trainer's, 2 x the point spacing)")
    p.add_argument("--representation", choices=("siren", "grid"), default=None,
                   help="the model's nets (default: the trainer's); cached per representation")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--multi-part", action="store_true",
                      help="also one model trained on all the parts' scans, per part next to its own model")
    mode.add_argument("--templates", action="store_true",
                      help="the Real3D-AD regime: train on views of 4 complete templates, test on partial scans")
    p.add_argument("--template-points", type=int, default=10000, help="--templates: points per template")
    p.add_argument("--views", type=int, default=16, help="--templates: training views per template")
    p.add_argument("--validation-views", type=int, default=4, help="--templates: held-back views per template")
    options.add_calibration_options(p, "collections and models", WORK, folds_help=", one row each")


def run(args):
    if args.family is not None and (args.templates or args.multi_part):
        raise SystemExit("inspection: --family goes with neither --templates nor --multi-part")
    if args.point_scores and args.templates:
        raise SystemExit("inspection: --point-scores does not go with --templates")
    parts = args.parts.split(",")
    figures = {"parts": {}, "multi_part": None}
    if args.templates:
        for part in parts:
            figures["parts"][part] = _templates(part, args)
        return figures
    rows, collections = [], {}
    for part in parts:
        collections[part], one, part_rows = _single(part, args)
        figures["parts"][part] = one
        rows += part_rows
    print()
    print(verdicts_table(rows))
    if args.multi_part:
        figures["multi_part"] = _multi_part(collections, figures["parts"], args)
    return figures


# ---------------------------------------------------------------------------------------------------- one part
def _train_options(args):
    from autodecoder.latent.folds import SUGGESTED_FOLDS

    return dict(seed=args.seed, epochs=args.epochs, calibration_fraction=args.calibration_fraction,
                representation=args.representation, lengthscale=args.lengthscale,
                width=args.width, depth=args.depth, grid_mean=_grid_settings(args.grid_mean),
                calibration_folds=None if args.folds == "off" else SUGGESTED_FOLDS)


def _grid_settings(text):
    """``"a=1,b=2"`` -> {"a": 1, "b": 2} (integers), None for None."""
    if not text:
        return None
    try:
        return {k.strip(): int(v) for k, v in (item.split("=") for item in text.split(","))}
    except ValueError:
        raise SystemExit(f"--grid-mean takes KEY=INTEGER pairs separated by commas, got {text!r}") from None


def sensor_options(args):
    """``synthesise``'s sensor and defect-size options set apart from the defaults (none at the defaults: the collections cached
    before these options keep their keys)."""
    options = {}
    if args.sensor != "pinhole":
        options["sensor"] = args.sensor
    if args.origin_standoff:
        try:
            low, high = (float(v) for v in args.origin_standoff.split(","))
        except ValueError:
            raise SystemExit(f"--origin-standoff takes LOW,HIGH, got {args.origin_standoff!r}") from None
        options["origin_standoff"] = (low, high)
    if args.origin_tilt:
        options["origin_tilt_deg"] = args.origin_tilt
    if args.defect_size != 1.0:
        options["defect_size"] = args.defect_size
    return options


def _run_name(args):
    """The scoring run's folder: what sets it apart from the defaults' (``defaults`` alone for the defaults)."""
    return ("defaults" + (f"_e{args.epochs}" if args.epochs else "")
            + (f"_cf{args.calibration_fraction:g}" if args.calibration_fraction is not None else "")
            + (f"_l{args.lengthscale:g}" if args.lengthscale else "")
            + (f"_w{args.width}" if args.width else "") + (f"_d{args.depth}" if args.depth else "")
            + ("_grid-" + args.grid_mean.replace("=", "").replace(",", "-") if args.grid_mean else "")
            + (f"_{args.representation}" if args.representation else "")
            + {True: "_aligned", False: "_noalign", None: ""}[args.align]
            + {True: "_rays", False: "_norays", None: ""}[args.rays])


def _single(part, args):
    """One part at the defaults. Returns (collection path, figures, table rows)."""
    t0 = time.perf_counter()
    sizes = dict(n_train=args.train, n_test_good=args.test_good, n_test_defective=args.per_defect or 16,
                 n_points=args.points, jitter_deg=args.jitter, **sensor_options(args))
    if args.family is not None:
        if args.no_origins:
            raise SystemExit("inspection: --family and --no-origins do not go together")
        data = cache.family_collection(part, args.seed, root=args.cache, progress=args.progress,
                                       test_stretch=args.family, kind=args.family_kind,
                                       scale=args.family_scale, **sizes)
    else:
        data = cache.synth_collection(part, args.seed, root=args.cache, progress=args.progress, **sizes,
                                      **({"sensor_origins": False} if args.no_origins else {}))
    model = cache.trained_model(data, root=args.cache, **_train_options(args))
    info = inspect_api.model_info(model)
    print(f"{part}: collection {data}, model {model} (trained in {info['train_seconds'] or float('nan'):.0f} s; "
          f"collection and model ready after {time.perf_counter() - t0:.0f} s here)", flush=True)
    one = {"collection": str(data), "model": str(model), "train_seconds": info["train_seconds"],
           "fold_seconds": _fold_seconds(model)}
    rows = []
    for folds in options.fold_settings(args.folds):
        run_dir = Path(args.work) / data.parent.name / (_run_name(args) + ("" if folds else "_nofolds"))
        summary = inspect_api.calibrate_and_score(model, data, run_dir, rays=args.rays, align=args.align,
                                                  progress=args.progress, folds=folds,
                                                  echo=lambda line: print(f"  {part}: {line}"))
        toolkit = inspect_api.summary_figures(summary)
        toolkit["method"] = (f"toolkit {toolkit['point_score']}/{toolkit['aggregate']}" + (" +rays" if toolkit["rays"]
                             else "") + (f" {args.representation}" if args.representation else "")
                             + ("" if folds else ", no folds"))
        toolkit.update(_oracle(run_dir, toolkit["alpha"]), calibration_gap=_calibration_gap(run_dir))
        if args.family is not None:  # issue 52, item 3: scans told outside the trained family
            toolkit["outside"] = outside = inspect_api.outside_family_figures(run_dir / "results")
            if outside is not None:
                print("  " + part + ": told outside the trained family: " + ", ".join(
                    f"{o['outside']} of {o['n']} {label} ({o['told_without']} -> {o['told']} told defective)"
                    for label, o in outside.items()), flush=True)
        one["toolkit" if folds else "toolkit_nofolds"] = toolkit
        one["run" if folds else "run_nofolds"] = str(run_dir)
        rows.append(dict(part=part, **toolkit))
    if args.point_scores:
        alone = inspect_api.point_score_runs(model, data, Path(args.work) / data.parent.name,
                                             inspect_api.parse_point_scores(args.point_scores), align=args.align,
                                             progress=args.progress)
        one["point_scores"] = alone
        rows += [dict(part=part, method=f"{spec} alone", **figures) for spec, figures in alone.items()]
    nn_figures = baselines.nn_figures(data, info["heldback_names"], summary["alpha"])
    one["nn"] = nn_figures
    if args.family is not None:  # issue 32, item 1: how well the projection fits the unseen member's true surface
        from benchmarks.family_fit import family_fit, paired_family_fit

        fit = family_fit(model, data, part, args.family_kind)
        one["projected_surface"] = fit
        print(f"  {part}: projected mean surface at the member's true surface (median first-order distance, "
              f"collection units): unseen member {fit['unseen']:.4f}, trained members' held-back scans "
              f"{fit['trained']:.4f}", flush=True)
        paired = paired_family_fit(model, data, part, args.family_kind, args.family, scale=args.family_scale)
        one["projected_surface_paired"] = paired
        members = ", ".join(f"{k} {v:.4f}" for k, v in paired["members"].items())
        print(f"  {part}: the same from the same {paired['views']} camera positions for every member: {members}; "
              f"unseen over trained, median over views {paired['paired_ratio']:.2f}", flush=True)
    return data, one, rows + [dict(part=part, **nn_figures)]


def _fold_seconds(model):
    """Seconds the cached model's fold models took to train (None when not recorded)."""
    path = Path(model).parent / "fold_seconds.json"
    return json.loads(path.read_text())["seconds"] if path.exists() else None


def _oracle(run_dir, alpha):
    """``oracle``: the defective test scans flagged by a threshold just above the worst good test scan;
    ``exact_alpha``: those flagged by a threshold at the good test scans' own fitted 1 - ``alpha`` quantile
    (:func:`benchmarks.metrics.exact_alpha_flagged`)."""
    scored = inspect_api.read_scores(Path(run_dir) / "results")
    return {"oracle": metrics.oracle_flagged(scored["score"], scored["label"]),
            "exact_alpha": metrics.exact_alpha_flagged(scored["score"], scored["label"], alpha)}


# ---------------------------------------------------------------------------------------------------- multi-part
def _multi_part(collections, singles, args):
    """One model on the merged collection of the parts; per part its scans' figures next to its own model's."""
    data = cache.merged_collection(collections, root=args.cache)
    model = cache.trained_model(data, root=args.cache, **_train_options(args))
    info = inspect_api.model_info(model)
    run_dir = Path(args.work) / data.parent.name / _run_name(args)
    inspect_api.calibrate_and_score(model, data, run_dir, rays=args.rays, align=args.align, maps="none",
                                    progress=args.progress, echo=lambda line: print(f"  multi-part: {line}"))
    scored = inspect_api.read_scores(run_dir / "results")
    out, rows = {"collection": str(data), "model": str(model), "train_seconds": info["train_seconds"], "parts": {}}, []
    for part, one in singles.items():
        mine = np.char.startswith(scored["name"].astype(str), f"{part}/")
        two = _verdict_figures(scored, mine)
        own = inspect_api.read_scores(Path(one.get("run") or one["run_nofolds"]) / "results")
        single = _verdict_figures(own, np.ones(len(own["name"]), bool))
        out["parts"][part] = {"multi_part": two, "single_part": single}
        rows += [dict(part=part, method="multi-part", train=info["train_seconds"], **two),
                 dict(part=part, method="single-part", train=one["train_seconds"], **single),
                 dict(part=part, method="nearest-neighbour top5%", train=0.0, auroc=one["nn"]["auroc"],
                      flagged=one["nn"]["flagged"])]
    kinds = sorted({k for r in rows for k in r["auroc"] if k != "overall"})
    flat = [{"part": r["part"], "method": r["method"], "auroc": r["auroc"]["overall"],
             **{k: r["auroc"].get(k) for k in kinds}, "def": r["flagged"]["defective"],
             "good": f"{round(r['flagged']['good'] * r['flagged']['n_good'])} of {r['flagged']['n_good']}",
             "train": r["train"]} for r in rows]
    print()
    print(format_table(flat, [("part", "part", ""), ("method", "method", ""), ("auroc", "AUROC", ".3f"),
                              *[(k, k, ".3f") for k in kinds], ("def", "def flagged", ".3f"),
                              ("good", "good flagged", ">"), ("train", "train s", ".0f")]))
    return out


def _verdict_figures(scored, keep):
    """AUROC per type and the flagged fractions of the scans ``keep`` of a scored run, from its own verdicts (which
    may come from one threshold per part)."""
    labels, flagged = scored["label"][keep], scored["flagged"][keep]
    bad = labels != metrics.GOOD
    return {"auroc": metrics.auroc_per_defect(scored["score"][keep], labels, scored["defect"][keep]),
            "flagged": {"defective": float(flagged[bad].mean()), "good": float(flagged[~bad].mean()),
                        "n_good": int((~bad).sum()), "n_defective": int(bad.sum())}}


# ---------------------------------------------------------------------------------------------------- templates
def _template_collection(part, args):
    """The imported Real3D-AD-like class folder of ``part`` (cached: :func:`benchmarks.cache.template_collection`,
    the synthetic collection's test scans as its test scans). Returns its ``data.h5``."""
    test = cache.synth_collection(part, args.seed, root=args.cache, n_train=0, n_test_good=args.test_good,
                                  n_test_defective=args.per_defect or 8, n_points=args.points)
    return cache.template_collection(part, test, args.seed, args.template_points, args.views, args.validation_views,
                                     root=args.cache)


def _calibration_gap(run_dir):
    """How far the good test scans' scores lie from the calibration scans' (:func:`benchmarks.inspect_api.
    calibration_gap`), printed."""
    gap = inspect_api.calibration_gap(run_dir)
    print("  calibration gap (mean log score, good test minus calibration): "
          + ", ".join(f"{k[6:]} {v:+.3f}" for k, v in gap.items() if k.startswith("minus_")))
    return gap


def _templates(part, args):
    """One part in the template regime: object and point AUROC per defect type, toolkit and baseline."""
    from datasets import ScanCollection

    data = _template_collection(part, args)
    model = cache.trained_model(data, root=args.cache, **_train_options(args))
    out = {"collection": str(data), "model": str(model), "fold_seconds": _fold_seconds(model)}
    rows = []
    for folds in options.fold_settings(args.folds):
        run_dir = Path(args.work) / data.parent.name / (_run_name(args) + ("" if folds else "_nofolds"))
        summary = inspect_api.calibrate_and_score(model, data, run_dir, rays=args.rays, maps="none", folds=folds,
                                                  progress=args.progress, echo=lambda line: print(f"  {part}: {line}"))
        toolkit = inspect_api.summary_figures(summary)
        toolkit.update(_oracle(run_dir, toolkit["alpha"]), calibration_gap=_calibration_gap(run_dir))
        toolkit["method"] = f"toolkit {toolkit['point_score']}/{toolkit['aggregate']}" + ("" if folds else ", no folds")
        out["toolkit_summary" if folds else "toolkit_summary_nofolds"] = toolkit
        rows.append(dict(part=part, **toolkit))
    print(verdicts_table(rows))
    scans, scored = inspect_api.point_maps(run_dir / "model.pt", data)
    with ScanCollection(data) as c:
        train = c.read_many(c.select(split="train"))
        n_validation = len(c.select(split="validation"))
    nn = baselines.nn_baseline(np.concatenate([s.points for s in train]), scans)
    labels, defects = [s.label for s in scans], [s.defect for s in scans]
    point_labels = [s.point_labels for s in scans]
    result = {}
    for name, scan_scores, maps in (("toolkit", [r["score"] for r in scored], [r["map"] for r in scored]),
                                    ("nn", [v for v, _ in nn], baselines.nn_point_maps(scans, [d for _, d in nn]))):
        result[name] = {"auroc": metrics.auroc_per_defect(scan_scores, labels, defects),
                        "point_auroc": metrics.point_auroc_per_defect(point_labels, maps, labels, defects)}
    print(f"\n== {part}: {len(train)} training views, {n_validation} validation views from 4 templates of "
          f"{args.template_points} points; {len(scans)} test scans of {args.points} points; point score "
          f"{toolkit['point_score']}/{toolkit['aggregate']}, false-alarm rate {toolkit['flagged']['good']:.3f} at "
          f"alpha {toolkit['alpha']}")
    kinds = list(result["toolkit"]["auroc"])
    print(format_table([{"defect": k, "mo": result["toolkit"]["auroc"][k], "no": result["nn"]["auroc"][k],
                         "mp": result["toolkit"]["point_auroc"][k], "np": result["nn"]["point_auroc"][k]}
                        for k in kinds],
                       [("defect", "defect", ""), ("mo", "model obj", ".3f"), ("no", "NN obj", ".3f"),
                        ("mp", "model pt", ".3f"), ("np", "NN pt", ".3f")]))
    return {**out, **result}
