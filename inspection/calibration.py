"""The calibration a model file stores: the fitted state an inspector scores with, its record, the record's versions.

:class:`FittedState` is one part type's calibration in memory (what :func:`inspection.calibrating.calibrate` fits);
:class:`Calibration` is the record of plain values a model file keeps under ``"calibration"``. A record carries its
``version``; :func:`migrate` upgrades a record of any older version, one version at a time, to
``CALIBRATION_VERSION``, and everything that reads a record reads that version only. The thresholds drawn from the
scores are :mod:`inspection.threshold`'s.
"""
from dataclasses import asdict, dataclass, field
from typing import List, Optional

import numpy as np

from .threshold import DEFAULT_ALPHA, fit_threshold

CALIBRATION_KEY = "calibration"
# 2: every record holds each entry of ``extra`` (``EXTRA_KEYS``), one role per score, its settings whole with ``align``
# decided, and its per-location reference complete (version 1 records may lack any of these: :func:`migrate`);
# 3: its settings hold ``coverage`` (a version 2 record scored every point: coverage 0)
# 4: ``extra['regions']``, the good calibration scans' largest map values (:mod:`inspection.regions`)
# 5: the reference's ``member_spread`` (:mod:`inspection.member_surface`)
# 6: the member spread's envelope of the trained members (``low``, ``high``, ``own``: :mod:`inspection.family_range`)
CALIBRATION_VERSION = 6
EXTRA_KEYS = ("config", "reading", "parts", "level_rendered", "reference", "rays", "align", "regions")


@dataclass
class FittedState:
    """One part type's calibration in memory: what :func:`inspection.calibrating.calibrate` fits, what a
    :class:`Calibration` record stores, and what :class:`inspection.Inspector` scores with (its fitted attributes).

    Attributes
    ----------
    settings : InspectionConfig
        The settings in force: 'auto' decided, ``align`` True or False.
    scores : (n,) float64 array
        Anomaly scores of the good calibration scans.
    names, roles : list of str
        Their names and roles (:class:`Calibration`).
    source : str
        Where the calibration scans came from, in words.
    reference : inspection.reference.LocalReference or None
        The per-location reference (the point scores with one).
    combination : inspection.combine.Combination or None
        The rays' weighing (with rays).
    aligner : inspection.align.Aligner or None
        The registration target (``settings.align`` True).
    alignment_note : str
        One line when the calibration decided to register the scans ('' otherwise, and for a stored record).
    level_rendered : bool
        Whether the threshold's level rests on views rendered from clean templates alone.
    region_maxima : (n,) float array or None
        The largest anomaly map value of each good calibration scan (:func:`inspection.regions.map_maximum`), in
        the order of ``scores``: what the region level is drawn from (None: not measured, no regions).
    region_roles : list of str or None
        Their roles (None: ``roles``; they differ once a site's scans set the level, which adds no map maxima).
    """

    settings: object
    scores: np.ndarray
    names: List[str]
    roles: List[str]
    source: str = ""
    reference: object = None
    combination: object = None
    aligner: object = None
    alignment_note: str = ""
    level_rendered: bool = False
    region_maxima: object = None
    region_roles: object = None


