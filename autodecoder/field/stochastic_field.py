"""StochasticField: the fitted stochastic implicit surface f(x) ~ N(g(x), c(x, x)) and its queries.

All public queries take and return coordinates and values in the cloud's own ("world") frame; internally the
networks work in the unit-cube model frame (see :class:`datasets.frame.Frame`). Convention: f < 0
inside, f > 0 outside; f is a length (its gradient is the unit outward normal on the surface).
"""
import math
import os
from pathlib import Path

import numpy as np
import torch

from autodecoder.field.checkpoint_io import atomic_torch_save, load_torch_file
from datasets.frame import Frame
from autodecoder.field.networks import build_networks
from autodecoder.field.protocol import Field
from datasets.validation import check_points

FIELD_FORMAT = "nsspr-field"
FIELD_VERSION = 1
_CHUNK = 65536
_MIN_VARIANCE = 1e-20


class StochasticField(Field):
    """A Gaussian process f over space given by a mean net g and a covariance net c (optionally with a code z).

    Parameters
    ----------
    mean_net, cov_net : torch.nn.Module
        The mean net and a covariance net: :class:`autodecoder.field.siren.MeanNet` and ``FeatureCovarianceNet`` or
        ``PairCovarianceNet``, or the grid's (:mod:`autodecoder.field.grid_networks`).
    frame : datasets.frame.Frame
        World -> model frame.
    config : dict
        Network configuration (see :func:`autodecoder.field.networks.build_networks`) plus ``lengthscale`` and the
        box ``box_lo``/``box_hi`` (model frame).
    code : (L,) tensor, optional
        Latent code the nets are conditioned on (None for a single-cloud field).
    noise : float
        Default measurement noise (world units) added to the variance in :meth:`nll`.
    info : dict, optional
        Free-form provenance (fit time, losses); plain Python values only.
    training_points, training_normals : (n, 3) arrays, optional
        The oriented cloud the field was fitted to (world frame), kept as float32 tensors and saved with the field
        so that :func:`autodecoder.scanning.update.update_field` can fine-tune on old + new data; None when unknown.
    """

    def __init__(self, mean_net, cov_net, frame, config, code=None, noise=0.0, info=None,
                 training_points=None, training_normals=None):
        self.mean_net = mean_net.eval()
        self.cov_net = cov_net.eval()
        self.frame = frame
        self.config = dict(config)
        self.code = None if code is None else code.detach().float().reshape(-1)
        self.noise = float(noise)
        self.info = dict(info or {})
        as_t = lambda a: None if a is None else torch.as_tensor(np.asarray(a), dtype=torch.float32).reshape(-1, 3)
        self.training_points, self.training_normals = as_t(training_points), as_t(training_normals)

    # ----------------------------------------------------------------------------------- torch, differentiable
    def _model_x(self, x):
        c = torch.tensor(self.frame.center, dtype=x.dtype, device=x.device)  # the frame's array is read-only
        return (x - c) * self.frame.scale

    def _code_for(self, x):
        return None if self.code is None else self.code.to(x.dtype)

    def torch_mean(self, x):
        """E f(x) for world points x (m, 3) tensor -> (m,), differentiable with respect to x."""
        return self.mean_net(self._model_x(x), self._code_for(x)) / self.frame.scale

    def torch_mean_and_gradient(self, x):
        """E f(x) and its gradient for world points x (m, 3) tensor -> (m,), (m, 3).

        The gradient is unitless (world length over world length), so E f / |grad E f| is a first-order distance to
        the mean surface in world units."""
        value, grad = self.mean_net.value_and_gradient(self._model_x(x), self._code_for(x))
        return value / self.frame.scale, grad

    def torch_covariance(self, x1, x2):
        """Cov(f(x1_i), f(x2_i)) for world points taken row by row: (m, 3), (m, 3) -> (m,)."""
        s2 = self.frame.scale**2
        return self.cov_net.covariance(self._model_x(x1), self._model_x(x2), self._code_for(x1)) / s2

    def torch_variance(self, x):
        """Var f(x) for world points (m, 3) -> (m,)."""
        return self.cov_net.variance(self._model_x(x), self._code_for(x)) / self.frame.scale**2

    @property
    def lengthscale(self):
        """The GP kernel lengthscale of the fit, world units (None for a config without one)."""
        h = self.config.get("lengthscale")
        return None if h is None else float(h) / self.frame.scale

    @property
    def bounds(self):
        """(2, 3) array: the integration box (min, max corners) in world coordinates."""
        return self.frame.to_file(np.stack([self.config["box_lo"], self.config["box_hi"]]))

    # ------------------------------------------------------------------------------------------ numpy queries
    def _evaluate(self, fn, *arrays, shape=()):
        """fn over the query arrays in chunks, without autograd -> (n, *shape) float64 array."""
        arrays = [check_points(a, "query points", min_points=0) for a in arrays]
        n = len(arrays[0])
        out = np.empty((n, *shape), dtype=np.float64)
        with torch.no_grad():
            for start in range(0, n, _CHUNK):
                chunk = [torch.as_tensor(a[start:start + _CHUNK], dtype=torch.float32) for a in arrays]
                out[start:start + _CHUNK] = fn(*chunk).double().numpy()
        return out

    def mean(self, x):
        """E f(x) at world points x (m, 3) -> (m,) array (world length units)."""
        return self._evaluate(self.torch_mean, x)

    def mean_gradient(self, x):
        """grad E f(x) at world points x (m, 3) -> (m, 3) array (unitless)."""
        return self._evaluate(lambda x_: self.torch_mean_and_gradient(x_)[1], x, shape=(3,))

    def mean_and_gradient(self, x):
        """(E f(x) (m,), grad E f(x) (m, 3)) at world points x (m, 3), in one pass of the mean net (the value is the
        one :meth:`mean` gives, carried forward with its gradient)."""
        both = self._evaluate(lambda x_: torch.cat([v.reshape(len(x_), -1) for v in self.torch_mean_and_gradient(x_)],
                                                   dim=1), x, shape=(4,))
        return both[:, 0], both[:, 1:]

    def variance(self, x):
        """Var f(x) at world points x (m, 3) -> (m,) array (world units squared)."""
        return self._evaluate(self.torch_variance, x)

    def covariance(self, x1, x2):
        """Cov(f(x1_i), f(x2_i)) for pairs of world points row by row: (m, 3), (m, 3) -> (m,)."""
        x1, x2 = np.asarray(x1), np.asarray(x2)
        if x1.shape != x2.shape:
            raise ValueError(f"x1 and x2 must have the same shape, got {x1.shape} and {x2.shape}")
        return self._evaluate(self.torch_covariance, x1, x2)

    def prob_inside(self, x):
        """P(f(x) <= 0) at world points x (m, 3) -> (m,) array in [0, 1]."""
        mean, var = self.mean(x), self.variance(x)
        return 0.5 * torch.special.erfc(torch.as_tensor(mean / np.sqrt(2 * np.maximum(var, _MIN_VARIANCE)))).numpy()

    def nll(self, points, noise=None):
        """Per-point negative log likelihood of f(p) = 0 under N(mean(p), variance(p) + noise^2).

        Parameters
        ----------
        points : (m, 3) array
            World points (e.g. a scan that should lie on the surface).
        noise : float, optional
            Measurement noise standard deviation in world units (default: ``self.noise``).

        Returns
        -------
        (m,) array
        """
        noise = self.noise if noise is None else float(noise)
        if noise < 0:
            raise ValueError(f"noise must be >= 0, got {noise}")
        mean, var = self.mean(points), self.variance(points)
        total = np.maximum(var + noise**2, _MIN_VARIANCE)
        return 0.5 * (mean**2 / total + np.log(2 * math.pi * total))

    def mesh(self, resolution=128):
        """The mean's zero level set, extracted by marching cubes over the integration box.

        Parameters
        ----------
        resolution : int
            Grid samples along each side of the (cubic) box.

        Returns
        -------
        trimesh.Trimesh in world coordinates, faces oriented outward (f > 0 outside).
        """
        import trimesh
        from skimage.measure import marching_cubes

        if resolution < 8:
            raise ValueError(f"resolution must be >= 8, got {resolution}")
        lo, hi = np.asarray(self.config["box_lo"]), np.asarray(self.config["box_hi"])
        axes = [np.linspace(lo[d], hi[d], resolution) for d in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        values = self.mean(self.frame.to_file(grid)).reshape((resolution,) * 3)
        if not (values.min() < 0 < values.max()):
            raise ValueError("the mean field has no zero crossing in its box: there is no surface to mesh")
        spacing = tuple((hi - lo) / (resolution - 1))
        # skimage's default winding ('descent') gives counter-clockwise faces seen from where values grow, i.e.
        # outward-facing normals for f < 0 inside (checked by the sphere test)
        verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=spacing)
        return trimesh.Trimesh(self.frame.to_file(verts + lo), faces, process=False)

    # ----------------------------------------------------------------------------------------------- files
    def state(self):
        """Everything needed to rebuild the field, as tensors and plain Python values."""
        return {
            "format": FIELD_FORMAT,
            "version": FIELD_VERSION,
            "config": self.config,
            "mean_state": self.mean_net.state_dict(),
            "cov_state": self.cov_net.state_dict(),
            "code": self.code,
            "normalization": self.frame.as_dict(),  # the file key of format version 1 (the frame was called so)
            "noise": self.noise,
            "info": self.info,
            "training_points": self.training_points,
            "training_normals": self.training_normals,
            # a latent grid model's covariance clamp (set_code_range): not in the net's state dict, so kept here
            "cov_code_range": _code_range(self.cov_net),
        }

    def save(self, path):
        """Write the field to ``path`` atomically (a temporary file renamed into place)."""
        atomic_torch_save(self.state(), path)

    @classmethod
    def from_state(cls, state, source="<state>"):
        if not isinstance(state, dict) or state.get("format") != FIELD_FORMAT:
            raise ValueError(f"{source}: not a stochastic field file (format tag {FIELD_FORMAT!r} missing)")
        if state.get("version") != FIELD_VERSION:
            raise ValueError(f"{source}: field file version {state.get('version')} is not supported "
                             f"(this toolkit reads version {FIELD_VERSION})")
        mean_net, cov_net = build_networks(state["config"])
        mean_net.load_state_dict(state["mean_state"])
        cov_net.load_state_dict(state["cov_state"])
        if state.get("cov_code_range") is not None:
            cov_net.set_code_range(*state["cov_code_range"])
        return cls(mean_net, cov_net, Frame.from_dict(state["normalization"]), state["config"],
                   code=state["code"], noise=state["noise"], info=state.get("info"),
                   training_points=state.get("training_points"), training_normals=state.get("training_normals"))

    @classmethod
    def load(cls, path):
        """Read a field written by :meth:`save` (``torch.load(weights_only=True)``)."""
        return cls.from_state(load_torch_file(path, what="stochastic field"), source=os.fspath(Path(path)))


def _code_range(net):
    """(lo, hi) of a net's code clamp (:meth:`GridCovarianceNet.set_code_range`), None when it has none."""
    lo, hi = getattr(net, "code_lo", None), getattr(net, "code_hi", None)
    return None if lo is None else (lo.clone(), hi.clone())
