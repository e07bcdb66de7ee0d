"""How good can NSSPR's mean surface be? The exact minimiser of the mean loss on a grid, against open3d.

Run by hand (not a test; about a minute per grid at 192^3 on 2 cores):

    .venv/bin/python benchmarks/target_limit.py [--h-factors 1,1.5,2] [--resolutions 128,192] [--regress-steps 5000]

``fit_cloud``'s mean net minimises the paper's mean loss

    E(g) = integral_B |mu(x) - grad g(x)|^2 dx + lambda_S mean_p g(p)^2

over SIRENs by Adam. This script minimises the same E over all functions on a regular grid of the same box B (the
model frame and the GP posterior mean mu of ``CloudTargets``, exactly as ``fit_cloud`` builds them): forward
differences along every grid edge against mu at the edge's midpoint, g(p) by trilinear interpolation. E is then a
positive-definite quadratic; its normal equations

    (delta sum_a D_a^T D_a + lambda_S / n W^T W) g = delta^2 sum_a D_a^T m_a

(delta the grid spacing, D_a the differences along axis a, m_a the edge values of mu_a, W the interpolation
matrix) are solved by conjugate gradients, preconditioned by the exact inverse of the first term (a Neumann
Laplacian, diagonal in the type-II DCT; the solver is ``autodecoder.grid_solve.grid_minimiser``). The zero level
set of the solution is what an infinitely expressive, perfectly trained mean net would give, up to the grid's discretisation (compare two resolutions). Its Chamfer
distance to the true mesh, next to open3d's screened Poisson (depth 8) of the same cloud, separates what the GP
target itself costs from what the network and its 4000 Adam steps add (``benchmarks/fandisk.py``).

With ``--regress-steps``, the default mean SIREN of ``fit_cloud`` is then fitted to that minimiser directly, by
supervised regression of its values and gradients (no Poisson problem left to solve: a much easier task than the
paper's loss sets it): how close a SIREN of this size gets to the exact answer in a given number of Adam steps.
"""
import argparse
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from autodecoder.fit import _cosine_lr
from autodecoder.frame import Normalization
from autodecoder.grid_solve import grid_minimiser
from autodecoder.losses import SCREENING_WEIGHT
from autodecoder.networks import MeanNet
from autodecoder.targets import CloudTargets, point_spacing
from fandisk import SHARED, chamfer, chamfer_by_edge_distance, open3d_poisson


def zero_level_mesh(g, lo, delta, normalization):
    """Marching cubes of g = 0 on the grid, in the cloud's own (world) coordinates."""
    verts, faces, _, _ = marching_cubes(g, level=0.0, spacing=(delta,) * 3)
    # marching cubes orients faces toward increasing values; g > 0 is outside, so this is already outward
    return trimesh.Trimesh(normalization.to_world(verts + lo), faces, process=False)


def regress_siren(g, lo, delta, targets, steps, seed=0, batch=256, near_fraction=0.9, lr=1e-3, width=64, depth=3,
                  omega0=30.0):
    """Fit a mean SIREN to the grid function g by Adam on values and gradients; returns the net.

    Samples: ``near_fraction`` of each batch within the kernel support of a cloud point (where the surface is), the
    rest uniform in the box. Loss: mean (net - g)^2 + h^2 mean |grad net - grad g|^2, g trilinear, its gradient by
    central differences over half a cell. Cosine learning-rate decay to 5 %, as ``fit_cloud``.
    """
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
            group["lr"] = lr * _cosine_lr(step, steps, 0.05)
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


def net_on_grid(net, shape, lo, delta):
    """The net's values at the grid's nodes -> array of ``shape``."""
    axes = [lo[a] + delta * np.arange(shape[a]) for a in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    with torch.no_grad():
        values = torch.cat([net(torch.from_numpy(chunk)) for chunk in np.array_split(x, 64)])
    return values.numpy().reshape(shape).astype(np.float64)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(SHARED / "fandisk.obj"))
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--h-factors", default="1,1.5,2", help="kernel lengthscale / point spacing")
    parser.add_argument("--resolutions", default="128,192", help="grid nodes per side")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--screening-weight", type=float, default=SCREENING_WEIGHT)
    parser.add_argument("--regress-steps", default="",
                        help="comma-separated Adam step counts: fit the mean SIREN to the finest grid's minimiser")
    args = parser.parse_args(argv)

    mesh = trimesh.load(args.mesh, force="mesh")
    points, faces = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)
    normals = mesh.face_normals[faces]
    diag = float(np.linalg.norm(mesh.extents))
    print(f"{Path(args.mesh).name}: {len(points)} points (seed {args.seed}), diagonal {diag:.4g}, "
          f"lambda_S {args.screening_weight:g}")
    t0 = time.perf_counter()
    o3d_mesh = open3d_poisson(points, normals)
    cd_o3d = chamfer(o3d_mesh, mesh)
    print(f"open3d Poisson d8: Chamfer {cd_o3d:.5f} ({time.perf_counter() - t0:.1f} s)")

    normalization = Normalization.fit(points)
    model_points = normalization.to_model(points)
    spacing = point_spacing(model_points)
    for factor in (float(f) for f in args.h_factors.split(",")):
        targets = CloudTargets(model_points, normals, factor * spacing)
        h_world = targets.lengthscale / normalization.scale
        for resolution in (int(r) for r in args.resolutions.split(",")):
            g, lo, delta, info = grid_minimiser(targets, resolution, args.screening_weight)
            surface = zero_level_mesh(g, lo, delta, normalization)
            cd = chamfer(surface, mesh)
            print(f"h = {factor:g} spacings ({h_world:.4g}), grid {resolution}^3 (h / cell {targets.lengthscale / delta:.1f}):"
                  f" Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x open3d;  CG {info['iterations']} it, residual "
                  f"{info['residual']:.1e}; targets {info['targets_seconds']:.0f} s, solve {info['solve_seconds']:.0f} s")
            bands_o3d = {row[0]: row for row in chamfer_by_edge_distance(o3d_mesh, mesh, h_world)}
            print("    true -> ours by distance to a sharp edge: " + ", ".join(
                f"{label} {mean:.5f} (open3d {bands_o3d[label][2]:.5f})"
                for label, _, mean, _ in chamfer_by_edge_distance(surface, mesh, h_world)))
        for steps in (int(k) for k in args.regress_steps.split(",") if k):
            t0 = time.perf_counter()
            net = regress_siren(g, lo, delta, targets, steps, seed=args.seed)
            seconds = time.perf_counter() - t0
            surface = zero_level_mesh(net_on_grid(net, g.shape, lo, delta), lo, delta, normalization)
            cd = chamfer(surface, mesh)
            print(f"    SIREN (fit_cloud's mean net) regressed on that minimiser, {steps} steps ({seconds:.0f} s):"
                  f" Chamfer {cd:.5f} = {cd / cd_o3d:.2f} x open3d")


if __name__ == "__main__":
    main()