@dataclass
class Calibration:
    """What the model file stores under ``"calibration"``: enough to score new scans without other data.

    Attributes
    ----------
    scores : list of float
        Anomaly scores of the good calibration scans.
    names : list of str
        Their scan names.
    aggregate, point_score : str
        How the scores were computed (see :mod:`inspection.scores`); scoring must use the same.
    noise : float or None
        The noise floor used (None: the field's own).
    alpha : float
        Default false-alarm rate.
    source : str
        Where the calibration scans came from (a file, "held-back", ...).
    fingerprint : str
        Fingerprint of the collection they came from ('' when unknown).
    version : int
        ``CALIBRATION_VERSION`` (:func:`migrate` upgrades older records).
    extra : dict
        Every key of ``EXTRA_KEYS``: ``config`` (the settings in force, :meth:`InspectionConfig.as_dict`),
        ``reading`` (how scanner files are read, :mod:`inspection.loading`; or None), ``parts`` (a model of several
        part types: one record per part as a dict; else None), and for a single part ``level_rendered``,
        ``reference`` (:meth:`LocalReference.as_dict` or None), ``rays`` (``{"components": ...}``, the
        :class:`inspection.combine.Combination`, or None), ``align`` (the :class:`inspection.align.Aligner` or
        None) and ``regions`` (``{"maxima": [...], "roles": [...]}``, the good calibration scans' largest map
        values and their roles, or None: no regions).
    roles : list of str
        For each score, ``'held-back'`` (a good scan the model did not train on), ``'fold'`` (a training scan scored
        by a fold model that never trained on it), ``'cross-fitted'`` (a training scan scored by the model as if
        new, :meth:`inspection.Inspector.fit`) or ``'site'`` (:meth:`inspection.Inspector.fit_level`).
    """

    scores: List[float]
    names: List[str]
    aggregate: str
    point_score: str
    noise: Optional[float] = None
    alpha: float = DEFAULT_ALPHA
    source: str = ""
    fingerprint: str = ""
    version: int = CALIBRATION_VERSION
    extra: dict = field(default_factory=dict)
    roles: List[str] = field(default_factory=list)

    def threshold(self, alpha=None):
        """The :class:`inspection.threshold.Threshold` of these scores at ``alpha`` (default: the stored one)."""
        return fit_threshold(self.scores, self.alpha if alpha is None else alpha, self.roles or None)

    def config(self):
        """The :class:`inspection.config.InspectionConfig` the scores were computed with (its 'auto' settings
        decided)."""
        from .config import InspectionConfig

        return InspectionConfig.from_dict(self.extra["config"])

    @property
    def reading(self):
        """How the calibration's collection read its scanner files (a dict; None for scans given as a list)."""
        return self.extra["reading"]

    def parts(self):
        """A model of several part types: its part id -> that part's :class:`Calibration`, sorted; else None."""
        parts = self.extra["parts"]
        return None if not parts else {p: Calibration.from_dict(r) for p, r in sorted(parts.items())}

    def state(self):
        """The :class:`FittedState` a single-part record stores (a ValueError for a record that cannot score: its
        rays combined by a retired rule, or registration without its target)."""
        extra = self.extra
        settings = self.config()
        if extra["reference"] is None:
            reference = None
        else:
            from .reference import LocalReference

            reference = LocalReference.from_dict(extra["reference"])
        aligner = None
        if settings.align is True:
            if extra["align"] is None:
                raise ValueError("its settings say align=True but it stores no alignment target")
            from .align import Aligner

            aligner = Aligner.from_dict(extra["align"])
        combination = None
        if extra["rays"] is not None:
            from .combine import Combination

            combination = Combination.from_dict(extra["rays"]["components"])
        regions = extra["regions"]
        maxima = None if regions is None else np.asarray(regions["maxima"], dtype=np.float64)
        return FittedState(settings, np.asarray(self.scores, dtype=np.float64), list(self.names), list(self.roles),
                           self.source, reference, combination, aligner, "", bool(extra["level_rendered"]), maxima,
                           None if regions is None else list(regions["roles"]))

    @classmethod
    def from_state(cls, state, alpha, source, fingerprint, reading=None, parts=None):
        """The record of a fitted state.

        Parameters
        ----------
        state : FittedState
            For a model of several part types, every part's scores together (only its settings, scores, names and
            roles are stored).
        alpha : float
            The default false-alarm rate.
        source, fingerprint : str
        reading : dict or None
        parts : dict of str -> Calibration, optional
            A model of several part types: each part's record.
        """
        settings = state.settings
        single = not parts
        if single and settings.rays and state.combination is None:
            raise ValueError("rays=True: the calibration stores the rays' weighing, and this state has none")
        extra = {"config": settings.as_dict(), "reading": reading,
                 "parts": None if single else {p: c.as_dict() for p, c in sorted(parts.items())},
                 "level_rendered": bool(state.level_rendered) if single else False,
                 "reference": state.reference.as_dict() if single and state.reference is not None else None,
                 "rays": {"components": state.combination.as_dict()} if single and settings.rays else None,
                 "align": state.aligner.as_dict() if single and state.aligner is not None else None,
                 "regions": ({"maxima": np.asarray(state.region_maxima, dtype=np.float64).tolist(),
                              "roles": list(state.roles if state.region_roles is None else state.region_roles)}
                             if single and state.region_maxima is not None else None)}
        return cls(scores=np.asarray(state.scores, dtype=np.float64).tolist(), names=list(state.names),
                   roles=list(state.roles), aggregate=settings.aggregate, point_score=settings.point_score,
                   noise=settings.noise, alpha=float(alpha), source=source, fingerprint=fingerprint, extra=extra)

    def as_dict(self):
        d = asdict(self)
        d["scores"] = [float(s) for s in self.scores]
        d["names"] = [str(n) for n in self.names]
        return d

    @classmethod
    def from_dict(cls, d, source="<model>"):
        """The record :meth:`as_dict` wrote, of this or any older version (:func:`migrate`)."""
        d = migrate(d, source)
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


