"""The model: neural stochastic screened Poisson reconstruction (Sellán & Jacobson 2023) and its latent space.

Three sub-packages, each depending only on those before it (and on ``datasets``), never on ``inspection``:

- ``autodecoder.field``: the single-cloud stochastic field (kernel, GP targets, networks, losses, fit, queries);
- ``autodecoder.latent``: the latent model over a collection (training, checkpoints, projection of a new scan);
- ``autodecoder.scanning``: ray casting, free space along a scan's rays, next-best views, fine-tuning.

Public names are imported lazily so that ``import autodecoder`` (and ``--help`` of the command lines) stays fast.
"""
import importlib

_EXPORTS = {
    "fit_cloud": "autodecoder.field.fit",
    "FitOptions": "autodecoder.field.fit",
    "StochasticField": "autodecoder.field.stochastic_field",
    "GPPosterior": "autodecoder.field.gp_targets",
    # latent model: training over collections, checkpoints, test-time projection
    "LatentModel": "autodecoder.latent.model",
    "load_model": "autodecoder.latent.model",
    "LatentOptions": "autodecoder.latent.options",
    "train_latent": "autodecoder.latent.train",
    "Projection": "autodecoder.latent.projection",
    "ProjectionOptions": "autodecoder.latent.projection",
    "project": "autodecoder.latent.projection",
    "project_many": "autodecoder.latent.projection",
    # scanning: correlated ray casting, next-best-view, fine-tuning on new scans
    "cast_rays": "autodecoder.scanning.rays",
    "orthant_survival": "autodecoder.scanning.rays",
    "blocked_probability": "autodecoder.scanning.free_space",
    "missing_return_probability": "autodecoder.scanning.free_space",
    "next_best_views": "autodecoder.scanning.views",
    "update_field": "autodecoder.scanning.update",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'autodecoder' has no attribute {name!r}")

