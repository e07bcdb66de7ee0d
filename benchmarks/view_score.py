"""How well does the next-best-view score rank cameras? Score vs the oracle coverage gain on a one-scan field.

The sequential benchmark (``next_view.py``) mixes the score with the search, the fine-tuning and the Chamfer
metric's noise, and takes ~15 minutes a seed. This one isolates the score, in ~2 minutes a seed: the one-scan field
of ``next_view.py`` (same first view, fit and seed) scores ``--cameras`` cameras spread evenly over the scanning
sphere, aimed at the part's centre; each camera is also scanned with the virtual scanner, and its oracle gain is the
fraction of its points farther than one kernel support (2 h) from the points already measured (the new surface it
would really see). Run by hand:

    .venv/bin/python benchmarks/view_score.py [--seed 0] [--cameras 200] [--outside-weight 100] [--spsr]

Prints the oracle gain by angle from the first view, then for each score variant the Spearman correlation of score
and gain, the angle and gain of its best camera, and the mean gain of its top 10 against the best 10 possible.
Variants: the library's scores (expected point or first-hit distribution, with or without novelty), and three that
replace the learned Var f at the expected hit: 1 (P(hit) x novelty alone), the learned variance of grad f, and with
``--spsr`` gpytoolbox's stochastic Poisson variance of the same scan (the exact discrete GP-Poisson variance, on a
20^3 grid): whether the learned variance or the score itself limits the ranking.
"""
import argparse
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from autodecoder import fit_cloud
from autodecoder.field.targets import point_spacing
from autodecoder.scanning.views import camera_score, part_sphere
from datasets.scanner import VirtualScanner
from fandisk import spsr_grid
from next_view import SHARED, WithoutVariance, fibonacci_sphere  # same folder: the sequential benchmark's camera
# sphere, and its field wrapper whose variance reads 1 (the score is then P(hit) x novelty)


class GradientVariance(WithoutVariance):
    """The field with Var f replaced by the variance of its gradient, tr D c(x, x) / 3 (unitless): the quantity the
    covariance loss fits directly (D c ~ Sigma I), free of the part of c that the mixed derivatives leave open."""

    def torch_variance(self, x):
        f = self._field
        model_x = f._model_x(x)
        dc = f.cov_net.d_operator(model_x, model_x, f._code_for(x))
        return torch.diagonal(dc, dim1=1, dim2=2).mean(1)


