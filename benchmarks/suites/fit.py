"""Single-cloud fits (``fit_cloud``): the grid default and the paper's SIRENs against open3d's screened Poisson, the
exact minimiser of the mean loss, the covariance loss's throughput, and real range scans.

Modes (``--mode``):

``grid`` (default)
    ``fit_cloud``'s default representation (``autodecoder/field/grid_fit.py``) on 20k points sampled on ``--mesh``
    (fandisk): per variant the fit time (of which the mean's CG solve), the Chamfer distance of the mean surface
    (marched at ``--resolution``) next to open3d's depth-8 screened Poisson of the same cloud, and the variance's
    Spearman correlation with gpytoolbox's stochastic Poisson variance on its 20^3 grid (without gpytoolbox: with
    ``--reference-field``'s variance). ``--variants`` are separated by ``;``, each a ``,``-separated list of
    ``key=value`` (empty: the defaults): ``GridFitOptions`` fields (``cov_steps``, ``mean_steps``, ...), ``h``
    (kernel lengthscale in point spacings), ``seed`` (of the fit alone; ``--seed`` also draws the points),
    ``mean.<key>`` / ``cov.<key>`` (``GridMeanNet`` / ``GridCovarianceNet`` settings, e.g. ``mean.finest=96``).
    This is also the sweep behind the grid's defaults.
``siren``
    The paper's SIRENs (``representation='siren'``) on the same cloud: fit time, Chamfer next to open3d, where the
    error lies (the true surface split into bands by distance to the nearest sharp edge, in kernel lengthscales),
    the variance's Spearman correlation with gpytoolbox's (when installed), and ``slice.png`` (mean, variance,
    P(inside)) in ``--out``.
``target-limit``
    What the mean loss itself allows: the exact minimiser of ``fit_cloud``'s mean loss on a grid
    (``autodecoder.field.grid_minimiser``: same GP posterior mean, box and lambda_S) per kernel lengthscale and grid
    resolution, its Chamfer next to open3d's; with ``--regress-steps`` a mean SIREN regressed directly onto that
    minimiser's values and gradients (how close a SIREN of this size gets in that many Adam steps).
``d-operator``
    Covariance-loss throughput, one training step (forward + backward to the parameters) on a clustered batch:
    (a) the pair SIREN's D c by plain autograd double backward, (b) by its forward-carried mixed jet
    (``PairCovarianceNet.d_operator``), (c) the feature covariance (``FeatureCovarianceNet``), which consumes all
    m (m - 1) ordered pairs of the batch through ``covariance_dirichlet_loss_features``. Columns: ms/step, pairs/s
    (loss terms consumed), points/s (network evaluations: 2 per pair for (a)/(b), 1 per point for (c)), the pairs/s
    ratio to (a), matmul GFLOP/step (from the operand shapes, ``torch.utils.flop_counter``; elementwise work not
    counted), GFLOP/s and the share of the fp32 matmul peak measured in the same run (torch.mm, 2048 x 2048).
``real-scans``
    ``fit_cloud``'s grid and SIREN at their defaults on single real range scans (the bunny's Cyberware views in
    ``../shared/realscans/bunny``, metres; stray returns removed, normals estimated toward a viewpoint 1 m along +z
    from the centroid): fit time, the scan's own points' distance to the mean surface (marched at 160^3, 400,000
    samples; mean and 95th percentile in median point spacings) and the field's noise level. A real scan has no true
    surface to compare with. Skipped, with a message, where the shared scans are absent.

The Chamfer distance is ``benchmarks.surface_metrics.mean_surface_distance`` throughout.
"""
import time
from pathlib import Path

from benchmarks.cache import CACHE
from benchmarks.surface_metrics import SPSR_GRID

DESCRIPTION = ("single-cloud fits: grid default and SIREN vs open3d's Poisson, the mean loss's exact minimiser, "
               "covariance-loss throughput, real range scans")
MODES = ("grid", "siren", "target-limit", "d-operator", "real-scans")
OUT = {"grid": "results/grid_fandisk", "siren": "results/fandisk"}


def _int_list(text):
    return [int(v) for v in text.split(",") if v.strip()]


def _float_list(text):
    return [float(v) for v in text.split(",") if v.strip()]


