"""The NSSPR losses: Dirichlet terms for the mean and the covariance, and the screening terms.

Batched over S scans (S = 1 for a single cloud); see :mod:`autodecoder.field.sampling` for the estimators and weights.
"""
import torch

SCREENING_WEIGHT = 100.0  # lambda_S of the paper


def mean_dirichlet_loss(grad_g, mu, omega, box_volume):
    """|B|/s sum_k omega_k |mu(x_k) - grad g(x_k)|^2, the paper's mean loss with importance weights omega.

    Parameters
    ----------
    grad_g, mu : (..., s, 3) tensors
    omega : (..., s) tensor
        Importance weights (1 for uniform sampling).
    box_volume : float
        |B|.

    Returns
    -------
    scalar tensor (averaged over leading batch dimensions)
    """
    return box_volume * (omega * (mu - grad_g).square().sum(-1)).mean()


def screening_loss(values, weight=SCREENING_WEIGHT):
    """lambda_S * mean of values^2 (values: g(p) or c(p, p) at cloud points, any shape)."""
    return weight * values.square().mean()


def covariance_dirichlet_loss_pairs(d_c, sigma, weights):
    """sum_k w_k ||Sigma_k I - D c_k||_F^2 over an explicit list of pairs (the paper's pair network).

    Parameters
    ----------
    d_c : (P, 3, 3) tensor
    sigma : (P,) tensor
    weights : (P,) tensor

    Returns
    -------
    scalar tensor
    """
    eye = torch.eye(3, dtype=d_c.dtype, device=d_c.device)
    return (weights * (sigma[:, None, None] * eye - d_c).square().sum((-1, -2))).sum()


def covariance_dirichlet_loss_features(jac, sigma, weights, cluster_size=None):
    """sum_{i,j} w_ij ||Sigma_ij I - J_i^T J_j||_F^2 over all ordered pairs of each scan's batch (feature net).

    For c(a, b) = phi(a) . phi(b), D c(a, b) = J(a)^T J(b) with J the (K, 3) Jacobian of phi. The Frobenius norm is
    expanded as ||D c||^2 - 2 Sigma tr(D c) + 3 Sigma^2, and the weights are split as w_ij = w0 + (w_ij - w0) with
    w0 the largest weight of the scan: the pair samplers give every pair further apart than the kernel's support
    that same weight (they have no clustering density), and there Sigma = 0 too. The w0 part over ALL pairs
    needs no pair at all,

        w0 sum_{i,j} ||J_i^T J_j||_F^2 = w0 ||A||_F^2,    A = sum_i J_i J_i^T  (K x K),

    which costs O(m K^2) instead of the O(m^2 K) of the Gram matrix of every pair; the remainder (w_ij - w0) and the
    Sigma terms are non-zero only for the few pairs within the support and the diagonal (w_ii = 0), which are
    gathered explicitly. The result is the same sum, rearranged (exact for any weights; when they are not of this
    form the dense Gram matrix is used).

    With ``cluster_size`` c (the batch is m / c clusters of c consecutive points, as
    :func:`autodecoder.field.sampling.sample_pair_clusters` lays them out) the near pairs inside a cluster, most of
    them, come from each cluster's own Gram matrix of its 3c Jacobian rows (one small matrix product per cluster);
    only the near pairs across clusters are gathered one by one. The same sum again: a pair inside a cluster that is
    not near adds exact zeros. Why: a product of one 3 x K by one K x 3 matrix per near pair (thousands per step)
    was half of a latent training's covariance half-step (docs/results_archive.md, "Speed").

    Parameters
    ----------
    jac : (S, m, 3, K) tensor
        Jacobians of the (scaled) features at each scan's m pair points.
    sigma : (S, m, m) tensor
        Target covariances Sigma(x_i, x_j).
    weights : (S, m, m) tensor
        Pair weights w_ij (zero on the diagonal).
    cluster_size : int, optional
        c >= 2 dividing m: the pairs inside clusters by each cluster's Gram matrix (above). None: every near pair
        gathered.

    Returns
    -------
    scalar tensor (averaged over scans)
    """
    s, m, _, k = jac.shape
    base = weights.amax(dim=(1, 2)).detach()  # (S,)
    residual_weight = weights - base[:, None, None]
    near_mask = (residual_weight != 0) | (sigma != 0)
    blocks = cluster_size is not None and int(cluster_size) >= 2 and m % int(cluster_size) == 0
    if blocks:
        c = int(cluster_size)
        cluster = torch.arange(m, device=jac.device) // c
        near_mask = near_mask & (cluster[:, None] != cluster[None, :])  # the rest: inside the clusters' Gram blocks
    scan, i, j = torch.nonzero(near_mask, as_tuple=True)
    if not blocks and len(scan) > s * m * m // 8:  # not a sparse correction: the dense Gram matrix is cheaper
        return _covariance_loss_dense(jac, sigma, weights)
    flat = jac.reshape(s, 3 * m, k)
    moment = flat.transpose(1, 2) @ flat  # (S, K, K)
    # summed in double: w0 ||A||^2 includes the near pairs, which the correction then takes out again
    per_scan = base.double() * moment.double().square().sum((1, 2))  # (S,)
    if blocks:
        n_clusters = m // c
        rows = flat.view(s, n_clusters, 3 * c, k)
        gram = (rows @ rows.transpose(-1, -2)).view(s, n_clusters, c, 3, c, 3)  # [s, q, i, a, j, b]

        def block_diagonal(a):  # (S, m, m) -> (S, C, c, c): the pairs inside each cluster
            return torch.diagonal(a.view(s, n_clusters, c, n_clusters, c), dim1=1, dim2=3).permute(0, 3, 1, 2)

        sig_b = block_diagonal(sigma)
        inside = (block_diagonal(residual_weight) * gram.square().sum((3, 5))
                  + block_diagonal(weights) * (3 * sig_b.square() - 2 * sig_b * gram.diagonal(dim1=3, dim2=5).sum(-1)))
        per_scan = per_scan + inside.sum((1, 2, 3)).double()
    rows = jac.reshape(s * m, 3, k)
    d_c = torch.einsum("pak,pbk->pab", rows.index_select(0, scan * m + i), rows.index_select(0, scan * m + j))
    frob = d_c.square().sum((1, 2))
    trace = d_c.diagonal(dim1=1, dim2=2).sum(-1)
    sig = sigma[scan, i, j]
    near = residual_weight[scan, i, j] * frob + weights[scan, i, j] * (3 * sig.square() - 2 * sig * trace)
    per_scan = per_scan.index_add(0, scan, near.double())
    return per_scan.mean().to(jac.dtype)


def _covariance_loss_dense(jac, sigma, weights):
    """The same loss from the Gram matrix of every pair's D c (no assumption on the weights)."""
    s, m, _, k = jac.shape
    flat = jac.reshape(s, 3 * m, k)
    gram = (flat @ flat.transpose(1, 2)).view(s, m, 3, m, 3)  # gram[s, i, k, j, l] = (D c_ij)_kl
    frob = gram.square().sum((2, 4))  # (S, m, m)
    trace = gram.diagonal(dim1=2, dim2=4).sum(-1)  # (S, m, m)
    per_pair = frob - 2 * sigma * trace + 3 * sigma.square()
    return (weights * per_pair).sum((1, 2)).mean()
