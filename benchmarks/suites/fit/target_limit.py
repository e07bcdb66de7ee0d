"""``fit --mode target-limit``: what the mean loss itself allows. The exact minimiser of ``fit_cloud``'s mean loss on
a grid (``autodecoder.field.grid_minimiser``: same GP posterior mean, box and lambda_S) per kernel lengthscale and
grid resolution, its Chamfer next to open3d's; with ``--regress-steps`` a mean SIREN regressed directly onto that
minimiser's values and gradients (how close a SIREN of this size gets in that many Adam steps)."""
import time

from benchmarks.suites.fit.cloud import chamfer_by_edge_distance, open3d_reference, sampled_cloud


def run(args):
    """The minimisers' (and regressed SIRENs') table; returns the figures."""
    from autodecoder.field.grid_minimiser import grid_minimiser, zero_level_mesh
    from autodecoder.field.losses import SCREENING_WEIGHT
    from autodecoder.field.targets import CloudTargets, point_spacing
    from benchmarks.surface_metrics import mean_surface_distance
    from datasets.frame import Frame

    weight = SCREENING_WEIGHT if args.screening_weight is None else args.screening_weight
    mesh, points, normals, diag = sampled_cloud(args)
    print(f"lambda_S {weight:g}")
    o3d_mesh, cd_o3d = open3d_reference(mesh, points, normals)
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

    from autodecoder.field.siren import MeanNet
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
