"""The inspection settings in one place: every default of the Python API and the command line, validated once.

:class:`InspectionConfig` is what an :class:`inspection.Inspector` is made with (its scikit-learn parameters are
these fields), what ``nsspr-inspect calibrate`` builds from its options, and what a calibration stores whole
(:mod:`inspection.calibration`), so that scoring later uses exactly the settings the threshold was drawn with.

Two fields are decided from the data when left at ``'auto'`` (by :meth:`inspection.Inspector.fit`, which records
what it chose in its fitted attributes, never in the parameters):

* ``point_score='auto'``: ``'joint'`` when the good scans given to ``fit`` include the model's training scans (they
  give the per-location reference), else ``'residual'``, the one score that needs nothing but the projected field.
* ``rays='auto'``: the sensor's rays are used when there is a per-location reference (its training scans give the
  band of good surfaces the rays are tested in) and every good scan records a sensor origin.
* ``align='auto'``: scans are registered when the training scans' poses spread: registering each of them onto the
  others lowers its point-to-plane residuals by a median factor above ``inspection.align.AUTO_RATIO``
  (:func:`inspection.align.pose_spread`; a part in a fixture gives 1.0); never without training scans.
* ``coverage='auto'``: scans are scored over their covered points (``inspection.coverage.COVERAGE_LENGTHSCALES``)
  when the held-back good scans show surface the good training scans did not cover, at least
  ``inspection.coverage.COVERAGE_MIN_SHARE`` of their points (:func:`inspection.coverage.decide_coverage`); else
  every point counts.
"""
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from .threshold import DEFAULT_ALPHA, check_alpha

DEFAULT_AGGREGATE = "top1"
# Projection settings for inspection (autodecoder.latent.projection.ProjectionOptions fields): a shorter run from fewer
# starts, on 128 points a step, than the trainer's defaults that reaches the same projection loss at a fraction of the
# time (docs/results.md#at-the-line-seconds-per-scan-issue-30). ``projection='default'`` means these; None means the
# projector's own defaults.
DEFAULT_PROJECTION = {"steps": 60, "starts": 2, "explore": 20, "max_candidates": 16, "sample": 128}
RAYS_CHOICES = (True, False, "auto")