def add_arguments(parser):
    parser.add_argument("--mode", choices=MODES, default="grid", help="what to measure (default: %(default)s)")
    cloud = parser.add_argument_group("the sampled cloud (grid, siren, target-limit)")
    cloud.add_argument("--mesh", default="fandisk", help="fandisk, bunny, a built-in part or a mesh file")
    cloud.add_argument("--points", type=int, default=20_000)
    cloud.add_argument("--seed", type=int, default=0, help="draws the points and seeds the fits")
    cloud.add_argument("--resolution", type=int, default=192, help="marching-cubes grid of the mean surface")
    cloud.add_argument("--out", default=None, help=f"written files (default: {OUT})")
    cloud.add_argument("--cache", default=CACHE, help="gpytoolbox's variance solves (default: %(default)s)")
    grid = parser.add_argument_group("grid")
    grid.add_argument("--variants", default="", help="';'-separated variants (see the module docstring)")
    grid.add_argument("--reference-field", default=None,
                      help="field whose variance the Spearman correlation uses when gpytoolbox is not installed")
    siren = parser.add_argument_group("siren")
    siren.add_argument("--steps", type=int, default=None, help="Adam steps (default: fit_cloud's)")
    siren.add_argument("--width", type=int, default=None, help="SIREN width (default: fit_cloud's)")
    siren.add_argument("--depth", type=_int_list, default=None,
                       help="SIREN hidden layers (siren; default: fit_cloud's), or a list of sine-layer counts "
                            "(d-operator; default 3, the paper's 5: --depth 3,5)")
    siren.add_argument("--h-factor", type=float, default=None,
                       help="kernel lengthscale / point spacing (default: fit_cloud's)")
    siren.add_argument("--omega0", type=float, default=None, help="SIREN first-layer frequency (default: fit_cloud's)")
    siren.add_argument("--covariance-every", type=int, default=None,
                       help="one covariance step every this many mean steps (default: fit_cloud's)")
    siren.add_argument("--no-gpytoolbox", action="store_true", help="skip the variance's comparison")
    siren.add_argument("--quiet", action="store_true", help="no progress bar")
    siren.add_argument("--field", default=None, help="load this fitted field instead of fitting (e.g. the field.pt "
                       "an earlier run wrote)")
    limit = parser.add_argument_group("target-limit")
    limit.add_argument("--h-factors", type=_float_list, default=[1.0, 1.5, 2.0],
                       help="kernel lengthscales / point spacing (default: 1,1.5,2)")
    limit.add_argument("--resolutions", type=_int_list, default=[128, 192], help="grid nodes per side")
    limit.add_argument("--screening-weight", type=float, default=None, help="lambda_S (default: the library's)")
    limit.add_argument("--regress-steps", type=_int_list, default=[],
                       help="comma-separated Adam step counts: fit the mean SIREN to the finest grid's minimiser")
    throughput = parser.add_argument_group("d-operator")
    throughput.add_argument("--batch", type=int, default=512, help="points (feature net) / pairs (pair net) per step")
    throughput.add_argument("--widths", type=_int_list, default=[128, 256, 512])
    throughput.add_argument("--latent", type=_int_list, default=[0, 128], help="latent code dimensions (0: none)")
    throughput.add_argument("--features", type=int, default=128, help="K of the feature covariance")
    throughput.add_argument("--seconds", type=float, default=3.0, help="wall time per measurement")
    real = parser.add_argument_group("real-scans")
    real.add_argument("--views", default="bun000,bun090", help="comma-separated file stems in --source")
    real.add_argument("--source", default=None, help="folder of the scans (default: ../shared/realscans/bunny)")


def run(args):
    return {"grid": _grid, "siren": _siren, "target-limit": _target_limit, "d-operator": _d_operator,
            "real-scans": _real_scans}[args.mode](args)


# --- the sampled cloud and open3d's reconstruction of it ---------------------------------------------------------

def _cloud(args):
    """(mesh, points, normals, diagonal) of ``--points`` area-uniform samples of ``--mesh`` (seed ``--seed``)."""
    import numpy as np
    import torch
    import trimesh

    from benchmarks.cache import part_mesh

    mesh = part_mesh(args.mesh)
    points, faces = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)
    diag = float(np.linalg.norm(mesh.extents))
    print(f"{Path(args.mesh).stem}: {len(mesh.faces)} faces, {len(points)} points (seed {args.seed}), diagonal "
          f"{diag:.4g}, torch threads {torch.get_num_threads()}")
    return mesh, points, mesh.face_normals[faces], diag


