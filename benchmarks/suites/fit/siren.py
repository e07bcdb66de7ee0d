"""``fit --mode siren``: the paper's SIRENs (``representation='siren'``) on a sampled cloud: fit time, Chamfer next
to open3d, where the error lies (the true surface split into bands by distance to the nearest sharp edge, in kernel
lengthscales), the variance's Spearman correlation with gpytoolbox's (when installed), and ``slice.png`` (mean,
variance, P(inside)) in ``--out``."""
from pathlib import Path

from benchmarks.suites.fit.cloud import (OUT, chamfer_by_edge_distance, gpytoolbox_variance_correlation,
                                         has_gpytoolbox, open3d_reference, sampled_cloud)
from benchmarks.surface_metrics import SPSR_GRID


def run(args):
    """Fit (or load ``--field``), compare, write the slice and the mean surface; returns the figures."""
    from autodecoder import StochasticField, fit_cloud
    from autodecoder.field.targets import point_spacing
    from benchmarks.surface_metrics import mean_surface_distance

    if args.depth is not None and len(args.depth) != 1:
        raise SystemExit("--mode siren: --depth takes one number of hidden layers")
    mesh, points, normals, diag = sampled_cloud(args)
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
    o3d_mesh, cd_o3d = open3d_reference(mesh, points, normals)
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
    elif not has_gpytoolbox():
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