class GridVariance(WithoutVariance):
    """The field with Var f replaced by gpytoolbox's stochastic Poisson (SPSR) variance of the same scan on a
    grid over the field's box, trilinearly interpolated (no gradient: for scoring only). What the paper's score
    would be with the variance of the discrete GP-Poisson solve instead of the learned one."""

    def __init__(self, field, points, normals, grid=20):
        from gpytoolbox import stochastic_poisson_surface_reconstruction
        from scipy.interpolate import RegularGridInterpolator

        super().__init__(field)
        lo, hi = field.bounds
        gs, step, axes, self.grid_points = spsr_grid(lo, hi, grid)
        _, var, _ = stochastic_poisson_surface_reconstruction(points, normals, gs=gs, h=step, corner=lo,
                                                              output_variance=True, solve_subspace_dim=0)
        self.grid_var = np.ravel(var)
        self.interp = RegularGridInterpolator(axes, np.reshape(var, tuple(gs), order="F"), bounds_error=False,
                                              fill_value=None)

    def torch_variance(self, x):
        return torch.as_tensor(self.interp(x.detach().double().numpy()), dtype=x.dtype)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=SHARED / "fandisk.obj")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cameras", type=int, default=200)
    ap.add_argument("--points", type=int, default=3000, help="points of the first scan")
    ap.add_argument("--fit-steps", type=int, default=400)
    ap.add_argument("--features", type=int, default=64, help="rank of the feature covariance (next_view.py's 64)")
    ap.add_argument("--covariance", choices=("feature", "pair"), default="feature")
    ap.add_argument("--cov-screening", type=float, default=None, help="FitOptions.covariance_screening_weight")
    ap.add_argument("--outside-weight", type=float, default=0.0, help="FitOptions.outside_weight of the fit")
    ap.add_argument("--h-factor", type=float, default=2.0, help="kernel lengthscale / point spacing (next_view.py's)")
    ap.add_argument("--spsr", action="store_true",
                    help="also score with gpytoolbox's SPSR variance of the first scan (20^3 grid, minutes)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    mesh = trimesh.load(str(args.mesh), force="mesh")
    scanner = VirtualScanner(mesh)
    radius = 1.8 * scanner.diagonal
    # the first view and fit of next_view.py
    first = scanner.random_view(radius_range=(1.8, 1.8), seed=args.seed)
    scan0 = scanner.scan(first.camera_position, scanner.center, n_points=args.points, noise=0.0, seed=0)
    p0, n0 = scan0.points.astype(np.float64), scan0.normals.astype(np.float64)
    field = fit_cloud(p0, n0, representation="siren",
                      seed=args.seed, steps=args.fit_steps, quiet=True, width=64, depth=3,
                      lengthscale=args.h_factor * point_spacing(p0),
                      features=args.features, covariance=args.covariance,
                      mean_batch=2048, screen_batch=1024, pair_clusters=64, covariance_every=1, pool_passes=4,
                      average_decay=0.0, outside_weight=args.outside_weight,
                      covariance_screening_weight=args.cov_screening)
    s = 2.0 * float(field.config["lengthscale"]) / float(field.frame.scale)
    seen = torch.tensor(p0, dtype=torch.float32)

    dirs = fibonacci_sphere(args.cameras)
    u0 = (first.camera_position - scanner.center) / np.linalg.norm(first.camera_position - scanner.center)
    angle = np.degrees(np.arccos(np.clip(dirs @ u0, -1, 1)))
    tree = cKDTree(p0)
    gain = np.zeros(len(dirs))
    for k, d in enumerate(dirs):
        try:
            new = scanner.scan(scanner.center + radius * d, scanner.center, n_points=1000, noise=0.0, seed=k)
            gain[k] = np.mean(tree.query(new.points)[0] > s)
        except ValueError:  # nothing in view: no gain
            pass
    bands = [(a, float(gain[(angle >= a) & (angle < a + 45)].mean())) for a in (0, 45, 90, 135)]
    print(f"seed {args.seed}: oracle gain by angle from the first view: "
          + ", ".join(f"{a}-{a + 45} deg {g:.2f}" for a, g in bands))

    center, rad = part_sphere(field)
    pos = torch.tensor(center + dirs * 2.0 * rad, dtype=torch.float32)  # mid stand-off of next_best_views
    look = torch.tensor(center, dtype=torch.float32) - pos
    variants = {
        "expected-point + novelty (default)": (field, dict(observed=seen, observed_scale=s)),
        "expected-point, no novelty": (field, {}),
        "distribution + novelty": (field, dict(observed=seen, observed_scale=s, hit_summary="distribution")),
        "P(hit) x novelty, no variance": (WithoutVariance(field), dict(observed=seen, observed_scale=s)),
        "gradient variance + novelty": (GradientVariance(field), dict(observed=seen, observed_scale=s)),
        "gradient variance, no novelty": (GradientVariance(field), {}),
    }
    if args.spsr:
        spsr = GridVariance(field, p0, n0)
        rho = spearmanr(field.variance(spsr.grid_points), spsr.grid_var).statistic
        print(f"  Spearman of the learned variance with SPSR's on its grid: {rho:+.2f}")
        variants["SPSR variance + novelty"] = (spsr, dict(observed=seen, observed_scale=s))
        variants["SPSR variance, no novelty"] = (spsr, {})
    best10 = np.sort(gain)[-10:].mean()
    for name, (scored, kw) in variants.items():
        with torch.no_grad():
            score = torch.cat([camera_score(scored, pos[i:i + 50], look[i:i + 50], center, rad, **kw)
                               for i in range(0, len(pos), 50)]).double().numpy()
        top = np.argsort(-score)[:10]
        print(f"  {name:36s} Spearman(score, gain) {spearmanr(score, gain).statistic:+.2f}; best camera at "
              f"{angle[top[0]]:3.0f} deg, gain {gain[top[0]]:.2f}; top-10 mean gain {gain[top].mean():.2f} "
              f"(best 10: {best10:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
