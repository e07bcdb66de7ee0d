"""Whether a batch of scans looks like the good scans the threshold was drawn from: a binomial check of the batch.

A threshold promises its false-alarm rate only for good scans like the calibration's. Scans from another sensor
(noisier, sparser, another stand-off, ragged borders) or of a part in other units can all score above it: every good
part is then called defective while the note promises 2 %. Labels are not needed to see it, if a share of the batch
is good. Under the hypothesis H0 "at least ``1 - max_defective_share`` of the batch are good scans that score like
the calibration's" (``max_defective_share``, pi, is the largest share of defective parts the user expects in a batch;
scikit-learn calls it contamination):

* each scan lies above the threshold with probability at most pi + (1 - pi) alpha: a count of scans above it
  beyond a binomial's upper tail is unlikely under H0;
* each scan lies below the calibration scores' median (p-value > 1/2) with probability at least (1 - pi) / 2: a
  batch with too few such scans (none of its scans looks like a typical good calibration scan) is unlikely too.

Either test's binomial tail below ``level / 2`` fires the check (a Bonferroni pair). Fired, the verdicts are told
apart by what the batch can still say: a scan above the threshold stays ``'defective'`` only when its score lies
beyond the threshold moved up by the batch's whole shift (the batch's median log score over the calibration's: the
largest shift a batch with any share of defective scans can show, defective scans only raising the median), else
it is ``'uncertain'`` (check the sensor, calibrate on its good scans): a good scan of a shifted sensor is not called
defective for the shift, and a scan that is defective whatever the shift still is. No scan is passed as good by
the check.

The default pi = 0.8: the benchmarks' test batches hold 64 defective scans in 80; with a smaller pi those batches,
from the calibration's own sensor, would fire the check. A production batch holds far fewer defective parts: a
user who says so (``--max-defective-share 0.2``) makes the check sensitive on small batches: at 0.8 a batch of 16
good scans of a shifted sensor cannot fire it (the lower test's tail at 0 of 16 below the median is 0.9^16 = 0.19),
a batch of 50 can (0.9^50 = 0.005, below the level's half, 0.01); at 0.2, 16 can (0.6^16 = 0.0003).
"""
import math
from dataclasses import asdict, dataclass

import numpy as np

DEFAULT_MAX_DEFECTIVE_SHARE = 0.8
DEFAULT_LEVEL = 0.02  # the pair of tests fires at most at this probability under H0 (each at half of it)
MIN_BATCH = 8  # fewer scans say nothing either way at the default share


@dataclass
class BatchCheck:
    """The outcome of :func:`check_batch` (summary.json's ``batch_check``).

    Attributes
    ----------
    fired : bool
        The batch does not look like the calibration's good scans (either test below ``level / 2``).
    n : int
        Scans checked (scored).
    above : int
        Of them above the threshold.
    below_median : int
        Of them below the calibration scores' median (p-value > 1/2).
    p_above, p_below_median : float
        The two binomial tails under H0 (module docstring); 1.0 when the batch is too small to judge.
    max_defective_share, level : float
        pi and the check's level.
    shift : float
        The batch's median log score minus the calibration's median log score (a factor exp(shift) on the scores).
    shifted_threshold : float
        The threshold times exp(max(shift, 0)): above it a scan is defective even if the whole batch had moved.
    message : str
        One line for the user ('' when the check did not fire).
    """

    fired: bool
    n: int
    above: int
    below_median: int
    p_above: float
    p_below_median: float
    max_defective_share: float
    level: float
    shift: float
    shifted_threshold: float
    message: str = ""

    def as_dict(self):
        d = asdict(self)
        d["shifted_threshold"] = None if not math.isfinite(self.shifted_threshold) else self.shifted_threshold
        return d

    def verdict(self, score, verdict):
        """The verdict of a scan scored ``score`` that the threshold alone called ``verdict``, in this batch:
        ``'defective'`` becomes ``'uncertain'`` when the check fired and the score lies within the batch's shift."""
        if self.fired and verdict == "defective" and not score > self.shifted_threshold:
            return "uncertain"
        return verdict


def check_max_defective_share(share):
    """``share`` as a float in [0, 1), or a ValueError naming it."""
    try:
        share = float(share)
    except (TypeError, ValueError):
        raise ValueError(f"max_defective_share must be a number in [0, 1), got {share!r}") from None
    if not 0 <= share < 1:
        raise ValueError(f"max_defective_share must be in [0, 1), got {share!r}")
    return share