@dataclass(frozen=True)
class InspectionConfig:
    """Every setting of an inspection, with its default.

    Attributes
    ----------
    alpha : float in (0, 1)
        False-alarm rate: a scan is defective when its p-value is <= alpha.
    aggregate : str
        Per-scan aggregate of the point scores (:func:`inspection.aggregates.aggregate`): ``'top1'`` (mean of the worst
        1 % of the points: defects cover a few per cent of a scan, so the paper's ``'mean'`` dilutes them),
        ``'mean'``, ``'max'``, ``'median'``, ``'top<P>'``, ``'q<P>'``.
    point_score : str
        A name of :data:`inspection.scores.POINT_SCORES`, or ``'auto'`` (module docstring).
    noise : float or None
        Noise floor (measurement noise standard deviation, model frame units); None: the field's own.
    projection : 'default', dict or None
        Options of the latent model's ``project`` (``ProjectionOptions`` fields): ``'default'`` is
        ``DEFAULT_PROJECTION``, None the projector's own defaults. Ignored for a fixed field.
    rays : True, False or 'auto'
        Also score the sensor's rays (:mod:`inspection.ray_evidence`); ``'auto'``: module docstring.
    ray_options : dict or None
        Settings of the ray score (keys of ``inspection.ray_evidence.RAY_DEFAULTS``).
    align : True, False or 'auto'
        Register every scan onto good training scans (rigid ICP, :mod:`inspection.align`) before scoring it, for
        parts not held in a fixture. The calibration scans are registered as new scans are, so that the threshold
        is drawn from scores of scans moved the same way as those it judges. ``'auto'``: module docstring.
    coverage : 'auto' or float >= 0
        Score each scan over its points on surface the good scans covered, within this many kernel lengthscales
        (:mod:`inspection.coverage`; its evidence on other surface makes the verdict ``'uncertain'``); 0: every
        point counts, as calibrations stored before coverage do. ``'auto'``: module docstring.
    """

    alpha: float = DEFAULT_ALPHA
    aggregate: str = DEFAULT_AGGREGATE
    point_score: str = "auto"
    noise: object = None
    projection: object = "default"
    rays: object = "auto"
    ray_options: object = None
    align: object = "auto"
    coverage: object = "auto"

    def validated(self):
        """This configuration with every value checked (ValueError naming the setting, the expected values and the
        one received) and normalised (numbers as floats, option dicts copied). Cheap: no model is read."""
        from .aggregates import check_aggregate
        from .scores import POINT_SCORES

        check_alpha(self.alpha)
        check_aggregate(self.aggregate)
        if self.point_score != "auto" and self.point_score not in POINT_SCORES:
            raise ValueError(f"point_score must be 'auto' or one of {tuple(POINT_SCORES)}, got {self.point_score!r}")
        noise = self.noise
        if noise is not None:
            try:
                noise = float(noise)
            except (TypeError, ValueError):
                noise = float("nan")
            if not noise >= 0:
                raise ValueError(f"noise must be None or a number >= 0 (model frame units), got {self.noise!r}")
        if self.rays not in RAYS_CHOICES or isinstance(self.rays, (int, float)) and not isinstance(self.rays, bool):
            raise ValueError(f"rays must be True, False or 'auto', got {self.rays!r}")
        ray_options = None
        if self.ray_options:
            if self.rays is False:
                raise ValueError("ray_options need rays=True or 'auto', not rays=False")
            from .ray_evidence import check_ray_options

            check_ray_options(self.ray_options)
            ray_options = dict(self.ray_options)
        if self.align not in (True, False, "auto") or not isinstance(self.align, (bool, str)):
            raise ValueError(f"align must be True, False or 'auto', got {self.align!r}")
        coverage = self.coverage
        if coverage != "auto":
            try:
                coverage = float(self.coverage)
            except (TypeError, ValueError):
                coverage = float("nan")
            if not (coverage >= 0 and np.isfinite(coverage)) or isinstance(self.coverage, bool):
                raise ValueError(f"coverage must be 'auto' or a number >= 0 (kernel lengthscales; 0: every point "
                                 f"counts), got {self.coverage!r}")
        return replace(self, alpha=float(self.alpha), noise=noise, projection=check_projection(self.projection),
                       ray_options=ray_options, coverage=coverage)

    def decided(self, model, with_reference, with_origins):
        """These (validated) settings with ``point_score`` and ``rays`` decided for ``model`` (module docstring): for
        a calibration with a per-location reference (``with_reference``: the model's training scans among the good
        scans) and a sensor origin on every good scan (``with_origins``). ``ray_options`` become complete with rays
        and None without; ``projection`` becomes the ``project`` options themselves (:meth:`projection_for`).
        ``align`` is left as it is: the calibration decides it from the training scans' poses
        (:func:`inspection.calibrating.fit_alignment`)."""
        from .ray_evidence import check_ray_options

        point_score = self.point_score
        if point_score == "auto":
            point_score = "joint" if with_reference else "residual"
        rays = self.rays
        if rays == "auto":
            rays = bool(with_reference and with_origins)
        return replace(self, point_score=point_score, rays=bool(rays),
                       ray_options=check_ray_options(self.ray_options) if rays else None,
                       projection=self.projection_for(model))

    def projection_for(self, model):
        """The ``project`` options these settings mean for ``model``: None for a fixed field (no ``project``);
        ``'default'`` means ``DEFAULT_PROJECTION`` for the toolkit's latent models
        (:class:`autodecoder.latent.model.LatentModel`) and the projector's own defaults (None) for any other model
        with a ``project`` method; an empty dict means the projector's own defaults too."""
        if not hasattr(model, "project"):
            return None
        if self.projection == "default":
            from autodecoder.latent.model import LatentModel

            return self.projection_options() if isinstance(model, LatentModel) else None
        return self.projection_options() or None

    def projection_options(self):
        """The ``project`` keyword arguments these settings mean (a dict, possibly empty)."""
        if self.projection == "default":
            return dict(DEFAULT_PROJECTION)
        return dict(self.projection or {})

    def as_dict(self):
        """Plain Python values (what a calibration stores under ``extra['config']``)."""
        d = asdict(self)
        d["projection"] = self.projection if isinstance(self.projection, (str, type(None))) else dict(self.projection)
        d["ray_options"] = None if self.ray_options is None else dict(self.ray_options)
        return d

    @classmethod
    def from_dict(cls, d):
        """The configuration :meth:`as_dict` wrote; unknown keys are errors (a record of another version)."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"inspection settings: unknown key(s) {unknown}; expected some of {sorted(names)}")
        return cls(**d).validated()


def check_projection(projection):
    """``'default'``, None, or a dict of ``ProjectionOptions`` fields with values of the right kind (copied);
    anything else is a ValueError naming the bad key. The check reads the dataclass's fields without running a
    projection, so a typo fails before a model is loaded."""
    if projection is None or projection == "default":
        return projection
    if not isinstance(projection, dict):
        raise ValueError(f"projection must be 'default', None or a dict of ProjectionOptions fields, got "
                         f"{projection!r}")
    from autodecoder.latent.projection import ProjectionOptions

    known = {f.name: f for f in fields(ProjectionOptions)}
    unknown = sorted(set(projection) - set(known))
    if unknown:
        raise ValueError(f"projection: unknown option(s) {unknown}; expected some of {sorted(known)}")
    out = {}
    for key, value in projection.items():
        default = getattr(ProjectionOptions(), key)
        if isinstance(default, bool) or not isinstance(default, (int, float)) or isinstance(value, bool):
            out[key] = value
            continue
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"projection option {key} must be a number, got {value!r}") from None
        if isinstance(default, int) and number != int(number):
            raise ValueError(f"projection option {key} must be an integer, got {value!r}")
        if number < 0:
            raise ValueError(f"projection option {key} must be >= 0, got {value!r}")
        out[key] = int(number) if isinstance(default, int) else number
    return out


def parse_key_values(text, option):
    """``'KEY=VALUE,...'`` -> dict, each value an int where it parses, else a float, else the string; ``option``
    names the command-line option in the error of a malformed pair."""
    out = {}
    for item in filter(None, (t.strip() for t in str(text).split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{option}: expected KEY=VALUE pairs separated by commas, got {item!r}")
        for cast in (int, float, str):
            try:
                out[key.strip()] = cast(value.strip())
                break
            except ValueError:
                continue
    return out
