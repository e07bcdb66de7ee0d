"""Per-point anomaly scores of a scan under a stochastic field: the registry of point scores and their formulas.

Their per-scan aggregates are :mod:`inspection.aggregates`'; the per-location reference the ``'distance'`` and
``'joint'`` scores compare with is :mod:`inspection.reference`'s.

Every score here is "higher = more anomalous". The point scores read the field at the scan's points, which must be
in the field's own (world) frame, i.e. the collection frame for a model trained on a collection.
"""
import math
from dataclasses import dataclass

import numpy as np

from .reference import checked_term_variances, field_quantity


@dataclass(frozen=True)
class PointScore:
    """One per-point score of the registry :data:`POINT_SCORES`.

    Attributes
    ----------
    name : str
    reference : bool
        Whether it compares the scan with good scans at the same place (a :class:`inspection.reference.LocalReference` built from the
        model's training scans: calibration then needs them).
    in_deviations : bool
        Whether its values are standardized residuals, in standard deviations (the maps' fixed colour range,
        :mod:`inspection.maps`); the NLL is in nats.
    summary : str
        One line for the command line's help.
    """

    name: str
    reference: bool
    in_deviations: bool
    summary: str


# The per-point scores, the one list the estimator, the command line's choices, the maps and the benchmarks read
# (formulas: point_scores). The default is 'joint' where the training scans give a reference, else 'residual'.
POINT_SCORES = {s.name: s for s in (
    PointScore("joint", True, True, "the field's distance residual and the good scans' own surface together (default)"),
    PointScore("distance", True, True, "the first-order distance to the mean surface against good scans there"),
    PointScore("surface", True, True, "the good scans' own surface alone, no field: the model-free term of joint "
                                      "(a baseline)"),
    PointScore("agreement", True, True, "the field's distance residual and the good scans' own surface, counted as "
                                        "far as both agree (their geometric mean)"),
    PointScore("residual", False, True, "the standardized residual |E f| / sd (needs no reference)"),
    PointScore("nll", False, False, "the paper's negative log likelihood of f = 0"),
)}
_MIN_VARIANCE = 1e-20
# the point scores that weigh two terms by their variances on good scans (fit_term_variances)
WEIGHED_SCORES = ("joint", "agreement")
CHI2_1_MEDIAN = 0.454936423119572  # the median of chi-square(1): median(z^2) / this estimates Var z for Gaussian z
MIN_TERM_VARIANCE = 1e-4  # fit_term_variances: a term that is ~0 on every good point still divides by this


def noise_floor(field, noise=None):
    """The measurement noise standard deviation (model frame units) a scan's point scores add to their variance:
    ``noise`` when the settings give one (:attr:`inspection.config.InspectionConfig.noise`), else the scan's
    projected ``field``'s own ``noise`` (0 for a field without one). A float."""
    return float(getattr(field, "noise", 0.0) if noise is None else noise)


