"""Which good scans calibrate a model and which give its per-location reference: the one rule, for the API and the CLI.

A model that was trained on a collection records its training scans (``train_names``, with their ``train_part_ids``)
and the good scans its trainer held back for calibration (``calibration_names``). Given good scans, the rule is:

* **calibration scans** (scored as new scans would be; they set the threshold): the model's held-back scans when
  any of them are among the scans given; otherwise every given scan the model did not train on. With a ``split``,
  that split's good scans the model did not train on (held-back ones included).
* **reference scans** (projected without their own trained code to give :class:`inspection.reference.LocalReference`,
  then cross-fitted into the calibration): up to ``MAX_REFERENCE_SCANS`` of the model's training scans among those
  given, evenly spread over the training order; with explicit reference scans, up to as many of those.
* **surface scans** (the good scans' own points, :meth:`inspection.reference.LocalReference.surface`): every training
  scan given (a subset can miss a region few views saw).

A model of several part types (two or more distinct ``train_part_ids``) applies the rule per part: a scan's part is
its ``part_id`` (:func:`model_parts`).
"""
from dataclasses import dataclass, field
from typing import List

import numpy as np

# training scans projected for the per-location reference, at most (each is one projection, the calibration's cost)
MAX_REFERENCE_SCANS = 32


def model_parts(model):
    """The part ids a latent model was trained on, sorted, when there are two or more; else [] (one part)."""
    parts = sorted({str(p) for p in (getattr(model, "train_part_ids", None) or []) if p})
    return parts if len(parts) >= 2 else []


@dataclass
class ScanSelection:
    """Good scans sorted into their roles (module docstring); ``how`` says in words where the calibration scans came
    from (it goes into the calibration record and the command line's report)."""

    calibration: List[object]
    reference: List[object] = field(default_factory=list)
    surface: List[object] = field(default_factory=list)
    how: str = ""


def _names(model):
    train = [str(n) for n in (getattr(model, "train_names", None) or [])]
    held = [str(n) for n in (getattr(model, "calibration_names", None) or [])]
    parts = [str(p) for p in (getattr(model, "train_part_ids", None) or [""] * len(train))]
    return train, held, parts


def _evenly(items, n):
    """Up to ``n`` of ``items`` evenly spread (all of them when there are fewer), in their order."""
    if len(items) <= n:
        return list(items)
    pick = np.unique(np.linspace(0, len(items) - 1, n).round().astype(int))
    return [items[i] for i in pick]


def select_scans(model, scans, reference_scans=None, split=None, part=None, training_scans_given=True):
    """Sort good ``scans`` into calibration, reference and surface scans by the module's rule.

    Parameters
    ----------
    model : latent model or field
        Read for ``train_names``, ``calibration_names`` and ``train_part_ids`` (absent: no scan is a training scan).
    scans : sequence of Scan
        Good scans (each with a ``name``; ``split`` and ``part_id`` when it has them).
    reference_scans : sequence of Scan, optional
        Explicit reference scans (usually the model's training scans); None: the training scans among ``scans``.
    split : str, optional
        Calibrate on this split's scans only.
    part : str, optional
        Keep only scans of this part id (a model of several part types).
    training_scans_given : bool
        False when ``scans`` come from other data than the model's training collection: no scan is then taken for
        a training scan because of its name (a scan named like one is left out of the calibration all the same).

    Returns
    -------
    ScanSelection
    """
    train, held, part_ids = _names(model)
    train_set, held_set = set(train), set(held)
    scans = [s for s in scans if part is None or str(getattr(s, "part_id", "") or "") == part]
    by_name = {getattr(s, "name", None): s for s in scans}
    if reference_scans is None:
        present = [n for n, p in zip(train, part_ids) if training_scans_given and n in by_name
                   and (part is None or p == part)]
        surface = [by_name[n] for n in present]
    else:
        surface = [s for s in reference_scans if part is None or str(getattr(s, "part_id", "") or "") == part]
    reference = _evenly(surface, MAX_REFERENCE_SCANS)
    not_trained = [s for s in scans if getattr(s, "name", None) not in train_set or s.name in held_set]
    if split is not None:
        calibration = [s for s in not_trained if getattr(s, "split", None) == split]
        how = f"good scans of split {split!r} the model did not train on"
    elif held_set and any(s.name in held_set for s in not_trained if getattr(s, "name", None)):
        calibration = [s for s in not_trained if s.name in held_set]
        how = f"the model's {len(calibration)} held-back good scan{'' if len(calibration) == 1 else 's'}"
    else:
        calibration = not_trained
        how = "good scans the model did not train on"
    if part is not None:
        how += f", part {part}"
    return ScanSelection(calibration, reference, surface, how)
