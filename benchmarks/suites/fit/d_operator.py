"""``fit --mode d-operator``: the covariance loss's throughput, one training step (forward + backward to the
parameters) on a clustered batch: (a) the pair SIREN's D c by plain autograd double backward, (b) by its
forward-carried mixed jet (``PairCovarianceNet.d_operator``), (c) the feature covariance (``FeatureCovarianceNet``),
which consumes all m (m - 1) ordered pairs of the batch through ``covariance_dirichlet_loss_features``.

Columns: ms/step, pairs/s (loss terms consumed), points/s (network evaluations: 2 per pair for (a)/(b), 1 per point
for (c)), the pairs/s ratio to (a), matmul GFLOP/step (from the operand shapes, ``torch.utils.flop_counter``;
elementwise work not counted), GFLOP/s and the share of the fp32 matmul peak measured in the same run (torch.mm,
2048 x 2048).
"""
import time


def run(args):
    """The throughput table; returns the figures."""
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
    from autodecoder.field.siren import FeatureCovarianceNet, PairCovarianceNet
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