def point_scores(field, points, kind="residual", noise=None, reference=None, normals=None, origin=None):
    """Per-point anomaly scores of ``points`` under ``field`` (higher = more anomalous).

    With m = E f(p), v = Var f(p) and total = v + noise^2 (the noise floor):

    * ``'nll'``: the paper's negative log likelihood of f(p) = 0, 0.5 * (m^2 / total + log(2 pi total));
    * ``'residual'``: the standardized residual |m| / sqrt(total), the square root of twice the NLL's data term.
      It drops the log-variance term, which varies from view to view with how densely training covered a region
      (measured: docs/results.md, "The per-cloud NLL") and carries no information about the point itself, and it
      is unitless (in standard deviations), so one colour range serves every part.
    * ``'distance'``: d = m / max(|grad m|, ``GRADIENT_FLOOR``), the first-order signed distance to the mean
      surface (world units), standardized against good scans at the same place, |d - d_ref| / sqrt(s_ref^2 +
      noise^2), where d_ref and s_ref are the mean and standard deviation of d over the ``REFERENCE_NEIGHBOURS``
      nearest points of good scans, each under its own projected field (a :class:`inspection.reference.LocalReference`). A field that
      misses the part in the same way on every good scan (a rounded edge, a drifting face) then stops looking
      anomalous there: the noise floor is modelled per location. The distance rather than E f itself:
      E f is an integral of the GP's normal field, which vanishes two kernel lengthscales off the points, so E f
      saturates there: a pit or a bump deeper than that scores no higher than a shallow one under E f,
      ``'residual'`` or ``'nll'``, and no higher than the model's own error on good parts at a hard feature. d
      follows the depth while |grad m| >= the floor and then stays at |m| / floor: points off the field's shell
      are lifted by up to 1 / floor = 5 x relative to points near the mean surface (where |grad m| ~ 1), which is
      where the defects are and good scans are not (figures: docs/results.md#the-per-point-score).
    * ``'joint'`` (the default with a reference): the ``'distance'`` score z_d and the reference surface's z_s (:meth:`LocalReference.surface_scores`:
      the point's offset from the plane through its nearest good-scan points) taken together as two independent
      standardized residuals, each over its variance on good scans, sqrt((z_d^2 / v_d + z_s^2 / v_s) / 2)
      (:func:`joint_score`, :func:`fit_term_variances`). The projected field errs at a scan's borders and at
      grazing angles, where the good scans' points still lie on the part; the good scans' points do not follow the
      scan's own field and are noisy and sparse, where the field is smooth. A point scores high only when its
      residual is large under both on average, in the same units as the other scores.
    * ``'surface'``: z_s alone, the model-free term of ``'joint'``: what the good scans' points say without any
      field (a baseline: whether the model adds anything, ``python -m benchmarks ablation --trees``).
    * ``'agreement'``: the same two terms, sqrt(z_d z_s) (:func:`agreement_score`): a point counts only as far as
      both say it is off. Surface the good scans' points never showed (z_s high) is not accused where the projected
      field explains it (z_d low), and the field's own error at an edge (z_d high) is not where the good points lie
      on the part (z_s low). In standard deviations, as ``'joint'``.

    Parameters
    ----------
    field : object with ``mean(x)`` and ``variance(x)`` ((m, 3) -> (m,)) and a ``noise`` attribute
        E.g. a :class:`autodecoder.StochasticField`.
    points : (m, 3) array
        In the field's frame.
    kind : str
        A name of :data:`POINT_SCORES`.
    noise : float, optional
        Measurement noise standard deviation (the noise floor), in the field's length units; default
        ``field.noise``.
    reference : LocalReference
        Needed by the scores with ``POINT_SCORES[kind].reference`` (``'distance'`` and ``'joint'``).
    normals, origin : (m, 3) array and (3,) array, optional
        The scan's normals and sensor origin: with both, the reference scores' noise grows where the sensor's ray
        grazes the surface (:func:`autodecoder.scanning.sensor.grazing_factor`, weighted by the reference's ``grazing_scale``); with the
        normals, ``'joint'``'s reference surface is fitted through points on the same side
        (:meth:`LocalReference.surface`).

    Returns
    -------
    (m,) float64 array
    """
    if kind not in POINT_SCORES:
        raise ValueError(f"point_score must be one of {tuple(POINT_SCORES)}, got {kind!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (m, 3), got {points.shape}")
    if len(points) == 0:
        raise ValueError("points: the scan has no points to score")
    noise = noise_floor(field, noise)
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    if POINT_SCORES[kind].reference:
        if reference is None:
            raise ValueError(f"point_score {kind!r} needs a LocalReference (calibrate with the training scans)")
        value, variance = field_quantity(field, points, reference.quantity, with_variance=True)
        from autodecoder.scanning.sensor import grazing_factor

        grazing = None if origin is None or normals is None else grazing_factor(points, normals, origin)
        return reference_scores(reference, kind, points, value, variance, noise, grazing, normals)
    mean = np.asarray(field.mean(points), dtype=np.float64)
    var = np.maximum(np.asarray(field.variance(points), dtype=np.float64), 0.0)
    total = np.maximum(var + noise**2, _MIN_VARIANCE)
    if kind == "residual":
        return np.abs(mean) / np.sqrt(total)
    return 0.5 * (mean**2 / total + np.log(2 * math.pi * total))


