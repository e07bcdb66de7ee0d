"""The latent model: training and projection on partial fandisk scans against per-scan fits, the training budget
against object AUROC, and projection time per scan.

Modes (``--mode``):

``fandisk`` (default)
    A latent model trained on all 32 good partial scans of a fandisk collection (4,000 points each; collection and
    model cached, ``benchmarks.cache``), its 16 held-out good test scans projected: training time (the trainer's
    own), projection seconds per scan (alone, median of 4, and batched 16 at once), the projected mean surfaces'
    Chamfer distance to the true mesh (collection frame), the scans' own distance to it (the sensor-noise floor),
    and for ``--fit-scans`` held-out scans ``fit_cloud``'s SIREN from scratch: its time and Chamfer, and the ratios.
    Writes ``projection.png`` (a held-out scan, its projected mean surface, the variance on a slice) in ``--out``.
``budget``
    The training budget against object AUROC: per part and seed, the collection of a new user's first run
    (``benchmarks.cache.synth_collection``: 32 good training scans, 16 good test scans, 16 per defect type), a model
    trained with ``--options`` (a JSON object of ``LatentOptions`` overrides; the library's defaults for the rest,
    the training seed = the collection's seed; cached by the options), scored with the inspection's defaults
    (``benchmarks.inspect_api.calibrate_and_score``: calibration on the held-back scans, rays where the scans have
    sensor origins) in ``--out/<name>/``; beside it the nearest-neighbour baseline thresholded the same way.
``projection``
    Seconds per scan of latent models' projection side by side: each of ``--models`` projects the same ``--scans``
    test scans of ``--data`` with the inspection's projection settings, the models taking turns ``--repeats``
    times (a changing machine load falls on all alike), after a warm-up that pays the one-off costs.
``defects``
    How far the projection follows a defect (issue 28, item 1), on scored runs: each run folder below ``--runs``
    with a calibrated ``model.pt`` and its scoring summary (the verdicts suite writes these; ``--match`` picks some)
    scored with the field's term alone (``distance``) twice, its code projected from the whole scan (the
    inspection's) and from the scan's good points alone (the labelled defect points left out: a projection no defect
    can pull), the field's term without the field's own variance, and the good points' term alone (``surface``);
    object AUROC overall and per defect type, and the median field term at the defect points under each code
    (``benchmarks.inspect_api.defect_projection``).

The Chamfer distance is ``benchmarks.surface_metrics.mean_surface_distance``.
"""
import json
import time
from pathlib import Path

from benchmarks.cache import CACHE

DESCRIPTION = ("latent model: projection vs per-scan fits on fandisk, training budget vs AUROC, projection time per "
               "scan")
MODES = ("fandisk", "budget", "projection", "defects")
OUT = {"fandisk": "results/latent_fandisk", "budget": "results/latent_budget"}


def add_arguments(parser):
    parser.add_argument("--mode", choices=MODES, default="fandisk", help="what to measure (default: %(default)s)")
    parser.add_argument("--out", "--work", dest="out", default=None, help=f"written files (default: {OUT})")
    parser.add_argument("--cache", default=CACHE, help="collections and models (default: %(default)s)")
    fandisk = parser.add_argument_group("fandisk")
    fandisk.add_argument("--seed", type=int, default=0, help="of the collection, the training and the projection")
    fandisk.add_argument("--epochs", type=int, default=None, help="training epochs (default: LatentOptions)")
    fandisk.add_argument("--latent-dim", type=int, default=None)
    fandisk.add_argument("--width", type=int, default=None)
    fandisk.add_argument("--depth", type=int, default=None)
    fandisk.add_argument("--batch", type=int, default=None)
    fandisk.add_argument("--steps", type=int, default=None, help="projection steps (default: the projector's)")
    fandisk.add_argument("--fit-scans", type=int, default=2, help="held-out scans also fitted with fit_cloud (slow)")
    fandisk.add_argument("--fit-steps", type=int, default=None, help="fit_cloud steps (default: FitOptions)")
    fandisk.add_argument("--samples", type=int, default=20000, help="surface samples per side of the Chamfer distance")
    fandisk.add_argument("--resolution", type=int, default=128, help="marching-cubes grid of the mean surfaces")
    fandisk.add_argument("--threads", type=int, default=1,
                         help="torch threads of projection and fits (1 is fastest on a loaded 2-core box)")
    budget = parser.add_argument_group("budget")
    budget.add_argument("--name", default=None, help="names the variant's scoring folder (default: from --options)")
    budget.add_argument("--options", default="{}", help="JSON object of LatentOptions overrides (e.g. epochs)")
    budget.add_argument("--parts", default="fandisk,builtin,enclosure,cup")
    budget.add_argument("--seeds", default="0", help="comma-separated collection (and training) seeds")
    projection = parser.add_argument_group("projection")
    projection.add_argument("--data", help="scan collection (its 'test' split is projected)")
    projection.add_argument("--models", help="comma-separated latent model files")
    projection.add_argument("--scans", type=int, default=32, help="test scans projected per repeat")
    projection.add_argument("--repeats", type=int, default=3)
    defects = parser.add_argument_group("defects")
    defects.add_argument("--runs", help="a suite's work folder of scored runs (e.g. results/verdicts)")
    defects.add_argument("--match", default="", help="comma-separated texts: only runs whose path has one of them")
    defects.add_argument("--root", default=".", help="the folder the runs were made from (a relative collection "
                                                     "path in a run's summary is read from here)")


