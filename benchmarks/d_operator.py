"""Covariance-loss throughput: autograd double backward vs forward-carried jets vs the feature-map covariance.

Run by hand (CPU; a few minutes with the defaults):

    .venv/bin/python benchmarks/d_operator.py                      # batch 512, widths 128,256,512, latent 0,128
    .venv/bin/python benchmarks/d_operator.py --depth 3,5 --seconds 2

One training step of the covariance Dirichlet loss (forward + backward to all parameters, and to the latent code
when there is one) is timed for three methods on a batch of 512 points drawn in clusters (64 clusters of 8,
:func:`autodecoder.field.sampling.sample_pair_clusters`):

(a) ``autograd``: the paper's pair network c(a, b) = (SoftPlus(h(a, b)) + SoftPlus(h(b, a))) / 2
    (:class:`PairCovarianceNet`, a SIREN on [x1, x2]); D c by plain autograd: grad of c w.r.t. a with
    create_graph=True, then grad of each of its 3 components w.r.t. b with create_graph=True, then the loss
    :func:`covariance_dirichlet_loss_pairs` and ``backward()``. 512 explicit pairs per step.
(b) ``mixed-jet``: the same network, D c from :meth:`PairCovarianceNet.d_operator` (forward-carried mixed jet).
    512 explicit pairs per step.
(c) ``feature``: :class:`FeatureCovarianceNet` (same width/depth, K = 128 features): Jacobians of the 512 points
    from the order-1 jet, then :func:`covariance_dirichlet_loss_features`, which consumes all m (m - 1) = 261,632
    ordered pairs of the batch (the far pairs through the K x K matrix sum_i J_i J_i^T, the few pairs within the
    kernel's support gathered one by one; before stop 9 it formed the Gram matrix of all pairs). Reported both as pairs/s (what the loss consumes) and as
    points/s (network evaluations), since a pair of the feature net is much cheaper than a pair of (a)/(b).

Columns: ms/step; pairs/s; points/s (points pushed through the network: 2 per pair for (a)/(b) -- each pair
evaluates h at (a, b) and (b, a) -- and 1 per point for (c)); the ratio of pairs/s to (a); GFLOP/step; GFLOP/s; and
the fraction of the fp32 matmul peak measured in the same run (torch.mm of two 2048 x 2048 fp32 matrices repeated,
2 * 2048^3 FLOPs each).

FLOPs per step count matrix multiplies only (2 m n k for an (m, k) @ (k, n) product), read from the exact matmul
shapes of one step by ``torch.utils.flop_counter.FlopCounterMode`` (aten::mm / addmm / bmm, forward and
backward). The elementwise sines etc. are not counted. For reference, the analytic forward counts (B = 512, W
width, d depth = number of sine layers, L latent, a latent code (L,) shared by the batch costs only 2 L W):

    (b) mixed jet, 2B rows (both orders), 16 channels each:  2 (2B) 6 W + (d - 1) 2 (16 * 2B) W^2 + 2 (16 * 2B) W
    (c) order-1 jet, B rows, 4 channels each:                2 B 3 W + (d - 1) 2 (4B) W^2 + 2 (4B) W K
        + sum_i J_i J_i^T of the (3B, K) stacked Jacobians:  2 (3B) K^2   (the Gram matrix was 2 (3B)^2 K)
    (a) forward 2 (2B) 6 W + (d - 1) 2 (2B) W^2 + 2 (2B) W, then one create_graph backward and three more
        backwards through that graph, each roughly 1-2x the forward.

and the backward to parameters roughly doubles each matmul count (one product for the input gradient, one for the
weight gradient): a step is ~3x its forward.

The CPU may be shared: the 1/5/15-minute load averages are printed at the start and at the end.
"""
import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from autodecoder.field.losses import covariance_dirichlet_loss_features, covariance_dirichlet_loss_pairs  # noqa: E402
from autodecoder.field.networks import FeatureCovarianceNet, PairCovarianceNet  # noqa: E402
from autodecoder.field.sampling import Box, sample_pair_clusters  # noqa: E402


def int_list(text):
    return [int(v) for v in text.split(",") if v.strip()]


def loadavg():
    try:
        return "load average: " + ", ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "load average: n/a"


def time_loop(step, seconds, warmup=2, min_calls=2):
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