def _open3d(mesh, points, normals):
    """open3d's depth-8 reconstruction, its Chamfer distance to ``mesh``, printed. Returns (its mesh, Chamfer)."""
    from benchmarks.surface_metrics import mean_surface_distance, open3d_poisson

    t0 = time.perf_counter()
    o3d_mesh = open3d_poisson(points, normals)
    seconds = time.perf_counter() - t0
    cd = mean_surface_distance(o3d_mesh, mesh)
    print(f"open3d Poisson d8: {seconds:5.1f} s, Chamfer {cd:.5f}")
    return o3d_mesh, cd


def chamfer_by_edge_distance(mesh_ours, mesh_true, lengthscale, n=30_000, seed=0, dihedral_deg=30.0):
    """Where the error is: the true surface's samples split by their distance to the nearest sharp edge (dihedral
    angle above ``dihedral_deg``), in kernel lengthscales.

    A kernel of lengthscale h rounds a sharp edge over about one h (the posterior mean is a smoothed normal field,
    so the Poisson solution is a smoothed indicator); ``--mode target-limit`` measures how much of the first band
    that rounding explains.

    Returns
    -------
    list of (band label, area share, mean distance to ``mesh_ours``, share of the one-sided (true -> ours) sum)
    """
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    samples = trimesh.sample.sample_surface(mesh_true, n, seed=seed)[0]
    dist = trimesh.proximity.closest_point(mesh_ours, samples)[1]
    sharp = mesh_true.face_adjacency_edges[mesh_true.face_adjacency_angles > np.radians(dihedral_deg)]
    if len(sharp) == 0:
        return []
    t = np.linspace(0, 1, 64)[None, :, None]
    seg = mesh_true.vertices[sharp]
    edge_points = (seg[:, :1] * (1 - t) + seg[:, 1:] * t).reshape(-1, 3)
    to_edge = cKDTree(edge_points).query(samples)[0] / lengthscale
    rows = []
    for lo, hi in ((0, 1), (1, 2), (2, 4), (4, np.inf)):
        band = (to_edge >= lo) & (to_edge < hi)
        label = f"[{lo}, {hi}) h" if np.isfinite(hi) else f">= {lo} h"
        rows.append((label, float(band.mean()), float(dist[band].mean()) if band.any() else float("nan"),
                     float(dist[band].sum() / dist.sum())))
    return rows


# --- the variance against gpytoolbox's stochastic Poisson reconstruction ---------------------------------------

def _has_gpytoolbox():
    import importlib.util

    return importlib.util.find_spec("gpytoolbox") is not None


def gpytoolbox_variance_correlation(field, points, normals, grid=SPSR_GRID, cache=CACHE):
    """Spearman correlation of the field's variance with gpytoolbox SPSR's on its grid over the field's box.

    gpytoolbox's solve takes minutes: it is cached in ``cache`` (``benchmarks.cache``, kind ``spsr``) by a digest of
    its inputs (the cloud, the box, the grid).

    Returns
    -------
    rho : float
    mean_rho : float
        Spearman of the two means: an ordering check (the grids' orders must match).
    seconds : float
        Of gpytoolbox's solve; 0 when it came from the cache.
    """
    import hashlib

    import numpy as np
    from scipy.stats import spearmanr

    from benchmarks.cache import cached_path
    from benchmarks.surface_metrics import spsr, spsr_grid

    lo, hi = field.bounds
    gs, _, _, grid_points = spsr_grid(lo, hi, grid)
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes()
                                     for a in (points, normals, lo, hi, gs))).hexdigest()[:16]
    solved = []

    def build(folder):
        t0 = time.perf_counter()
        mean, var = spsr(points, normals, lo, hi, grid)
        solved.append(time.perf_counter() - t0)
        np.savez(folder / "spsr.npz", mean=mean, var=var)

    folder = cached_path("spsr", {"inputs": digest, "grid": grid}, build, root=cache, label="gpytoolbox")
    with np.load(folder / "spsr.npz") as saved:
        mean, var = saved["mean"], saved["var"]
    rho = spearmanr(field.variance(grid_points), np.ravel(var)).statistic
    mean_rho = spearmanr(field.mean(grid_points), np.ravel(mean)).statistic
    return float(rho), float(mean_rho), solved[0] if solved else 0.0