def migrate(record, source="<model>"):
    """A calibration record (a dict as :meth:`Calibration.as_dict` writes it) of any version this toolkit wrote,
    upgraded one version at a time to ``CALIBRATION_VERSION`` (each part's record of a model of several part types
    too). The record given is not modified; a record of another version is a ValueError naming ``source``.

    Why: a model file outlives the code that calibrated it; its record must load and score as it was calibrated,
    and the code that reads records reads one layout, the current one.
    """
    version = record.get("version") if isinstance(record, dict) else record
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= CALIBRATION_VERSION:
        raise ValueError(f"{source}: calibration record of unsupported version {version!r} (this toolkit reads "
                         f"versions 1 to {CALIBRATION_VERSION})")
    record = dict(record)
    try:
        while record["version"] < CALIBRATION_VERSION:
            record = _UPGRADES[record["version"]](record)
    except (KeyError, TypeError, AttributeError) as exc:  # a damaged older record: one line naming the file
        raise ValueError(f"{source}: damaged calibration record of version {version} ({type(exc).__name__}: "
                         f"{exc})") from None
    missing = [k for k in ("scores", "names", "aggregate", "point_score", "extra") if k not in record]
    if not missing:
        extra = record["extra"]
        missing = ([f"extra[{k!r}]" for k in EXTRA_KEYS if k not in extra] if isinstance(extra, dict)
                   else ["extra (not a dict)"])
    if missing:
        raise ValueError(f"{source}: damaged calibration record: no {', '.join(missing)}; calibrate the model "
                         f"again")
    parts = record["extra"]["parts"]
    if parts:
        record["extra"] = {**record["extra"],
                           "parts": {p: migrate(r, f"{source}: part {p}") for p, r in parts.items()}}
    return record