def matmul_peak(seconds):
    """fp32 GFLOP/s of torch.mm on 2048 x 2048 matrices."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    out = torch.empty(2048, 2048)
    per_call = time_loop(lambda: torch.mm(a, b, out=out), seconds)
    return 2 * 2048**3 / per_call / 1e9


def count_matmul_flops(step):
    """Matmul FLOPs of one call of ``step`` (forward and backward), from the operands' shapes.

    torch.utils.flop_counter.FlopCounterMode counts 2 m n k per (m, k) @ (k, n) product for aten::mm, addmm, bmm,
    baddbmm and the matmuls inside convolutions/attention (none here); elementwise work is not counted. The call
    doubles as the first warm-up call.
    """
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        step()
    return counter.get_total_flops()


def d_operator_autograd(net, a, b, z):
    """(a): d2 c / da_k db_l by plain autograd double backward, differentiable to the parameters."""
    a = a.detach().requires_grad_(True)
    b = b.detach().requires_grad_(True)
    c = net.covariance(a, b, z)
    ga = torch.autograd.grad(c.sum(), a, create_graph=True)[0]  # (P, 3)
    rows = [torch.autograd.grad(ga[:, k].sum(), b, create_graph=True)[0] for k in range(3)]
    return torch.stack(rows, 1)  # (P, 3, 3)


def make_steps(width, depth, latent, batch, features, seed=0):
    """The three step functions (forward + backward of the covariance loss) on one clustered batch."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    box = Box(np.zeros(3), np.ones(3))
    cluster_size = 8
    x, w = sample_pair_clusters(box, batch // cluster_size, cluster_size, 0.08, rng)
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
        covariance_dirichlet_loss_pairs(d_operator_autograd(pair_net, a, b, z), sigma_pairs, w_pairs).backward()

    def step_jet():
        clear(pair_net)
        covariance_dirichlet_loss_pairs(pair_net.d_operator(a, b, z), sigma_pairs, w_pairs).backward()

    def step_feature():
        clear(feat_net)
        _, jac = feat_net.features_and_jacobian(x, z)  # (m, 3, K)
        covariance_dirichlet_loss_features(jac[None], sigma_all, w_all).backward()

    # (method, step, pairs per step, network points per step)
    return [
        ("(a) autograd", step_autograd, m, 2 * m),
        ("(b) mixed-jet", step_jet, m, 2 * m),
        ("(c) feature", step_feature, m * (m - 1), m),
    ]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=512, help="points (feature net) / pairs (pair net) per step")
    parser.add_argument("--widths", type=int_list, default=[128, 256, 512])
    parser.add_argument("--latent", type=int_list, default=[0, 128], help="latent code dimensions (0: none)")
    parser.add_argument("--depth", type=int_list, default=[3], help="sine layers; the paper uses 5 (--depth 3,5)")
    parser.add_argument("--features", type=int, default=128, help="K of the feature covariance")
    parser.add_argument("--seconds", type=float, default=3.0, help="wall time per measurement")
    args = parser.parse_args(argv)
    if args.batch % 8:
        parser.error("--batch must be a multiple of 8 (clusters of 8)")

    torch.set_num_threads(torch.get_num_threads())  # as is: whatever the environment gives
    torch.manual_seed(0)
    print(f"# d_operator benchmark  torch {torch.__version__}  threads {torch.get_num_threads()}  "
          f"{platform.processor() or platform.machine()}  cpus {os.cpu_count()}")
    print(f"# start {loadavg()}")
    peak = matmul_peak(args.seconds)
    print(f"# fp32 matmul peak (torch.mm 2048x2048): {peak:.1f} GFLOP/s")
    print(f"# batch {args.batch}, K = {args.features}, {args.seconds:g} s per measurement; "
          f"pairs/s = loss terms consumed per second; x(a) = pairs/s ratio to (a)")
    header = (f"{'depth':>5} {'width':>5} {'latent':>6}  {'method':<14} {'ms/step':>9} {'pairs/s':>11} "
              f"{'points/s':>10} {'x(a)':>8} {'GFLOP/step':>10} {'GFLOP/s':>8} {'%peak':>6}")
    print(header)
    print("-" * len(header))
    for depth in args.depth:
        for width in args.widths:
            for latent in args.latent:
                base = None
                for name, step, pairs, points in make_steps(width, depth, latent, args.batch, args.features):
                    gflop = count_matmul_flops(step) / 1e9  # also the first warm-up call
                    sec = time_loop(step, args.seconds, warmup=1)
                    pairs_s = pairs / sec
                    base = base or pairs_s
                    print(f"{depth:>5} {width:>5} {latent:>6}  {name:<14} {sec * 1e3:>9.2f} {pairs_s:>11.4g} "
                          f"{points / sec:>10.4g} {pairs_s / base:>8.3g} {gflop:>10.3f} {gflop / sec:>8.1f} "
                          f"{100 * gflop / sec / peak:>5.1f}%", flush=True)
    print(f"# end {loadavg()}")


if __name__ == "__main__":
    main()
