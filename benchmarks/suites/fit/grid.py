"""``fit --mode grid``: ``fit_cloud``'s default representation (``autodecoder/field/grid_fit.py``) on a sampled
cloud, per variant: the fit time (of which the mean's CG solve), the Chamfer distance of the mean surface next to
open3d's, and the variance's Spearman correlation with gpytoolbox's stochastic Poisson variance (without gpytoolbox:
with ``--reference-field``'s variance). The sweep behind the grid's defaults.

``--variants`` are separated by ``;``, each a ``,``-separated list of ``key=value`` (empty: the defaults):
``GridFitOptions`` fields (``cov_steps``, ``mean_steps``, ...), ``h`` (kernel lengthscale in point spacings),
``seed`` (of the fit alone; ``--seed`` also draws the points), ``mean.<key>`` / ``cov.<key>`` (``GridMeanNet`` /
``GridCovarianceNet`` settings, e.g. ``mean.finest=96``).
"""
from benchmarks.suites.fit.cloud import has_gpytoolbox, open3d_reference, sampled_cloud, variance_correlation


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


def run(args):
    """The variants' table; returns the figures."""
    from autodecoder import StochasticField
    from autodecoder.field.grid_fit import fit_grid_cloud
    from autodecoder.field.targets import point_spacing
    from benchmarks.surface_metrics import mean_surface_distance
    from benchmarks.table import format_table

    mesh, points, normals, diag = sampled_cloud(args)
    spacing = point_spacing(points)
    _, cd_o3d = open3d_reference(mesh, points, normals)
    reference = None if args.reference_field is None else StochasticField.load(args.reference_field)
    against = "gpytoolbox SPSR" if has_gpytoolbox() else "reference field" if reference is not None else "none"
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
                     "spearman": variance_correlation(field, points, normals, reference, args.cache)})
        print(f"{rows[-1]['settings']}: fit {info['fit_seconds']:.1f} s, Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x "
              f"open3d", flush=True)
    print(format_table(rows, [("settings", "settings", ""), ("fit_seconds", "fit s", ".1f"),
                              ("solve_seconds", "of which solve s", ".1f"), ("cg_iterations", "CG it", "d"),
                              ("chamfer", "Chamfer", ".5f"), ("chamfer_over_open3d", "/ open3d", ".2f"),
                              ("spearman", f"Spearman ({against})", ".3f")]))
    return {"mesh": args.mesh, "points": len(points), "diagonal": diag, "open3d_chamfer": cd_o3d,
            "spearman_against": against, "variants": rows}
