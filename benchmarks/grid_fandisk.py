"""Grid networks (autodecoder/field/grid_fit.py) on fandisk: fit time, Chamfer next to open3d, variance vs a reference.

Run by hand (not a test):

    OMP_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/grid_fandisk.py \\
        --variants ";mean.finest=96;h=1.5,cov_steps=500" [--reference-field results/fandisk/field.pt]

Variants are separated by ``;``, each a ``,``-separated list of ``key=value`` settings (empty: the defaults):
:class:`GridFitOptions` fields (``cov_steps``, ``mean_steps``, ``solve=0``, ...), ``h`` (kernel lengthscale in
point spacings), ``seed`` (of the fit alone; ``--seed`` also draws the points) and ``mean.<key>`` /
``cov.<key>`` (settings of :class:`GridMeanNet` / :class:`GridCovarianceNet`, e.g. ``mean.finest=96``,
``cov.channels=16``). open3d's screened Poisson (depth 8) of the same cloud is measured
once in the same run; the Chamfer distance is ``surface_metrics.mean_surface_distance`` for both, of the mean surface marched at 192^3.

The variance is compared by Spearman rank correlation on gpytoolbox's 20^3 SPSR grid over the field's box: with
gpytoolbox's stochastic Poisson variance when gpytoolbox is installed (``fandisk.py``'s measure), else with the
variance of ``--reference-field`` (a field written by ``benchmarks/fandisk.py``, e.g. the SIREN fit, whose own
correlation with gpytoolbox is in docs/results.md).
"""
import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
import numpy as np
import torch
import trimesh

from scipy.stats import spearmanr

from autodecoder import StochasticField
from autodecoder.field.grid_fit import fit_grid_cloud
from autodecoder.field.targets import point_spacing
from fandisk import SHARED, gpytoolbox_variance_correlation, open3d_poisson, spsr_grid
from surface_metrics import mean_surface_distance


def parse_variant(text):
    """'cov_steps=500,mean.finest=96,h=1.5' -> ({'cov_steps': 500}, {'finest': 96}, {}, {'h': 1.5})."""
    options, mean, cov, extra = {}, {}, {}, {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, value = item.split("=", 1)
        try:
            value = int(value)
        except ValueError:
            try:
                value = float(value)
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


def _has_gpytoolbox():
    import importlib.util

    return importlib.util.find_spec("gpytoolbox") is not None


def variance_correlation(field, points, normals, reference, cache_dir):
    """Spearman correlation of the field's variance with gpytoolbox SPSR's (when installed) or with ``reference``'s
    (a StochasticField, or None: nan), on gpytoolbox's 20^3 grid over the field's box."""
    if _has_gpytoolbox():
        return gpytoolbox_variance_correlation(field, points, normals, cache_dir=cache_dir)[0]
    if reference is None:
        return float("nan")
    grid_points = spsr_grid(*field.bounds, 20)[3]
    return float(spearmanr(field.variance(grid_points), reference.variance(grid_points)).statistic)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(SHARED / "fandisk.obj"))
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--variants", default="", help="';'-separated variants (see the module docstring)")
    parser.add_argument("--resolution", type=int, default=192, help="marching-cubes grid of the mean surface")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reference-field", default=None,
                        help="field whose variance the Spearman correlation uses when gpytoolbox is not installed")
    parser.add_argument("--out", default="results/grid_fandisk")
    args = parser.parse_args(argv)

    mesh = trimesh.load(args.mesh, force="mesh")
    points, faces = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)
    normals = mesh.face_normals[faces]
    diag = float(np.linalg.norm(mesh.extents))
    spacing = point_spacing(points)
    print(f"{Path(args.mesh).name}: {len(points)} points (seed {args.seed}), diagonal {diag:.4g}, "
          f"torch threads {torch.get_num_threads()}")
    t0 = time.perf_counter()
    cd_o3d = mean_surface_distance(open3d_poisson(points, normals), mesh)
    print(f"open3d Poisson d8: Chamfer {cd_o3d:.5f} ({time.perf_counter() - t0:.1f} s)")
    reference = None if args.reference_field is None else StochasticField.load(args.reference_field)
    against = "gpytoolbox SPSR" if _has_gpytoolbox() else "reference field" if reference is not None else "none"
    rows = []
    for text in args.variants.split(";"):
        options, mean, cov, extra = parse_variant(text)
        lengthscale = extra.get("h", None)
        lengthscale = None if lengthscale is None else float(lengthscale) * spacing
        field = fit_grid_cloud(points, normals, seed=extra.get("seed", args.seed), lengthscale=lengthscale,
                               grid_mean=mean, grid_cov=cov, **options)
        info = field.info
        cd = mean_surface_distance(field.mesh(args.resolution), mesh)
        rho = variance_correlation(field, points, normals, reference, args.out)
        rows.append((text or "defaults", info["fit_seconds"], info["solve_seconds"], cd, cd / cd_o3d, rho))
        print(f"{text or 'defaults':50s} fit {info['fit_seconds']:5.1f} s (solve {info['solve_seconds']:.1f} s, CG "
              f"{info['solve'].get('iterations', 0)} it)  Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x open3d  "
              f"Spearman {rho:.3f}", flush=True)
    print(f"\n| settings | fit s | of which solve s | Chamfer | / open3d | Spearman ({against}) |\n|---|---|---|---|---|---|")
    for text, seconds, solve, cd, ratio, rho in rows:
        print(f"| {text} | {seconds:.1f} | {solve:.1f} | {cd:.5f} | {ratio:.2f} | {rho:.3f} |")


if __name__ == "__main__":
    main()
