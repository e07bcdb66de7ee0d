"""The NSSPR losses: Dirichlet terms for the mean and the covariance, and the screening terms.

Batched over S scans (S = 1 for a single cloud); see :mod:`autodecoder.sampling` for the estimators and weights.
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


def covariance_dirichlet_loss_features(jac, sigma, weights):
    """sum_{i,j} w_ij ||Sigma_ij I - J_i^T J_j||_F^2 over all ordered pairs of each scan's batch (feature net).

    For c(a, b) = phi(a) . phi(b), D c(a, b) = J(a)^T J(b) with J the (K, 3) Jacobian of phi; one Gram matrix of
    the stacked Jacobians gives D c for every pair. The Frobenius norm is expanded as
    ||D c||^2 - 2 Sigma tr(D c) + 3 Sigma^2 so that no (m, m, 3, 3) difference tensor is formed.

    Parameters
    ----------
    jac : (S, m, 3, K) tensor
        Jacobians of the (scaled) features at each scan's m pair points.
    sigma : (S, m, m) tensor
        Target covariances Sigma(x_i, x_j).
    weights : (S, m, m) tensor
        Pair weights w_ij (zero on the diagonal).

    Returns
    -------
    scalar tensor (averaged over scans)
    """
    s, m, _, k = jac.shape
    flat = jac.reshape(s, 3 * m, k)
    gram = (flat @ flat.transpose(1, 2)).view(s, m, 3, m, 3)  # gram[s, i, k, j, l] = (D c_ij)_kl
    frob = gram.square().sum((2, 4))  # (S, m, m)
    trace = gram.diagonal(dim1=2, dim2=4).sum(-1)  # (S, m, m)
    per_pair = frob - 2 * sigma * trace + 3 * sigma.square()
    return (weights * per_pair).sum((1, 2)).mean()