def _from_version_1(record):
    """Version 1 -> 2. Version 1 records were written as the calibration grew; each entry missing from one is what
    the code of its time did without it: roles -> every scan held back; the settings from the separate fields
    (``projection`` under ``extra``, ray options under ``extra['rays']``); ``align`` 'auto' (stored before
    registration was a setting) -> False, never registered; no ``level_rendered``, ``reading``, ``parts``,
    ``reference``, ``rays`` or ``align`` -> False or None; a reference without its noise model, term variances or
    surface -> the reference alone (scales 0), equal weights (1, 1), the reference points as the surface, and the
    good points' term kept on faces no good scan saw (``field_on_unseen_faces`` False); rays combined without a
    named rule -> the retired ``'gated'`` (reading it asks to calibrate again)."""
    from .config import InspectionConfig
    from .reference import REFERENCE_NEIGHBOURS, REFERENCE_QUANTITY

    extra = dict(record.get("extra") or {})
    rays = extra.get("rays")
    if extra.get("config") is not None:
        config = dict(extra["config"])
    else:
        config = InspectionConfig(alpha=record.get("alpha", DEFAULT_ALPHA), aggregate=record["aggregate"],
                                  point_score=record["point_score"], noise=record.get("noise"),
                                  projection=extra.get("projection"), rays=rays is not None,
                                  ray_options=None if rays is None else dict(rays["options"])).validated().as_dict()
    if config.get("align", "auto") == "auto":
        config["align"] = False
    extra.pop("projection", None)
    extra["config"] = config
    for key in EXTRA_KEYS:
        extra.setdefault(key, False if key == "level_rendered" else None)
    if extra["reference"] is not None:
        extra["reference"] = {"k": REFERENCE_NEIGHBOURS, "quantity": REFERENCE_QUANTITY, "variance_scale": 0.0,
                              "grazing_scale": 0.0, "surface_points": None, "surface_normals": None,
                              "term_variances": [1.0, 1.0], "field_on_unseen_faces": False, **extra["reference"]}
    if rays is not None and isinstance(rays.get("components"), dict):
        extra["rays"] = {**rays, "components": {"rule": "gated", **rays["components"]}}
    roles = list(record.get("roles") or []) or ["held-back"] * len(record["scores"])
    return {**record, "version": 2, "extra": extra, "roles": roles}


def _from_version_2(record):
    """Version 2 -> 3: the settings get ``coverage`` 0, every point counted (:mod:`inspection.coverage`), as the
    scores of a version 2 record were."""
    extra = dict(record["extra"])
    extra["config"] = {**extra["config"], "coverage": 0.0}
    return {**record, "version": 3, "extra": extra}


def _from_version_3(record):
    """Version 3 -> 4: no ``regions`` (a version 3 calibration did not measure its good scans' maps): the model
    scores as calibrated and reports no defect regions until it is calibrated again."""
    return {**record, "version": 4, "extra": {**record["extra"], "regions": None}}


def _from_version_4(record):
    """Version 4 -> 5: the reference gets ``member_spread`` None (a version 4 calibration did not measure how its
    good scans' members differ): its good points' term compares with the surface as the good scans left it, as
    calibrated."""
    extra = dict(record["extra"])
    if extra["reference"] is not None:
        extra["reference"] = {**extra["reference"], "member_spread": None}
    return {**record, "version": 5, "extra": extra}


def _from_version_5(record):
    """Version 5 -> 6: a member spread gets no envelope (``low``, ``high``, ``own`` None: a version 5 calibration
    did not keep the trained members' range), so no scan is told it lies outside the trained family, as
    calibrated."""
    extra = dict(record["extra"])
    reference = extra["reference"]
    if reference is not None and reference.get("member_spread") is not None:
        extra["reference"] = {**reference, "member_spread": {**reference["member_spread"], "low": None, "high": None,
                                                             "own": None}}
    return {**record, "version": 6, "extra": extra}


# version -> the function that upgrades a record of that version to the next
_UPGRADES = {1: _from_version_1, 2: _from_version_2, 3: _from_version_3, 4: _from_version_4, 5: _from_version_5}


def read_calibration(path):
    """The :class:`Calibration` stored in a model file, or None when it has none."""
    from autodecoder.field.checkpoint_io import load_torch_file

    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (a {type(ckpt).__name__}, expected a dict)")
    record = ckpt.get(CALIBRATION_KEY)
    return None if record is None else Calibration.from_dict(record, source=str(path))


def write_calibration(path, calibration):
    """Store ``calibration`` in the model file at ``path`` (atomically: a temporary file renamed into place).

    The checkpoint is loaded as a dict, gets (or replaces) its ``"calibration"`` entry of plain Python values, and is
    written back; every other entry is untouched, so the model loads as before.
    """
    from autodecoder.field.checkpoint_io import atomic_torch_save, load_torch_file

    ckpt = load_torch_file(path, what="model checkpoint")
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: not a model checkpoint (a {type(ckpt).__name__}, expected a dict)")
    ckpt[CALIBRATION_KEY] = calibration.as_dict()
    atomic_torch_save(ckpt, path)