def joint_score(distance_scores, surface_scores, variances=(1.0, 1.0)):
    """sqrt((z_d^2 / v_d + z_s^2 / v_s) / 2) of two standardized residuals of the same points, elementwise.

    Under a good part each residual is ~N(0, v) with its own variance v, which good scans show
    (:func:`fit_term_variances`); taken as independent, -log of their joint density is (z_d^2 / v_d + z_s^2 / v_s) / 2
    up to a constant, and its square root keeps the score in standard deviations (a point off by one of its term's
    good spread under both terms scores 1), which the log-normal tail of :mod:`inspection.threshold` and the maps'
    fixed colour range expect. A term whose residuals spread more on good scans of this part (the field's at the
    edges of a real part, the good points' under placement) counts less; (1, 1), equal weights, is the score of a
    calibration stored before the variances were fitted.

    Parameters
    ----------
    distance_scores, surface_scores : (m,) arrays >= 0
    variances : (v_d, v_s), positive floats
        The two terms' variances on good scans.

    Returns
    -------
    (m,) float64 array
    """
    a, b = _paired(distance_scores, surface_scores, "joint_score")
    v_d, v_s = checked_term_variances(variances)
    return np.sqrt((a**2 / v_d + b**2 / v_s) / 2)


def agreement_score(distance_scores, surface_scores, variances=(1.0, 1.0)):
    """sqrt((z_d / sqrt(v_d)) (z_s / sqrt(v_s))) of two standardized residuals of the same points, elementwise: the
    geometric mean of the two terms, each in its good spread (``variances`` as in :func:`joint_score`), in standard
    deviations (a point 2 deviations off under both scores 2, one 8 off under one and 0.5 under the other 2).

    Parameters
    ----------
    distance_scores, surface_scores : (m,) arrays >= 0
    variances : (v_d, v_s), positive floats

    Returns
    -------
    (m,) float64 array
    """
    a, b = _paired(distance_scores, surface_scores, "agreement_score")
    v_d, v_s = checked_term_variances(variances)
    return np.sqrt(np.maximum(a, 0.0) / math.sqrt(v_d) * np.maximum(b, 0.0) / math.sqrt(v_s))


def fit_term_variances(distance_scores, surface_scores):
    """The variances (v_d, v_s) of the two terms of ``'joint'`` on good scans, each fitted robustly.

    Each term is modelled on the points of good scans the model and the reference did not see (held-back scans,
    training scans scored by fold models or cross-fitted; their stray returns left out by the caller) as z ~ N(0, v),
    and v is estimated by median(z^2) / ``CHI2_1_MEDIAN`` (the median of a chi-square with one degree of freedom): the
    variance's maximum-likelihood value, mean(z^2), when the terms are Gaussian, but not set by a few scans' far
    points. Why: each term is standardized by its own noise model, and on a given part one of them may still spread
    more than the other (the field's term on a real part's side views, the good points' under placement); weighing
    each by what good scans show is what makes their sum a likelihood. Why the median: with few training scans a
    cross-fitted scan carries surface that no other training scan saw, which inflates the good points' mean square
    (and so weighs that term down) although new scans, compared with every training scan, never show it; the mean
    square also weighed the 8-training-scan benchmarks' maps down where the median does not (figures:
    docs/results.md, issue 28).

    Parameters
    ----------
    distance_scores, surface_scores : (n,) arrays >= 0
        The terms of the same points (``'joint'`` takes the field's term where the good points' has no surface).

    Returns
    -------
    (v_d, v_s) : floats >= ``MIN_TERM_VARIANCE``
    """
    a, b = _paired(distance_scores, surface_scores, "fit_term_variances")
    if a.size == 0 or not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError(f"fit_term_variances needs finite residuals of at least one point, got {a.size} points")
    return tuple(max(float(np.median(z**2)) / CHI2_1_MEDIAN, MIN_TERM_VARIANCE) for z in (a, b))