def check_batch(scores, p_values, threshold, alpha, calibration_median, max_defective_share=DEFAULT_MAX_DEFECTIVE_SHARE,
                level=DEFAULT_LEVEL):
    """Check a batch's scores against the calibration they were judged by (module docstring).

    Parameters
    ----------
    scores : (n,) array
        The batch's anomaly scores (scans that could not be scored left out).
    p_values : (n,) array
        Their p-values under the threshold's calibration (:meth:`inspection.threshold.Threshold.p_values`).
    threshold : float
        The decision threshold (a scan above it is flagged).
    alpha : float
        The rate the p-values are compared with (``alpha_used``).
    calibration_median : float
        The median of the calibration's good scores (positive), on the scale of ``scores``.
    max_defective_share : float in [0, 1)
        pi: the largest share of defective scans a batch may hold under H0.
    level : float in (0, 1)
        The probability under H0 of firing.

    Returns
    -------
    BatchCheck
    """
    from scipy import stats

    share = check_max_defective_share(max_defective_share)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    p = np.asarray(p_values, dtype=np.float64).reshape(-1)
    if scores.shape != p.shape:
        raise ValueError(f"scores and p_values differ in length: {len(scores)} and {len(p)}")
    n = len(scores)
    above = int(np.sum(scores > threshold))
    below = int(np.sum(p > 0.5))
    p_above = p_below = 1.0
    if n >= MIN_BATCH:
        p_above = float(stats.binom.sf(above - 1, n, min(1.0, share + (1 - share) * alpha)))
        p_below = float(stats.binom.cdf(below, n, (1 - share) / 2))
    positive = scores[scores > 0]
    shift = 0.0
    if len(positive) and calibration_median > 0:
        shift = float(np.median(np.log(positive)) - math.log(calibration_median))
    shifted = threshold * math.exp(max(shift, 0.0)) if math.isfinite(threshold) else threshold
    fired = bool(min(p_above, p_below) < level / 2)
    message = ""
    if fired:
        message = (f"these scans do not look like the good scans the threshold was drawn from: {above} of {n} lie "
                   f"above it and {below} below the calibration's median score, which a batch with at least "
                   f"{100 * (1 - share):.0f} % good scans like the calibration's shows with probability "
                   f"{min(p_above, p_below):.2g}; their scores lie a factor {math.exp(shift):.2g} above the "
                   f"calibration's (another sensor, noise or stand-off? other units?). Scans above the threshold "
                   f"but not above {shifted:.4g} (the threshold moved by the batch's whole shift) are told "
                   f"'uncertain', not 'defective'; calibrate on a few good scans of this sensor "
                   f"(`nsspr-inspect calibrate --model MODEL --data GOOD_SCANS`)")
    return BatchCheck(fired, n, above, below, p_above, p_below, share, level, shift, shifted, message)


def calibration_median(insp):
    """The median of an inspector's good calibration scores that set its level (out of sample: held back, by fold
    models, or the site's), the scale :func:`check_batch` measures the batch's shift on."""
    from .threshold import OUT_OF_SAMPLE

    roles = np.asarray(insp.calibration_roles_)
    scores = np.asarray(insp.calibration_scores_, dtype=np.float64)
    site = roles == "site"
    chosen = scores[site] if site.any() else scores[np.isin(roles, OUT_OF_SAMPLE)]
    chosen = chosen if len(chosen) else scores
    return float(np.median(chosen))


def check_rows(one, rows, max_defective_share=DEFAULT_MAX_DEFECTIVE_SHARE):
    """:func:`check_batch` of the scored ``rows`` (dicts with ``score``, ``p_value``, ``verdict``: scores.csv's and
    the watch journal's) against the calibrated single-part inspector ``one``."""
    scored = [r for r in rows if r.get("verdict") != "error" and r.get("score") is not None]
    t = one.decision_threshold_
    return check_batch([r["score"] for r in scored], [r["p_value"] for r in scored], t.value, t.alpha_used,
                       calibration_median(one), max_defective_share)


def retell(row, check):
    """``row`` (a scored scan's dict) with its verdict as the batch ``check`` tells it (:meth:`BatchCheck.verdict`):
    a 'defective' turned 'uncertain' says why in ``why``. Returns whether it changed."""
    if row.get("verdict") == "error" or row.get("score") is None:
        return False
    verdict = check.verdict(float(row["score"]), row["verdict"])
    if verdict == row["verdict"]:
        return False
    row["verdict"] = verdict
    row["why"] = (f"{row.get('why', '')}; but the batch does not look like the calibration's good scans (their "
                  f"scores lie a factor {math.exp(check.shift):.2g} above them) and this score is not above "
                  f"{check.shifted_threshold:.4g}, the threshold moved by that shift: uncertain (check the sensor, "
                  f"calibrate on a few of its good scans)")
    return True


def check_run(insp, scans, rows, max_defective_share=DEFAULT_MAX_DEFECTIVE_SHARE, uncertain=True):
    """The batch check of a ``score`` run: per part type (a model of several: the scans' parts), each part's scored
    rows checked and, with ``uncertain``, retold (:func:`retell`). ``rows`` line up with ``scans`` (error rows of
    scans that could not be read come after them). Returns summary.json's ``batch_check``: a
    :meth:`BatchCheck.as_dict` (one part) or {part: that} (several), each with ``retold``, the verdicts it turned
    from 'defective' to 'uncertain'."""
    groups = {}
    for scan, row in zip(scans, rows):
        try:
            one = insp.for_scan(scan)
        except ValueError:  # an unknown part: an error row already
            continue
        groups.setdefault(id(one), (one, []))[1].append(row)
    out = {}
    for one, members in groups.values():
        part = next((p for p, o in (insp.parts_ or {}).items() if o is one), None)
        check = check_rows(one, members, max_defective_share)
        retold = sum(retell(r, check) for r in members) if uncertain else 0
        out[part] = {**check.as_dict(), "retold": int(retold)}
    if not insp.parts_:
        return out.get(None)
    return out
