"""Tolerances in the scan files' units, as a production line states them (a profile tolerance of GD&T: how far the
surface may depart from where good parts put it, and over how much area), judged on a scan's defect regions
(:mod:`inspection.regions`) beside the statistical verdict.

``--tolerance DEV[,AREA]``, e.g. ``0.2mm,4mm2`` or ``0.2,4``: a scan is out of tolerance when one of its regions
departs by more than DEV (its largest signed deviation, either way) over more than AREA (its footprint's area; 0
when not given). The numbers are in the scan files' units (millimetres when the scans are); a unit written after
them is read as a reminder of that, not converted: mm, mm2, mm^2, um or none.
"""
import re
from dataclasses import dataclass

_NUMBER = r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)"
_LENGTH = re.compile(rf"^{_NUMBER}\s*(mm|um|m)?$")
_AREA = re.compile(rf"^{_NUMBER}\s*(mm2|mm\^2|um2|um\^2|m2|m\^2)?$")


@dataclass(frozen=True)
class Tolerance:
    """A tolerance on defect regions: ``deviation`` (> 0) and ``area`` (>= 0), in the scan files' units."""

    deviation: float
    area: float = 0.0

    @classmethod
    def parse(cls, text):
        """The tolerance of ``DEV[,AREA]`` (module docstring); a ValueError saying what is wrong with ``text``."""
        parts = [p.strip() for p in str(text).split(",")]
        length = _LENGTH.match(parts[0]) if parts and parts[0] else None
        area = _AREA.match(parts[1]) if len(parts) == 2 else None
        if length is None or len(parts) > 2 or (len(parts) == 2 and area is None):
            raise ValueError(f"--tolerance must be DEV[,AREA] with positive numbers in the scans' units, e.g. "
                             f"0.2mm,4mm2 or 0.2; got {text!r}")
        deviation = float(length.group(1))
        if not deviation > 0:
            raise ValueError(f"--tolerance: the deviation must be > 0, got {text!r}")
        return cls(deviation, float(area.group(1)) if area else 0.0)

    def exceeded_by(self, regions):
        """The regions (:class:`inspection.regions.DefectRegion`) out of this tolerance."""
        return [r for r in regions if abs(r.deviation) > self.deviation and r.area > self.area]

    def text(self):
        return f"deviation {self.deviation:g}" + (f" over an area of {self.area:g}" if self.area else "")


def judged(verdict, why, regions, tolerance):
    """The verdict with a tolerance beside the statistics.

    Parameters
    ----------
    verdict, why : str
        The statistical verdict and its words.
    regions : list of DefectRegion
        The scan's defect regions.
    tolerance : Tolerance or None

    Returns
    -------
    dict
        ``verdict`` ('defective' when either says so), ``tolerance`` ('out' / 'within', None without one),
        ``decided_by`` ('statistics', 'tolerance', 'both', or '' for a scan neither calls defective) and ``why``.
    """
    statistical = verdict == "defective"
    if tolerance is None:
        return {"verdict": verdict, "tolerance": None, "decided_by": "statistics" if statistical else "", "why": why}
    out = tolerance.exceeded_by(regions)
    decided = {(True, True): "both", (True, False): "statistics", (False, True): "tolerance"}.get((statistical,
                                                                                                   bool(out)), "")
    if out and not statistical:
        worst = max(out, key=lambda r: abs(r.deviation))
        why = (f"out of tolerance ({tolerance.text()}): a {worst.kind} of {worst.deviation:+.3g} over "
               f"{worst.area:.3g}" + (f"; the statistics said {verdict}" if verdict else ""))
    return {"verdict": "defective" if out or statistical else verdict, "tolerance": "out" if out else "within",
            "decided_by": decided, "why": why}
