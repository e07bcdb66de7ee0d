"""Per-scan pools of GP posterior targets for latent training, drawn once and served for several epochs.

Drawing fresh GP targets (KD-tree queries, sparse kernel rows, the pair covariance matrices) cost about as much as the
network's forward and backward pass in a latent training step on a 2-core CPU
(docs/results.md#latent-training-and-projection-cost). A scan's
targets are the same distribution at every epoch, so a pool of them is drawn once and each sample serves
``passes`` epochs (in a fresh shuffled order each pass), which takes target sampling to a small fraction of a step.

Every draw is a pure function of (seed, scan index, epoch): the pools need no saved state, a resumed run reproduces
an uninterrupted one exactly, and under DDP a scan's targets do not depend on which rank owns it.
"""
import numpy as np
import torch


class ScanTargetPool:
    """The targets one scan serves at each epoch.

    Parameters
    ----------
    targets : CloudTargets
        The scan's GP posterior.
    scan_index : int
        The scan's index in the training set (seeds its draws).
    seed : int
        The training seed.
    mean_samples : int
        Mean-loss samples per epoch (one minibatch).
    refresh : int
        Minibatches in one mean pool (the pool holds ``mean_samples * refresh`` samples).
    passes : int
        Epochs each mean sample serves (shuffled passes over a pool) and steps each covariance batch serves.
    pair_clusters, cluster_size : int
        Shape of a covariance batch (see :meth:`CloudTargets.pair_batch`).
    """

    def __init__(self, targets, scan_index, seed, mean_samples, refresh, passes, pair_clusters, cluster_size):
        if refresh < 1 or passes < 1:
            raise ValueError(f"refresh and passes must be >= 1, got {refresh} and {passes}")
        self.targets, self.scan_index, self.seed = targets, int(scan_index), int(seed)
        self.mean_samples, self.refresh, self.passes = int(mean_samples), int(refresh), int(passes)
        self.pair_clusters, self.cluster_size = int(pair_clusters), int(cluster_size)
        self._mean_block = None  # (block, x, mu, omega)
        self._order = None  # (block, pass, permutation)
        self._pair = None  # (block, x, sigma, weights)

    def _rng(self, *stream):
        return np.random.default_rng([self.seed, self.scan_index, *stream])

    def mean_batch(self, epoch):
        """This epoch's mean-loss minibatch: x (n, 3), mu (n, 3), omega (n,) float32 arrays."""
        cycle = self.refresh * self.passes
        # scans start their cycles at staggered epochs, so that the pools of a collection are not all redrawn in
        # the same epoch (a visible stall every `cycle` epochs otherwise)
        block, within = divmod(int(epoch) + self.scan_index % cycle, cycle)
        if self._mean_block is None or self._mean_block[0] != block:
            x, mu, omega = self.targets.mean_batch(self.mean_samples * self.refresh, self._rng(1, block))
            self._mean_block = (block, x, mu, omega)
        pass_, slot = divmod(within, self.refresh)
        if self._order is None or self._order[:2] != (block, pass_):
            self._order = (block, pass_, self._rng(2, block, pass_).permutation(self.mean_samples * self.refresh))
        idx = self._order[2][slot * self.mean_samples:(slot + 1) * self.mean_samples]
        _, x, mu, omega = self._mean_block
        return x[idx], mu[idx], omega[idx]

    def pair_batch(self, epoch):
        """This epoch's covariance batch: x (m, 3), sigma (m, m), weights (m, m) float32 arrays."""
        block = (int(epoch) + self.scan_index % self.passes) // self.passes
        if self._pair is None or self._pair[0] != block:
            batch = self.targets.pair_batch(self.pair_clusters, self.cluster_size, self._rng(3, block))
            self._pair = (block, *batch)
        return self._pair[1:]


def stack_inputs(pools, epoch, screen_samples, rng, device):
    """S scans' targets for one step, stacked into the tensors the latent training's loss module takes.

    Parameters
    ----------
    pools : list of ScanTargetPool
    epoch : int
    screen_samples : int
        Cloud points per scan for the screening terms (capped at the smallest scan's size).
    rng : numpy.random.Generator
        Draws the screening points.
    device : torch.device

    Returns
    -------
    dict of tensors: x (S n, 3), mu (S, n, 3), omega (S, n), screen (S q, 3), pair_x (S m, 3), sigma (S, m, m),
    weights (S, m, m)
    """
    xs, mus, omegas, screens, pxs, sigmas, weights = [], [], [], [], [], [], []
    n_screen = min([screen_samples] + [len(p.targets.points32) for p in pools])
    for pool in pools:
        x, mu, omega = pool.mean_batch(epoch)
        px, sigma, w = pool.pair_batch(epoch)
        xs.append(x), mus.append(mu), omegas.append(omega), pxs.append(px), sigmas.append(sigma), weights.append(w)
        screens.append(pool.targets.screen_batch(n_screen, rng))

    def cat(a, stack=False):
        return torch.from_numpy(np.stack(a) if stack else np.concatenate(a)).to(device)

    return {"x": cat(xs), "mu": cat(mus, True), "omega": cat(omegas, True), "screen": cat(screens),
            "pair_x": cat(pxs), "sigma": cat(sigmas, True), "weights": cat(weights, True)}