def run(args):
    return {"fandisk": _fandisk, "budget": _budget, "projection": _projection, "defects": _defects}[args.mode](args)


# --- fandisk ---------------------------------------------------------------------------------------------------

def _fandisk(args):
    import numpy as np
    import torch
    import trimesh

    from autodecoder import fit_cloud
    from autodecoder.latent.model import load_model
    from benchmarks.cache import part_mesh, synth_collection, trained_model
    from benchmarks.surface_metrics import mean_surface_distance
    from datasets import ScanCollection

    torch.set_num_threads(args.threads)
    out = Path(args.out or OUT["fandisk"])
    out.mkdir(parents=True, exist_ok=True)
    data = synth_collection("fandisk", args.seed, root=args.cache, n_train=32, n_test_good=16, n_test_defective=0,
                            n_points=4000)
    with ScanCollection(data) as c:
        frame = c.frame
        held = c.read_many(c.select(split="test"))
        n_train = len(c.select(split="train"))
    mesh = part_mesh("fandisk")
    true_mesh = trimesh.Trimesh(frame.to_collection(mesh.vertices), mesh.faces, process=False)
    print(f"{n_train} training + {len(held)} held-out partial scans of fandisk (4000 points each): {data}")

    overrides = {k: v for k, v in dict(epochs=args.epochs, latent_dim=args.latent_dim, width=args.width,
                                       depth=args.depth, batch=args.batch).items() if v is not None}
    model_path = trained_model(data, root=args.cache, seed=args.seed, calibration_fraction=0.0, **overrides)
    model = load_model(model_path)
    c = model.config
    train_s = model.info.get("train_seconds", float("nan"))
    targets_s = model.info.get("targets_seconds", float("nan"))
    print(f"training: {train_s:.1f} s of steps (the trainer's own time; {c['epochs']} epochs, latent "
          f"{c['latent_dim']}, width {c['width']}, depth {c['depth']}, batch {c['batch']}; GP targets "
          f"{targets_s:.1f} s; final loss {model.info['history'][-1]['loss']:.4g}; noise {model.noise:.2e}): "
          f"{model_path}")

    popts = {} if args.steps is None else {"steps": args.steps}
    model.project(held[0].points, held[0].normals, steps=5)  # warm-up (first-call allocations)
    singles = []
    for s in held[:4]:
        t0 = time.perf_counter()
        model.project(s.points, s.normals, seed=args.seed, **popts)
        singles.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    projections = model.project_many(held, seed=args.seed, batch=16, **popts)
    batch_s = (time.perf_counter() - t0) / len(held)
    proj_s = float(np.median(singles))
    print(f"projection: {proj_s:.3f} s per scan alone (median of {len(singles)}), {batch_s:.3f} s per scan "
          f"batched (16 at once)")
    chamfer_proj = [mean_surface_distance(pr.field.mesh(args.resolution), true_mesh, args.samples, k)
                    for k, pr in enumerate(projections)]
    # a scan's own points against the true mesh: the floor set by sensor noise
    floor = float(np.median([trimesh.proximity.closest_point(true_mesh, s.points[:1000])[1].mean()
                             for s in held[:4]]))
    print(f"projected mean surface vs true mesh: Chamfer median {np.median(chamfer_proj):.5f}, mean "
          f"{np.mean(chamfer_proj):.5f} (collection units; {args.samples} samples per side; {len(held)} scans); "
          f"scan points to the true mesh {floor:.5f}")
    figures = {"train_seconds": train_s, "epochs": c["epochs"], "projection_seconds": proj_s,
               "projection_seconds_batched": batch_s, "chamfer_projected_median": float(np.median(chamfer_proj)),
               "chamfer_projected_mean": float(np.mean(chamfer_proj)), "scan_to_mesh": floor}

    fit_opts = {} if args.fit_steps is None else {"steps": args.fit_steps}
    fit_s, chamfer_fit = [], []
    for k, s in enumerate(held[:args.fit_scans]):
        t0 = time.perf_counter()
        f = fit_cloud(s.points, s.normals, representation="siren", seed=args.seed, quiet=True, **fit_opts)
        fit_s.append(time.perf_counter() - t0)
        chamfer_fit.append(mean_surface_distance(f.mesh(args.resolution), true_mesh, args.samples, k))
        print(f"  fit_cloud scan {k}: {fit_s[-1]:.1f} s, Chamfer {chamfer_fit[-1]:.5f} "
              f"(projection: {chamfer_proj[k]:.5f})")
    if fit_s:
        same = float(np.median(chamfer_proj[:len(fit_s)]))
        figures.update(fit_seconds=float(np.median(fit_s)), chamfer_fit_median=float(np.median(chamfer_fit)),
                       speedup=float(np.median(fit_s)) / proj_s, speedup_batched=float(np.median(fit_s)) / batch_s,
                       chamfer_projected_over_fit=same / float(np.median(chamfer_fit)))
        print(f"fit_cloud from scratch ({len(fit_s)} held-out scans, {f.info['steps']} steps): "
              f"{np.median(fit_s):.1f} s per scan, Chamfer median {np.median(chamfer_fit):.5f}")
        print(f"RATIOS: projection speed-up {figures['speedup']:.0f}x (batched {figures['speedup_batched']:.0f}x); "
              f"Chamfer projected / fit_cloud on the same scans {figures['chamfer_projected_over_fit']:.2f}")
    _projection_png(held[0], projections[0], out / "projection.png")
    print(f"wrote {out / 'projection.png'}")
    return figures


