"""The model: neural stochastic screened Poisson reconstruction (Sellán & Jacobson 2023) and its latent space.

Public names are imported lazily so that ``import autodecoder`` (and ``--help`` of the command lines) stays fast.
"""
import importlib

_EXPORTS = {
    "fit_cloud": "autodecoder.fit",
    "FitOptions": "autodecoder.fit",
    "StochasticField": "autodecoder.field",
    "GPPosterior": "autodecoder.gp_targets",
    # latent model: training over collections, checkpoints, test-time projection
    "LatentModel": "autodecoder.latent_model",
    "load_model": "autodecoder.latent_model",
    "LatentOptions": "autodecoder.latent_train",
    "train_latent": "autodecoder.latent_train",
    "Projection": "autodecoder.projection",
    "ProjectionOptions": "autodecoder.projection",
    "project": "autodecoder.projection",
    "project_many": "autodecoder.projection",
    # scanning: correlated ray casting, next-best-view, fine-tuning on new scans
    "cast_rays": "autodecoder.rays",
    "orthant_survival": "autodecoder.rays",
    "blocked_probability": "autodecoder.free_space",
    "missing_return_probability": "autodecoder.free_space",
    "next_best_views": "autodecoder.views",
    "update_field": "autodecoder.update",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'autodecoder' has no attribute {name!r}")