def _variance_correlation(field, points, normals, reference, cache):
    """Spearman of the field's variance with gpytoolbox SPSR's (when installed) or with ``reference``'s (a
    StochasticField, or None: nan), on gpytoolbox's grid over the field's box."""
    from scipy.stats import spearmanr

    from benchmarks.surface_metrics import spsr_grid

    if _has_gpytoolbox():
        return gpytoolbox_variance_correlation(field, points, normals, cache=cache)[0]
    if reference is None:
        return float("nan")
    grid_points = spsr_grid(*field.bounds, SPSR_GRID)[3]
    return float(spearmanr(field.variance(grid_points), reference.variance(grid_points)).statistic)


# --- grid ------------------------------------------------------------------------------------------------------

def parse_variant(text):
    """'cov_steps=500,mean.finest=96,h=1.5' -> ({'cov_steps': 500}, {'finest': 96}, {}, {'h': 1.5})."""
    options, mean, cov, extra = {}, {}, {}, {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, value = item.split("=", 1)
        for kind in (int, float):
            try:
                value = kind(value)
                break
            except ValueError:
                pass
        if key.startswith("mean."):
            mean[key[5:]] = value
        elif key.startswith("cov."):
            cov[key[4:]] = value
        elif key in ("h", "seed"):
            extra[key] = value
        else:
            options[key] = value
    return options, mean, cov, extra


def _grid(args):
    from autodecoder import StochasticField
    from autodecoder.field.grid_fit import fit_grid_cloud
    from autodecoder.field.targets import point_spacing
    from benchmarks.surface_metrics import mean_surface_distance
    from benchmarks.table import format_table

    mesh, points, normals, diag = _cloud(args)
    spacing = point_spacing(points)
    _, cd_o3d = _open3d(mesh, points, normals)
    reference = None if args.reference_field is None else StochasticField.load(args.reference_field)
    against = "gpytoolbox SPSR" if _has_gpytoolbox() else "reference field" if reference is not None else "none"
    rows = []
    for text in args.variants.split(";"):
        options, mean, cov, extra = parse_variant(text)
        lengthscale = None if "h" not in extra else float(extra["h"]) * spacing
        field = fit_grid_cloud(points, normals, seed=extra.get("seed", args.seed), lengthscale=lengthscale,
                               grid_mean=mean, grid_cov=cov, **options)
        info = field.info
        cd = mean_surface_distance(field.mesh(args.resolution), mesh)
        rows.append({"settings": text or "defaults", "fit_seconds": info["fit_seconds"],
                     "solve_seconds": info["solve_seconds"], "cg_iterations": info["solve"].get("iterations", 0),
                     "chamfer": cd, "chamfer_over_open3d": cd / cd_o3d,
                     "spearman": _variance_correlation(field, points, normals, reference, args.cache)})
        print(f"{rows[-1]['settings']}: fit {info['fit_seconds']:.1f} s, Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x "
              f"open3d", flush=True)
    print(format_table(rows, [("settings", "settings", ""), ("fit_seconds", "fit s", ".1f"),
                              ("solve_seconds", "of which solve s", ".1f"), ("cg_iterations", "CG it", "d"),
                              ("chamfer", "Chamfer", ".5f"), ("chamfer_over_open3d", "/ open3d", ".2f"),
                              ("spearman", f"Spearman ({against})", ".3f")]))
    return {"mesh": args.mesh, "points": len(points), "diagonal": diag, "open3d_chamfer": cd_o3d,
            "spearman_against": against, "variants": rows}


# --- siren -----------------------------------------------------------------------------------------------------

def _siren(args):
    from autodecoder import StochasticField, fit_cloud
    from autodecoder.field.targets import point_spacing
    from benchmarks.surface_metrics import mean_surface_distance

    if args.depth is not None and len(args.depth) != 1:
        raise SystemExit("--mode siren: --depth takes one number of hidden layers")
    mesh, points, normals, diag = _cloud(args)
    out = Path(args.out or OUT["siren"])
    extra = {k: v for k, v in (("steps", args.steps), ("width", args.width),
                                ("depth", args.depth and args.depth[0]), ("omega0", args.omega0),
                                ("covariance_every", args.covariance_every)) if v is not None}
    if args.h_factor is not None:
        extra["lengthscale"] = args.h_factor * point_spacing(points)
    if args.field:
        field = StochasticField.load(args.field)
    else:
        field = fit_cloud(points, normals, representation="siren", seed=args.seed, quiet=args.quiet, **extra)
        field.save(out / "field.pt")
    ours = field.mesh(args.resolution)
    cd = mean_surface_distance(ours, mesh)
    o3d_mesh, cd_o3d = _open3d(mesh, points, normals)
    fit_seconds = field.info["fit_seconds"]
    print(f"NSSPR fit        : {fit_seconds:7.1f} s ({field.info['steps']} steps, width {field.config['width']}, "
          f"depth {field.config['depth']}), Chamfer {cd:.5f} ({cd / diag:.2e} of the diagonal)")
    print(f"Chamfer ratio NSSPR / open3d: {cd / cd_o3d:.2f} (open3d's: {cd_o3d / diag:.2e} of the diagonal)")
    h_world = field.config["lengthscale"] / field.frame.scale
    print(f"where the error is (true -> ours, kernel lengthscale h = {h_world:.4g}; distance to the nearest sharp "
          f"edge):")
    bands_o3d = {row[0]: row for row in chamfer_by_edge_distance(o3d_mesh, mesh, h_world)}
    bands = []
    for label, area, mean_dist, share in chamfer_by_edge_distance(ours, mesh, h_world):
        bands.append({"band": label, "area": area, "mean_distance": mean_dist, "share": share,
                      "open3d_mean_distance": bands_o3d[label][2], "open3d_share": bands_o3d[label][3]})
        print(f"  {label:>11}: {area:5.1%} of the surface, mean distance {mean_dist:.5f}, {share:5.1%} of the error"
              f"   (open3d: {bands_o3d[label][2]:.5f}, {bands_o3d[label][3]:5.1%})")
    figures = {"mesh": args.mesh, "points": len(points), "diagonal": diag, "fit_seconds": fit_seconds,
               "steps": field.info["steps"], "chamfer": cd, "open3d_chamfer": cd_o3d,
               "chamfer_over_open3d": cd / cd_o3d, "edge_bands": bands}
    if args.no_gpytoolbox:
        pass
    elif not _has_gpytoolbox():
        print("gpytoolbox is not installed (pip install -e '.[bench]'): no variance comparison")
    else:
        rho, mean_rho, seconds = gpytoolbox_variance_correlation(field, points, normals, cache=args.cache)
        spsr = "from the cache" if seconds == 0 else f"took {seconds:.1f} s"
        print(f"Spearman(variance, gpytoolbox SPSR variance on its {SPSR_GRID}^3 grid): {rho:.3f}  (SPSR {spsr};"
              f" Spearman of the two means, an ordering check: {mean_rho:.3f})")
        figures.update(spearman=rho, spearman_means=mean_rho)
    _slice_png(field, out / "slice.png")
    ours.export(out / "mean_surface.ply")
    print(f"wrote {out / 'slice.png'} and {out / 'mean_surface.ply'}")
    return figures


def _slice_png(field, path, resolution=200):
    """Mean, variance and P(inside) on the box's mid z slice, the mean's zero level drawn on each."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = field.bounds
    mid = 0.5 * (lo + hi)
    u = np.linspace(lo[0], hi[0], resolution)
    v = np.linspace(lo[1], hi[1], resolution)
    uu, vv = np.meshgrid(u, v, indexing="xy")
    x = np.stack([uu.ravel(), vv.ravel(), np.full(uu.size, mid[2])], -1)
    mean = field.mean(x).reshape(resolution, resolution)
    panels = [("mean g(x)", mean, "RdBu_r"), ("variance c(x, x)", field.variance(x), "viridis"),
              ("P(f(x) <= 0)", field.prob_inside(x), "magma")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for ax, (title, values, cmap) in zip(axes, panels):
        img = values.reshape(resolution, resolution)
        lim = np.abs(img).max()
        kwargs = {"vmin": -lim, "vmax": lim} if title.startswith("mean") else {}
        im = ax.imshow(img, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap=cmap, **kwargs)
        ax.contour(u, v, mean, levels=[0], colors="k", linewidths=0.8)
        ax.set_title(title + f"   (z = {mid[2]:.3g})")
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- target-limit ----------------------------------------------------------------------------------------------

def _target_limit(args):
    from autodecoder.field.grid_minimiser import grid_minimiser, zero_level_mesh
    from autodecoder.field.losses import SCREENING_WEIGHT
    from autodecoder.field.targets import CloudTargets, point_spacing
    from benchmarks.surface_metrics import mean_surface_distance
    from datasets.frame import Frame

    weight = SCREENING_WEIGHT if args.screening_weight is None else args.screening_weight
    mesh, points, normals, diag = _cloud(args)
    print(f"lambda_S {weight:g}")
    o3d_mesh, cd_o3d = _open3d(mesh, points, normals)
    frame = Frame.fit(points)
    model_points = frame.to_collection(points)
    spacing = point_spacing(model_points)
    rows = []
    for factor in args.h_factors:
        targets = CloudTargets(model_points, normals, factor * spacing)
        h_world = targets.lengthscale / frame.scale
        bands_o3d = {row[0]: row for row in chamfer_by_edge_distance(o3d_mesh, mesh, h_world)}
        for resolution in args.resolutions:
            g, lo, delta, info = grid_minimiser(targets, resolution, weight)
            surface = zero_level_mesh(g, lo, delta, frame)
            cd = mean_surface_distance(surface, mesh)
            bands = chamfer_by_edge_distance(surface, mesh, h_world)
            rows.append({"h_factor": factor, "resolution": resolution, "chamfer": cd,
                         "chamfer_over_open3d": cd / cd_o3d, "cg_iterations": info["iterations"],
                         "bands": {label: mean for label, _, mean, _ in bands}})
            print(f"h = {factor:g} spacings ({h_world:.4g}), grid {resolution}^3 (h / cell "
                  f"{targets.lengthscale / delta:.1f}): Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x open3d;  CG "
                  f"{info['iterations']} it, residual {info['residual']:.1e}; targets {info['targets_seconds']:.0f} s, "
                  f"solve {info['solve_seconds']:.0f} s")
            print("    true -> ours by distance to a sharp edge: " + ", ".join(
                f"{label} {mean:.5f} (open3d {bands_o3d[label][2]:.5f})" for label, _, mean, _ in bands))
        for steps in args.regress_steps:
            t0 = time.perf_counter()
            net = _regress_siren(g, lo, delta, targets, steps, seed=args.seed)
            seconds = time.perf_counter() - t0
            cd = mean_surface_distance(zero_level_mesh(_net_on_grid(net, g.shape, lo, delta), lo, delta, frame), mesh)
            rows.append({"h_factor": factor, "resolution": resolution, "regress_steps": steps, "chamfer": cd,
                         "chamfer_over_open3d": cd / cd_o3d, "seconds": seconds})
            print(f"    SIREN (fit_cloud's mean net) regressed on that minimiser, {steps} steps ({seconds:.0f} s):"
                  f" Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x open3d")
    return {"mesh": args.mesh, "points": len(points), "screening_weight": weight, "open3d_chamfer": cd_o3d,
            "rows": rows}


def _regress_siren(g, lo, delta, targets, steps, seed=0, batch=256, near_fraction=0.9, lr=1e-3, width=64, depth=3,
                   omega0=30.0):
    """Fit a mean SIREN to the grid function g by Adam on values and gradients; returns the net.

    Samples: ``near_fraction`` of each batch within the kernel support of a cloud point (where the surface is), the
    rest uniform in the box. Loss: mean (net - g)^2 + h^2 mean |grad net - grad g|^2, g trilinear, its gradient by
    central differences over half a cell. Cosine learning-rate decay to 5 %, as ``fit_cloud``.
    """
    import numpy as np
    import torch
    from scipy.ndimage import map_coordinates

    from autodecoder.field.networks import MeanNet
    from autodecoder.field.schedule import cosine_decay

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = MeanNet(width=width, depth=depth, omega0=omega0)
    opt = torch.optim.Adam(net.parameters(), lr=lr, fused=True)
    points, box, reach = targets.posterior.points, targets.box, targets.posterior.radius
    h = targets.lengthscale

    def grid_value(x):
        return map_coordinates(g, ((x - lo) / delta).T, order=1, mode="nearest")

    eps = 0.5 * delta
    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = lr * cosine_decay(step, steps, 0.05)
        n_near = int(batch * near_fraction)
        x = np.concatenate([points[rng.integers(0, len(points), n_near)] + rng.uniform(-reach, reach, (n_near, 3)),
                            box.uniform(batch - n_near, rng)])
        value = torch.from_numpy(grid_value(x).astype(np.float32))
        grad = np.stack([(grid_value(x + eps * e) - grid_value(x - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
        net_value, net_grad = net.value_and_gradient(torch.from_numpy(x.astype(np.float32)))
        loss = ((net_value - value) ** 2).mean() + h**2 * ((net_grad - torch.from_numpy(grad.astype(np.float32))) ** 2
                                                           ).sum(1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return net.eval()


def _net_on_grid(net, shape, lo, delta):
    """The net's values at the grid's nodes -> array of ``shape``."""
    import numpy as np
    import torch

    axes = [lo[a] + delta * np.arange(shape[a]) for a in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    with torch.no_grad():
        values = torch.cat([net(torch.from_numpy(chunk)) for chunk in np.array_split(x, 64)])
    return values.numpy().reshape(shape).astype(np.float64)


# --- d-operator ------------------------------------------------------------------------------------------------

def _d_operator(args):
    import os
    import platform

    import torch

    from benchmarks.table import format_table

    if args.batch % 8:
        raise SystemExit("--batch must be a multiple of 8 (clusters of 8)")
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, {platform.processor() or platform.machine()}"
          f", cpus {os.cpu_count()}")
    peak = _matmul_peak(args.seconds)
    print(f"fp32 matmul peak (torch.mm 2048x2048): {peak:.1f} GFLOP/s; batch {args.batch}, K = {args.features}, "
          f"{args.seconds:g} s per measurement; pairs/s = loss terms consumed per second; x(a) = pairs/s ratio to (a)")
    rows = []
    for depth in args.depth or [3]:
        for width in args.widths:
            for latent in args.latent:
                base = None
                for name, step, pairs, points in _covariance_steps(width, depth, latent, args.batch, args.features):
                    gflop = _matmul_flops(step) / 1e9  # also the first warm-up call
                    sec = _time_loop(step, args.seconds, warmup=1)
                    base = base or pairs / sec
                    rows.append({"depth": depth, "width": width, "latent": latent, "method": name,
                                 "ms_per_step": sec * 1e3, "pairs_per_s": pairs / sec, "points_per_s": points / sec,
                                 "ratio": pairs / sec / base, "gflop_per_step": gflop, "gflop_per_s": gflop / sec,
                                 "peak_percent": 100 * gflop / sec / peak})
                    print(f"  {depth} x {width}, latent {latent}, {name}: {sec * 1e3:.2f} ms/step", flush=True)
    print(format_table(rows, [("depth", "depth", "d"), ("width", "width", "d"), ("latent", "latent", "d"),
                              ("method", "method", ""), ("ms_per_step", "ms/step", ".2f"),
                              ("pairs_per_s", "pairs/s", ".4g"), ("points_per_s", "points/s", ".4g"),
                              ("ratio", "x(a)", ".3g"), ("gflop_per_step", "GFLOP/step", ".3f"),
                              ("gflop_per_s", "GFLOP/s", ".1f"), ("peak_percent", "%peak", ".1f")]))
    return {"matmul_peak_gflops": peak, "batch": args.batch, "features": args.features, "rows": rows}


def _time_loop(step, seconds, warmup=2, min_calls=2):
    """Mean seconds per call of ``step`` over ~``seconds`` of wall time (at least ``min_calls``), after warm-up."""
    for _ in range(warmup):
        step()
    n, start = 0, time.perf_counter()
    while True:
        step()
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds and n >= min_calls:
            return elapsed / n


def _matmul_peak(seconds):
    """fp32 GFLOP/s of torch.mm on 2048 x 2048 matrices."""
    import torch

    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    out = torch.empty(2048, 2048)
    return 2 * 2048**3 / _time_loop(lambda: torch.mm(a, b, out=out), seconds) / 1e9


def _matmul_flops(step):
    """Matmul FLOPs of one call of ``step`` (forward and backward), from the operands' shapes: 2 m n k per
    (m, k) @ (k, n) product (``torch.utils.flop_counter``); elementwise work is not counted."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        step()
    return counter.get_total_flops()


def _d_operator_autograd(net, a, b, z):
    """(a): d2 c / da_k db_l by plain autograd double backward, differentiable to the parameters."""
    import torch

    a = a.detach().requires_grad_(True)
    b = b.detach().requires_grad_(True)
    c = net.covariance(a, b, z)
    ga = torch.autograd.grad(c.sum(), a, create_graph=True)[0]  # (P, 3)
    rows = [torch.autograd.grad(ga[:, k].sum(), b, create_graph=True)[0] for k in range(3)]
    return torch.stack(rows, 1)  # (P, 3, 3)


def _covariance_steps(width, depth, latent, batch, features, seed=0):
    """The three step functions (forward + backward of the covariance loss) on one batch drawn in clusters of 8
    (``sample_pair_clusters``), as (method, step, pairs per step, network points per step)."""
    import numpy as np
    import torch

    from autodecoder.field.losses import covariance_dirichlet_loss_features, covariance_dirichlet_loss_pairs
    from autodecoder.field.networks import FeatureCovarianceNet, PairCovarianceNet
    from autodecoder.field.sampling import Box, sample_pair_clusters

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    x, w = sample_pair_clusters(Box(np.zeros(3), np.ones(3)), batch // 8, 8, 0.08, rng)
    x = torch.from_numpy(x)
    m = len(x)
    # explicit pairs for (a)/(b): each point with another member of its cluster (the informative pairs)
    partner = np.arange(m) + 1 - 2 * (np.arange(m) % 2)  # 0<->1, 2<->3, ...: within the same cluster of 8
    a, b = x, x[torch.from_numpy(partner)]
    sigma_pairs = torch.rand(m)
    w_pairs = torch.from_numpy(w[np.arange(m), partner])
    sigma_all = torch.rand(1, m, m)
    sigma_all = 0.5 * (sigma_all + sigma_all.transpose(1, 2))
    w_all = torch.from_numpy(w)[None]

    pair_net = PairCovarianceNet(width, depth, latent_dim=latent)
    feat_net = FeatureCovarianceNet(width, depth, features=features, latent_dim=latent)
    z = torch.randn(latent, requires_grad=True) if latent else None

    def clear(net):
        net.zero_grad(set_to_none=True)
        if z is not None:
            z.grad = None

    def step_autograd():
        clear(pair_net)
        covariance_dirichlet_loss_pairs(_d_operator_autograd(pair_net, a, b, z), sigma_pairs, w_pairs).backward()

    def step_jet():
        clear(pair_net)
        covariance_dirichlet_loss_pairs(pair_net.d_operator(a, b, z), sigma_pairs, w_pairs).backward()

    def step_feature():
        clear(feat_net)
        _, jac = feat_net.features_and_jacobian(x, z)  # (m, 3, K)
        covariance_dirichlet_loss_features(jac[None], sigma_all, w_all).backward()

    return [("(a) autograd", step_autograd, m, 2 * m), ("(b) mixed-jet", step_jet, m, 2 * m),
            ("(c) feature", step_feature, m * (m - 1), m)]


# --- real-scans ------------------------------------------------------------------------------------------------

def _real_scans(args):
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    from benchmarks.cache import REAL_SCANS
    from benchmarks.table import format_table

    source = Path(args.source) if args.source else REAL_SCANS / "bunny"
    if not source.is_dir():
        print(f"fit --mode real-scans: skipped, {source} not found (the real scans are shared data, not in the "
              f"repository)")
        return {"skipped": f"{source} not found"}
    from autodecoder import fit_cloud
    from datasets.normals import estimate_normals
    from datasets.outliers import stray_points

    rows = []
    for view in args.views.split(","):
        path = source / f"{view}.ply"
        if not path.is_file():
            raise SystemExit(f"{path}: no such scan")
        points = np.asarray(trimesh.load(path).vertices, dtype=np.float64)
        points = points[~stray_points(points)]
        normals = estimate_normals(points, sensor_origin=points.mean(0) + np.array([0.0, 0.0, 1.0]))
        spacing = float(np.median(cKDTree(points).query(points, 2)[0][:, 1]))
        for representation in ("grid", "siren"):
            t0 = time.perf_counter()
            field = fit_cloud(points, normals, representation=representation, quiet=True)
            seconds = time.perf_counter() - t0
            surface = trimesh.sample.sample_surface(field.mesh(160), 400_000, seed=0)[0]
            d = cKDTree(surface).query(points)[0] / spacing
            rows.append({"view": view, "representation": representation, "points": len(points),
                         "fit_seconds": seconds, "mean_spacings": float(d.mean()),
                         "q95_spacings": float(np.quantile(d, 0.95)), "noise_spacings": field.noise / spacing})
            print(f"  {view} {representation}: fit {seconds:.1f} s", flush=True)
    print("scan points to the mean surface, in median point spacings:")
    print(format_table(rows, [("view", "view", ""), ("representation", "fit", ""), ("points", "points", "d"),
                              ("fit_seconds", "fit s", ".1f"), ("mean_spacings", "mean", ".2f"),
                              ("q95_spacings", "95 %", ".2f"), ("noise_spacings", "field noise", ".2f")]))
    return {"source": str(source), "rows": rows}