def _projection_png(scan, projection, path):
    """A held-out scan, its projected mean surface, and the variance on a vertical slice through the scan."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    field = projection.field
    mesh = field.mesh(96)
    fig = plt.figure(figsize=(15, 5))
    ax = fig.add_subplot(131, projection="3d")
    pts = scan.points[::4]
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1, c=pts[:, 2], cmap="viridis")
    ax.set_title(f"held-out partial scan {scan.name} ({len(scan.points)} points)")
    ax = fig.add_subplot(132, projection="3d")
    ax.plot_trisurf(mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.faces, mesh.vertices[:, 2], color="0.7",
                    linewidth=0)
    ax.set_title(f"projected mean surface (loss {projection.loss:.3g})")
    for a in fig.axes:
        a.set_xlim(-0.5, 0.5), a.set_ylim(-0.5, 0.5), a.set_zlim(-0.5, 0.5)
    ax = fig.add_subplot(133)
    t = np.linspace(-0.6, 0.6, 200)
    gy, gz = np.meshgrid(t, t, indexing="xy")
    x0 = float(np.median(scan.points[:, 0]))
    grid = np.stack([np.full(gy.size, x0), gy.ravel(), gz.ravel()], 1)
    var = field.variance(grid).reshape(gy.shape)
    mean = field.mean(grid).reshape(gy.shape)
    im = ax.imshow(np.log10(var + 1e-12), extent=(-0.6, 0.6, -0.6, 0.6), origin="lower", cmap="magma")
    ax.contour(gy, gz, mean, levels=[0.0], colors="cyan", linewidths=1)
    near = np.abs(scan.points[:, 0] - x0) < 0.01
    ax.scatter(scan.points[near, 1], scan.points[near, 2], s=3, c="white")
    ax.set_xlabel("y"), ax.set_ylabel("z")
    fig.colorbar(im, ax=ax, label="log10 variance")
    ax.set_title(f"variance on the slice x = {x0:.2f}\n(cyan: mean zero level; white: scan points within 0.01)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --- budget ----------------------------------------------------------------------------------------------------

def _budget_options(text):
    """The ``--options`` JSON object, its keys checked against ``LatentOptions`` (the trainer ignores unknown keys,
    so a typo would silently train the default)."""
    import dataclasses

    from autodecoder.latent.options import LatentOptions

    options = json.loads(text)
    if not isinstance(options, dict):
        raise SystemExit("--options must be a JSON object")
    unknown = sorted(set(options) - {f.name for f in dataclasses.fields(LatentOptions)})
    if unknown:
        raise SystemExit(f"--options: not LatentOptions fields: {', '.join(unknown)}")
    return options


def _budget(args):
    from benchmarks import inspect_api
    from benchmarks.baselines import nn_figures
    from benchmarks.cache import synth_collection, trained_model
    from benchmarks.table import verdicts_table

    options = _budget_options(args.options)
    name = args.name or (",".join(f"{k}={v}" for k, v in sorted(options.items())) or "defaults").replace("/", "_")
    work = Path(args.out or OUT["budget"]) / name
    rows, trained = [], []
    for seed in [int(s) for s in args.seeds.split(",")]:
        for part in args.parts.split(","):
            data = synth_collection(part, seed, root=args.cache)
            model = trained_model(data, root=args.cache, seed=seed, **options)
            info = inspect_api.model_info(model)
            trained.append({"part": part, "seed": seed, "model": str(model), "train_seconds": info["train_seconds"]})
            print(f"{part} seed {seed}: model {model} (training {info['train_seconds'] or float('nan'):.1f} s, "
                  f"{options or 'the defaults'})", flush=True)
            summary = inspect_api.calibrate_and_score(model, data, work / f"{data.parent.name}_s{seed}",
                                                      echo=lambda line, p=part: print(f"  {p}: {line}"))
            ours = inspect_api.summary_figures(summary)
            label = f"{part} s{seed}"
            rows.append({**ours, "part": label, "method": f"toolkit {ours['point_score']}/{ours['aggregate']}"
                         + (" +rays" if ours["rays"] else "")})
            rows.append({"part": label, **nn_figures(data, info["heldback_names"], ours["alpha"])})
    print(verdicts_table(rows))
    return {"name": name, "options": options, "trained": trained, "rows": rows}


# --- projection ------------------------------------------------------------------------------------------------

def _projection(args):
    import numpy as np
    import torch

    from autodecoder.latent.model import load_model
    from benchmarks.inspect_api import defaults
    from benchmarks.table import format_table
    from datasets import ScanCollection

    if not args.data or not args.models:
        raise SystemExit("--mode projection needs --data and --models")
    settings = defaults()["projection"]  # the inspection's own, batched as it does
    torch.set_num_threads(1)
    with ScanCollection(args.data) as c:
        scans = c.read_many(c.select(split="test")[:args.scans])
    models = [load_model(m) for m in args.models.split(",")]
    for m in models:  # warm-up
        m.project_many(scans[:2], seed=0, **settings)
    seconds = [[] for _ in models]
    for _ in range(args.repeats):
        for k, m in enumerate(models):
            t0 = time.perf_counter()
            m.project_many(scans, seed=0, **settings)
            seconds[k].append((time.perf_counter() - t0) / len(scans))
    rows = [{"model": m.source, "representation": m.representation, "fastest": min(s),
             "median": float(np.median(s))} for m, s in zip(models, seconds)]
    print(f"seconds per scan, {len(scans)} scans x {args.repeats} repeats, settings {settings}:")
    print(format_table(rows, [("model", "model", ""), ("representation", "representation", ""),
                              ("fastest", "fastest s/scan", ".3f"), ("median", "median s/scan", ".3f")]))
    return {"scans": len(scans), "repeats": args.repeats, "rows": rows}


def _defects(args):
    import numpy as np

    from benchmarks import inspect_api, metrics
    from benchmarks.table import format_table
    from benchmarks.trees import run_folders

    if not args.runs:
        raise SystemExit("--mode defects needs --runs")
    folders = run_folders(args.runs, args.match)
    if not folders:
        raise SystemExit(f"no run folder with model.pt and results/summary.json under {args.runs}")
    rows = []
    for folder in folders:
        data = Path(args.root) / json.loads((folder / "results" / "summary.json").read_text())["data"]
        try:
            scans = inspect_api.defect_projection(folder / "model.pt", data)
        except ValueError as e:
            print(f"skipped: {e}", flush=True)
            continue
        labels, defects = [s["label"] for s in scans], [s["defect"] for s in scans]
        name = f"{Path(data).parent.name}/{folder.name}"
        for key, what in (("own", "field, own code"), ("clean", "field, code from good points"),
                          ("no_variance", "field without its variance"), ("surface", "good points")):
            per = metrics.auroc_per_defect([s[key] for s in scans], labels, defects)
            row = {"run": name, "score": what, **per}
            if key in ("own", "clean"):
                row["at_defects"] = float(np.median([s["defect_" + key] for s in scans if "defect_" + key in s]))
            rows.append(row)
        print(f"{name}: field AUROC {rows[-4]['overall']:.3f} -> {rows[-3]['overall']:.3f} with a clean code, "
              f"{rows[-2]['overall']:.3f} without its variance (good points {rows[-1]['overall']:.3f})", flush=True)
    kinds = sorted({k for r in rows for k in r} - {"run", "score", "at_defects"}, key=lambda k: (k != "overall", k))
    print("\nobject AUROC (no rays) of the field's term with the code projected from the whole scan and from its good "
          "points alone, without the field's variance, and the good points' term; 'at defects': median field term at "
          "the defect points")
    print(format_table(rows, [("run", "run", ""), ("score", "score", "")] + [(k, k, ".3f") for k in kinds]
                       + [("at_defects", "at defects", ".2f")]))
    return {"rows": rows}