def _paired(distance_scores, surface_scores, who):
    """The two terms of the same points as float64 arrays; a ValueError naming ``who`` when their shapes differ."""
    a = np.asarray(distance_scores, dtype=np.float64)
    b = np.asarray(surface_scores, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"{who} needs one surface score per distance score, got shapes {a.shape} and {b.shape}")
    return a, b


def reference_terms(reference, points, value, variance, noise, grazing=None, normals=None, uncovered=None,
                    field=None):
    """The two terms (z_d, z_s) of ``'joint'`` for (m, 3) points (arguments as in :func:`reference_scores`), before
    their variances weigh them: the field's distance residual against good scans there, and the offset from the good
    scans' own surface; the field's term stands for the good points' where ``uncovered`` and where no good scan saw
    the point's side of the surface.

    Why the second: with the points' normals, the good points' plane is fitted through good points on the point's
    side (:meth:`inspection.reference.LocalReference.surface`); where fewer than 3 of them are (``supported``
    False: the face of a thin wall no training view saw, an enclosure's inside seen from below), the plane comes
    from the wall's other face, a wall's thickness away, and a good scan's points there read as far off as a
    defect's. The good points cannot speak where no good scan looked; the projected field, which saw this scan, can
    (as for a training scan left out of the reference, :func:`inspection.calibrating.uncovered_points`). Measured:
    docs/results.md, "Faces no good scan saw". A reference stored before this rule
    (``reference.field_on_unseen_faces`` False) keeps the good points' term there, as it was calibrated.

    ``field``: the scan's projected field. Where the reference's good scans are members of a family that differ in
    shape (``reference.member_spread``), the good points' term compares with their surface carried to this scan's
    member by it (:mod:`inspection.member_surface`). Returns two (m,) float64 arrays."""
    distance = reference.standardized(points, value, variance, noise, grazing)
    carried = None
    if field is not None and getattr(reference, "member_spread", None) is not None:
        from .member_surface import carried_surface_scores

        carried = carried_surface_scores(reference, reference.member_spread, field, points, noise, grazing, normals)
    if carried is None:
        carried = reference.surface_scores(points, noise, grazing, normals, with_support=True)
    surface, supported = carried
    unseen = ~supported if reference.field_on_unseen_faces else np.zeros(len(distance), dtype=bool)
    if uncovered is not None:
        unseen |= np.asarray(uncovered, dtype=bool)
    return distance, np.where(unseen, distance, surface)


def reference_scores(reference, kind, points, value, variance, noise, grazing=None, normals=None, uncovered=None,
                     terms=None, field=None):
    """The per-location point score ``kind`` (``'distance'``, ``'joint'``, ``'agreement'`` or ``'surface'``) of (m, 3)
    points whose compared quantity (m,) and field variance (m,) are given, against ``reference`` (a
    :class:`inspection.reference.LocalReference`); ``grazing`` (m,) and the points' ``normals`` (m, 3) (for the
    reference surface's side) or None. ``uncovered`` (m,) bool or None: points where the reference has no good
    surface to compare with (a training scan left out of it, :func:`inspection.calibrating.uncovered_points`); there
    ``'joint'`` and ``'agreement'`` take the field's term for the good points' term. These two weigh their terms by
    the reference's ``term_variances`` (:func:`fit_term_variances`). ``terms``: (z_d, z_s) of
    :func:`reference_terms` already computed for these points (``'joint'`` and ``'agreement'`` only). ``field``: the
    scan's projected field, whose member the good surface is carried to in those two (:func:`reference_terms`).
    Returns (m,) float64."""
    if kind == "surface":
        return reference.surface_scores(points, noise, grazing, normals)
    if kind in WEIGHED_SCORES:
        if terms is None:
            terms = reference_terms(reference, points, value, variance, noise, grazing, normals, uncovered, field)
        combine = joint_score if kind == "joint" else agreement_score
        return combine(*terms, variances=reference.term_variances)
    return reference.standardized(points, value, variance, noise, grazing)
