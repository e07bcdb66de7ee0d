"""The mean network g(x, z) and the covariance network c(x1, x2, z) of NSSPR, of either representation.

:func:`build_networks` builds the pair a configuration asks for: the SIRENs of :mod:`autodecoder.field.siren`
(:class:`~autodecoder.field.siren.MeanNet`, :class:`~autodecoder.field.siren.FeatureCovarianceNet` or the paper's
:class:`~autodecoder.field.siren.PairCovarianceNet`), or the B-spline grid nets of
:mod:`autodecoder.field.grid_networks`. Each representation's nets live with their building blocks, so that building
them enters each module once.
"""
from autodecoder.field.grid_networks import build_grid_networks
from autodecoder.field.siren import build_siren_networks


def build_networks(config):
    """Mean and covariance nets from a configuration dict.

    Keys: ``width``, ``depth``, ``latent_dim``, ``covariance`` ('feature' or 'pair'), ``features`` (feature net),
    ``omega0``; optional ``cov_width``/``cov_depth`` (default: the mean net's). With ``representation: 'grid'``
    the B-spline grid nets of :func:`autodecoder.field.grid_networks.build_grid_networks` instead.

    Returns
    -------
    (MeanNet, FeatureCovarianceNet or PairCovarianceNet), of :mod:`autodecoder.field.siren`; or the grid's pair
    """
    if config.get("representation", "siren") == "grid":
        return build_grid_networks(config)
    return build_siren_networks(config)
