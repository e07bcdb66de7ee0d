"""Thresholds from the scores of good scans: exact split-conformal when there are enough, a log-normal predictive
tail when there are not, each with the false-alarm rate it implies and a probability interval for it.

Split-conformal (the rule when there are enough scans)
------------------------------------------------------
With n calibration scores c_1..c_n of good scans the model did not train on, the p-value of a score s is

    p(s) = (1 + #{i : c_i >= s}) / (n + 1).

If good scans are exchangeable, P(p(s) <= alpha) <= alpha for a new good scan. Flagging p <= alpha is flagging
s > t, t the (k+1)-th largest calibration score with k = floor(alpha (n + 1) - 1); the false-alarm rate averaged over
calibration draws is (k + 1) / (n + 1), and the rate of one fixed threshold, F_bar(t), is Beta(k + 1, n - k)
distributed whatever the score's distribution (the coverage of an order statistic). It needs k >= 0, i.e.
n >= 1 / alpha - 1: 99 good scans for alpha = 0.01.

Log-normal predictive tail (fewer scans than that)
--------------------------------------------------
Scan scores here are positive and right-skewed (a mean of the worst point scores); their logarithm is modelled as
Normal(mu, sigma^2), both unknown. With y_i = log c_i, mean m and standard deviation s (n - 1 degrees of freedom),
a new good scan's y satisfies (y - m) / (s sqrt(1 + 1/n)) ~ Student t_{n-1} exactly (the predictive distribution).
So

    t = exp(m + t_{n-1}(1 - alpha) s sqrt(1 + 1/n)),   p(s) = T_{n-1, sf}((log s - m) / (s sqrt(1 + 1/n)))

flag a new good scan with probability exactly alpha, averaged over calibration draws, for any n >= 3. One threshold's
own rate, F_bar(t) = Phi_bar(Z + q W) with Z = (m - mu) / sigma ~ N(0, 1/n), W = s / sigma ~ sqrt(chi2_{n-1} /
(n - 1)) and q = t_{n-1}(1 - alpha) sqrt(1 + 1/n), has a distribution free of mu and sigma; its quantiles are what
:class:`Threshold` reports as ``far_interval``. The log-normal shape is an assumption, not a theorem: the benchmark
(``python -m benchmarks inspection``) measures the rate it gives on good test scans of several parts.
"""
import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

log = logging.getLogger(__name__)

BASES = ("conformal", "log-normal")
FAR_INTERVAL_LEVEL = 0.9  # probability of the reported false-alarm interval
MIN_TAIL_SCANS = 3  # the t-predictive needs n - 1 >= 2 degrees of freedom to have a finite variance
_TOL = 1e-9
# The default false-alarm rate: at 0.02 no part of the inspection and real benchmark suites flagged more
# than 1 of its 16 good test scans, and more defects were found than at 0.01 (docs/results.md)
DEFAULT_ALPHA = 0.02
_FAR_FLOOR = 1e-12  # rates below this are reported as 0


def check_alpha(alpha):
    """``alpha`` as a float in (0, 1), or a ValueError naming it."""
    try:
        alpha = float(alpha)
    except (TypeError, ValueError):
        raise ValueError(f"alpha must be a number in (0, 1), got {alpha!r}") from None
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    return alpha


def _scores(calibration_scores):
    cal = np.asarray(calibration_scores, dtype=np.float64).reshape(-1)
    if len(cal) == 0:
        raise ValueError("calibration_scores is empty: calibrate on at least one good scan")
    if not np.all(np.isfinite(cal)):
        raise ValueError("calibration_scores must be finite numbers")
    return cal


def conformal_p_values(calibration_scores, scores):
    """Split-conformal p-values of ``scores`` against the calibration scores (ties count as at least as extreme).

    Parameters
    ----------
    calibration_scores : (n,) array
        Anomaly scores of good held-out scans (higher = more anomalous), n >= 1.
    scores : (m,) array
        Anomaly scores to test.

    Returns
    -------
    (m,) float64 array in [1 / (n + 1), 1]
    """
    cal = np.sort(_scores(calibration_scores))
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    at_least = len(cal) - np.searchsorted(cal, s, side="left")  # #{c >= s}
    return (1.0 + at_least) / (len(cal) + 1.0)


def allowed_exceedances(n, alpha):
    """k = floor(alpha (n + 1) - 1): a score is flagged iff at most k calibration scores are >= it (-1: never)."""
    return int(math.floor(alpha * (n + 1) - 1 + _TOL))


def conformal_threshold(calibration_scores, alpha):
    """The split-conformal threshold t with ``p(s) <= alpha  <=>  s > t`` (ties included).

    Returns
    -------
    float
        The (k+1)-th largest calibration score, k = :func:`allowed_exceedances`; +inf when k < 0 (too few scores:
        nothing can be flagged), -inf when k >= n.
    """
    alpha = check_alpha(alpha)
    cal = np.sort(_scores(calibration_scores))[::-1]
    k = allowed_exceedances(len(cal), alpha)
    if k < 0:
        return math.inf
    if k >= len(cal):
        return -math.inf
    return float(cal[k])


def _log_fit(level_scores, spread_scores=(), spread_groups=None):
    """The log-normal fit (module docstring): (m, s, n_level, df).

    m: mean log score of ``level_scores``; s: the standard deviation of the log scores pooled within the groups
    (each around its own mean: the level scores, and the spread scores as one group or, with ``spread_groups`` (one
    label per spread score), as several), with df = the sum over groups of their size - 1."""
    level = _scores(level_scores)
    spread = np.asarray(spread_scores, dtype=np.float64).reshape(-1)
    both = np.concatenate([level, spread])
    if not np.all(np.isfinite(both)) or np.any(both <= 0):
        raise ValueError(f"the log-normal tail needs positive finite scores; got a minimum of {both.min():.4g}")
    y, x = np.log(level), np.log(spread)
    m = float(y.mean())
    groups = np.zeros(len(x), dtype=int) if spread_groups is None else np.unique(spread_groups, return_inverse=True)[1]
    squares, df = float(np.sum((y - m) ** 2)), len(y) - 1
    for g in np.unique(groups):
        xg = x[groups == g]
        squares += float(np.sum((xg - xg.mean()) ** 2))
        df += len(xg) - 1
    if df < MIN_TAIL_SCANS - 1:
        raise ValueError(f"the log-normal tail needs >= {MIN_TAIL_SCANS - 1} degrees of freedom for its spread "
                         f"(>= {MIN_TAIL_SCANS} scores), got {df}")
    s = max(math.sqrt(squares / df), 1e-12 * max(1.0, abs(m)))
    return m, s, len(y), df


def _tail_factor(n_level, df, alpha):
    from scipy import stats

    return float(stats.t.ppf(1 - alpha, df) * math.sqrt(1 + 1 / n_level))


def lognormal_threshold(calibration_scores, alpha, spread_scores=()):
    """exp(m + t_df(1 - alpha) s sqrt(1 + 1/n) ) of the log scores (module docstring)."""
    alpha = check_alpha(alpha)
    m, s, n, df = _log_fit(calibration_scores, spread_scores)
    return float(math.exp(m + _tail_factor(n, df, alpha) * s))


def lognormal_p_values(calibration_scores, scores, spread_scores=()):
    """Predictive p-values P(Y_new >= log s) of ``scores`` under the log-normal fit (module docstring): (m,)."""
    m, s, n, df = _log_fit(calibration_scores, spread_scores)
    return _t_p_values(scores, m, s, n, df)


def _t_p_values(scores, m, s, n, df):
    from scipy import stats

    x = np.asarray(scores, dtype=np.float64).reshape(-1)
    with np.errstate(divide="ignore"):
        y = np.log(np.maximum(x, 0.0))  # a score <= 0 is as normal as it gets: p = 1
    return stats.t.sf((y - m) / (s * math.sqrt(1 + 1 / n)), df)


def _lognormal_far_cdf(a, n, df, q):
    """P(F_bar(t) <= a) for the log-normal threshold with factor q, level from n scores, spread with df degrees of
    freedom (module docstring)."""
    from scipy import integrate, stats

    z_a = stats.norm.isf(a)
    chi = stats.chi(df)
    scale = math.sqrt(df)

    def integrand(u):  # u ~ chi_df; W = u / sqrt(df)
        return stats.norm.sf(math.sqrt(n) * (z_a - q * u / scale)) * chi.pdf(u)

    lo, hi = chi.ppf(1e-12), chi.ppf(1 - 1e-12)
    return float(integrate.quad(integrand, lo, hi, limit=200, epsabs=1e-12)[0])


def lognormal_far_interval(n, alpha, level=FAR_INTERVAL_LEVEL, df=None):
    """The central ``level`` probability interval of the false-alarm rate F_bar(t) of a log-normal threshold whose
    level rests on n scores and spread on df degrees of freedom (default n - 1)."""
    from scipy import optimize

    df = n - 1 if df is None else df
    q = _tail_factor(n, df, alpha)
    out = []
    for target in ((1 - level) / 2, (1 + level) / 2):
        f = lambda log_a: _lognormal_far_cdf(math.exp(log_a), n, df, q) - target  # noqa: E731
        lo, hi = math.log(_FAR_FLOOR), math.log(1 - 1e-6)
        # with very few scores the rate can be below any floor with probability > target: report 0
        out.append(0.0 if f(lo) >= 0 else float(math.exp(optimize.brentq(f, lo, hi, xtol=1e-10))))
    return out[0], out[1]


def conformal_far_interval(n, alpha, level=FAR_INTERVAL_LEVEL):
    """The central ``level`` interval of Beta(k + 1, n - k), the false-alarm rate of a conformal threshold."""
    from scipy import stats

    k = allowed_exceedances(n, alpha)
    if k < 0:
        return 0.0, 0.0
    if k >= n:
        return 1.0, 1.0
    dist = stats.beta(k + 1, n - k)
    return float(dist.ppf((1 - level) / 2)), float(dist.ppf((1 + level) / 2))


@dataclass
class Threshold:
    """A decision threshold on scan scores, and what it is based on.

    Attributes
    ----------
    value : float
        A scan is defective when its score > value (+inf: nothing can be flagged).
    alpha : float
        The false-alarm rate asked for.
    basis : {'conformal', 'log-normal'}
        Exact split-conformal, or extrapolated with the log-normal predictive tail (module docstring).
    n : int
        Calibration scores it rests on (held back and cross-fitted).
    predicted_far : float
        False-alarm rate on good scans, averaged over calibration draws: (k + 1) / (n + 1) or alpha.
    far_interval : (2,) floats
        ``FAR_INTERVAL_LEVEL`` probability interval of this threshold's own false-alarm rate.
    note : str
        One line for the user when the threshold is not exact split-conformal at alpha ('' otherwise).
    alpha_used : float
        The rate the p-values are compared with: ``alpha``, or 1 / (n + 1) when too few scores allow nothing
        smaller. ``p <= alpha_used`` exactly when ``score > value``.
    fit : dict
        The log-normal fit (``mean``, ``sd``, ``n_level``, ``df``) or the conformal scores (``scores``): what the
        p-values of new scores need. ``cross_fit_shift``: how much lower the cross-fitted scans' mean log score was
        than the held-back ones' (the optimism the level avoids), when there were both.
    """

    value: float
    alpha: float
    basis: str
    n: int
    predicted_far: float
    far_interval: tuple
    note: str = ""
    alpha_used: float = None
    fit: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.alpha_used is None:
            self.alpha_used = self.alpha

    def p_values(self, scores):
        """p-values of scores on this threshold's basis: ``p <= alpha_used`` exactly when score > value."""
        if self.basis == "log-normal":
            f = self.fit
            return _t_p_values(scores, f["mean"], f["sd"], f["n_level"], f["df"])
        return conformal_p_values(self.fit["scores"], scores)

    def uncertain(self, scores):
        """(k,) bool: the scores whose p-value lies within ``far_interval``, the threshold's own uncertainty.

        A threshold drawn from other good scans of the same process would sit anywhere whose false-alarm rate lies
        in ``far_interval`` (with probability ``FAR_INTERVAL_LEVEL``): a score whose p-value (its rate as a
        threshold) lies in that interval would be flagged by some of those thresholds and passed by others, so its
        verdict is a coin flip of the calibration draw, not a property of the scan. Monotone in the score: the
        uncertain scores form one interval around ``value``."""
        p = np.asarray(self.p_values(scores), dtype=np.float64)
        lo, hi = self.far_interval
        return (p >= lo) & (p <= hi)

    def reason(self, score, verdict):
        """A scan's verdict in words, for the report and the API: its score against this threshold, its p-value, and
        what an ``'uncertain'`` verdict means (``verdict`` as :meth:`inspection.Inspector.verdicts_from_scores`
        gave it for ``score``)."""
        p = float(self.p_values([score])[0])
        lo, hi = self.far_interval
        where = f"score {score:.4g}, threshold {self.value:.4g}, p-value {p:.3g}"
        if verdict == "uncertain":
            return (f"{where}: within the threshold's own uncertainty (the p-value lies in its "
                    f"{100 * FAR_INTERVAL_LEVEL:.0f} % false-alarm interval {format_rate(lo)} to {format_rate(hi)}): "
                    f"rescan")
        if verdict == "defective":
            return f"{where}: above the threshold (good scans score this high {format_rate(p)} of the time)"
        return f"{where}: below the threshold"

    def as_dict(self):
        d = asdict(self)
        d["value"] = None if not math.isfinite(self.value) else float(self.value)
        d["far_interval"] = [float(v) for v in self.far_interval]
        d["far_interval_level"] = FAR_INTERVAL_LEVEL
        d["fit"] = {k: v for k, v in self.fit.items() if k != "scores"}
        return d


def format_rate(rate):
    """A rate as a short percentage for one-line notes: '11 %', '1 %', '0.072 %', '<0.001 %', '100 %'."""
    if 0 < rate < 1e-5:
        return "<0.001 %"
    return f"{100 * rate:.0f} %" if rate >= 0.095 else f"{100 * rate:.2g} %"


def describe_decision(decision):
    """A threshold (:meth:`Threshold.as_dict`, as summary.json holds it) as a quality engineer reads it: (the plain
    words first: the false-alarm rate, its interval, what set it and, when it is not exact, what would narrow it;
    then the statistics). The command lines, the report page and the calibration print these two."""
    lo, hi = decision["far_interval"]
    plain = decision.get("note") or (
        f"{_rate_and_interval(decision['predicted_far'], (lo, hi))}: set exactly (split-conformal) by "
        f"{_scans(decision['n'], 'good scan')}' scores the model never trained on")
    stats = [f"basis {decision['basis']} on {decision['n']} calibration scores", f"alpha {decision['alpha']:g}"]
    if decision.get("alpha_used") not in (None, decision["alpha"]):
        stats.append(f"reachable rate {decision['alpha_used']:.3g}")
    stats.append(f"predicted false-alarm rate {format_rate(decision['predicted_far'])}, "
                 f"{100 * decision.get('far_interval_level', FAR_INTERVAL_LEVEL):.0f} % interval {format_rate(lo)} to "
                 f"{format_rate(hi)}")
    fit = decision.get("fit") or {}
    if "mean" in fit:
        stats.append(f"log-normal level from {_scans(fit['n_level'], 'score')} (mean log score {fit['mean']:.4g}, "
                     f"sd {fit['sd']:.3g}, {fit['df']} degrees of freedom)")
    for key, what in (("cross_fit_shift", "cross-fit shift"), ("fold_shift", "fold shift"),
                      ("site_shift", "site shift (the own sensor's good scans over the model's calibration scans)")):
        if key in fit:
            stats.append(f"{what} {fit[key]:+.3g} in log score")
    return plain, "statistics: " + "; ".join(stats)


ROLES = ("held-back", "fold", "cross-fitted", "site")
# roles whose scores are out of sample: scored by a model that never trained on the scan
OUT_OF_SAMPLE = ("held-back", "fold", "site")
# 'site': real good scans from the inspection's own sensor, given to calibrate after the model's own calibration
# (:meth:`inspection.Inspector.fit_level`); with any of them they alone set the threshold's level


def _plan(n_out, n_crossed, alpha, positive=True):
    """How :func:`fit_threshold` draws a threshold from ``n_out`` out-of-sample and ``n_crossed`` cross-fitted
    scores at ``alpha`` (``positive``: every score > 0, which the log-normal tail needs): (basis, the rate its
    p-values are compared with, the ``FAR_INTERVAL_LEVEL`` interval of its false-alarm rate, the log-normal fit's
    degrees of freedom or None). The one rule, also for saying before any score exists what a calibration on so
    many scans will give (:func:`calibration_outlook`)."""
    if allowed_exceedances(n_out, alpha) >= 0:
        return "conformal", alpha, conformal_far_interval(n_out, alpha), None
    df = n_out - 1 + (n_crossed - 1 if n_crossed else 0)
    if positive and n_out >= 1 and df >= MIN_TAIL_SCANS - 1:
        return "log-normal", alpha, lognormal_far_interval(n_out, alpha, df=df), df
    reach = 1 / (n_out + 1)
    return "too few", reach, conformal_far_interval(n_out, reach), None


def _scans(n, what="held-back scan"):
    """'1 held-back scan', '6 held-back scans'."""
    return f"{n} {what}{'' if n == 1 else 's'}"


def _rate_and_interval(rate, interval):
    lo, hi = interval
    return (f"a good scan is flagged {format_rate(rate)} of the time on average, and this threshold's own rate lies "
            f"between {format_rate(lo)} and {format_rate(hi)} ({100 * FAR_INTERVAL_LEVEL:.0f} % interval)")


def _shift_words(shift):
    """How the cross-fitted scans scored against the held-back ones, from ``cross_fit_shift`` (mean log score of the
    held-back minus the cross-fitted): '60 % lower' or '25 % higher', never a negative 'lower'."""
    ratio = math.exp(-shift)  # the cross-fitted scans' geometric mean over the held-back scans'
    return f"{100 * (1 - ratio):.0f} % lower" if ratio <= 1 else f"{100 * (ratio - 1):.0f} % higher"


FOLDS_HINT = ("`nsspr-train --calibration-folds 2` scores the training scans by models that never saw them (more "
              "scans set the threshold), and more good scans narrow the interval")


def fit_threshold(calibration_scores, alpha, roles=None):
    """The threshold at false-alarm rate ``alpha`` from good scans' scores.

    Parameters
    ----------
    calibration_scores : (n,) array
        Scores of good scans (higher = more anomalous).
    alpha : float in (0, 1)
    roles : (n,) sequence of {'held-back', 'fold', 'cross-fitted'}, optional
        How each score was obtained (default: all held back): by the model on a scan it did not train on
        ('held-back'), by a fold model on a training scan it did not train on ('fold'; both out of sample), or by
        the model on a training scan scored as if new ('cross-fitted', :meth:`inspection.Inspector.fit`), or
        by the model on a real good scan of the inspection's own sensor given after its calibration ('site',
        :meth:`inspection.Inspector.fit_level`). Cross-fitted scores can be optimistic (the nets saw those scans):
        they never set the threshold's level, only the spread of the log-normal tail. With any 'site' scores, they
        alone set the level (the model's own calibration scans, rendered template views say, may come from another
        sensor) and every group gives the spread, each around its own mean.

    Returns
    -------
    Threshold
        Split-conformal (CV+ with fold scores) on the n_o out-of-sample scores when n_o >= 1 / alpha - 1 (it can
        reach alpha exactly); else the log-normal tail, its level the out-of-sample scores' mean log score and its
        spread pooled within the out-of-sample and cross-fitted groups (needs positive scores and >= 2 degrees of
        freedom); else conformal at its smallest reachable rate, 1 / (n_o + 1). Its ``note`` says in plain words,
        first, what a quality engineer needs (the rate, its interval, what set it, what would narrow it), the
        statistics after.
    """
    alpha = check_alpha(alpha)
    cal = _scores(calibration_scores)
    roles = np.array(["held-back"] * len(cal) if roles is None else list(roles))
    if roles.shape != cal.shape or not np.isin(roles, ROLES).all():
        raise ValueError(f"roles: one of {ROLES} per score ({len(cal)}), got {list(roles)}")
    if np.any(roles == "site"):
        return _site_threshold(cal, roles, alpha)
    out_of_sample = np.isin(roles, OUT_OF_SAMPLE)
    held, crossed = cal[out_of_sample], cal[roles == "cross-fitted"]
    folds = cal[roles == "fold"]
    if len(held) == 0:
        raise ValueError("fit_threshold needs at least one out-of-sample score (a good scan the model or a fold "
                         "model did not train on)")
    n_h, n = len(held), len(cal)
    what = (f"{n_h} out-of-sample scores ({n_h - len(folds)} held-back, {len(folds)} by fold models)" if len(folds)
            else _scans(n_h))
    need = math.ceil(1 / alpha - 1 - _TOL)
    fit = {}
    if len(folds) and n_h > len(folds) and np.all(cal > 0):
        # how much higher the fold models' scores lie than the held-back ones' (a fold model trains on fewer scans)
        fit["fold_shift"] = float(np.log(folds).mean() - np.log(held[roles[out_of_sample] == "held-back"]).mean())
    hint = "" if len(folds) else f"; {FOLDS_HINT}" if len(crossed) else "; more good scans narrow the interval"
    basis, alpha_used, interval, df = _plan(n_h, len(crossed), alpha, bool(np.all(cal > 0)))
    if basis == "conformal":
        k = allowed_exceedances(n_h, alpha)
        predicted = min(1.0, (k + 1) / (n_h + 1))
        note = "" if not len(folds) else f"{_rate_and_interval(predicted, interval)}: exact conformal (CV+) on {what}"
        return Threshold(conformal_threshold(held, alpha), alpha, "conformal", n_h, predicted, interval, note,
                         fit={**fit, "scores": held.tolist()})
    if basis == "log-normal":
        m, sd, _, df = _log_fit(held, crossed)
        fit.update(mean=m, sd=sd, n_level=n_h, df=df)
        how = f"{n} good scans' scores" if not len(folds) else "their scores"
        if len(crossed):
            fit["cross_fit_shift"] = float(np.log(held).mean() - np.log(crossed).mean())
            how = (f"the held-back scans' level and the spread of all {n} good scans' scores (the {len(crossed)} "
                   f"cross-fitted training scans scored {_shift_words(fit['cross_fit_shift'])})")
        note = (f"{_rate_and_interval(alpha, interval)}: it rests on {what}, fewer than the {need} an exact "
                f"conformal threshold at alpha={alpha:g} needs, so it is extrapolated from a log-normal fit of "
                f"{how}{hint}")
        value = float(math.exp(m + _tail_factor(n_h, df, alpha) * sd))
        return Threshold(value, alpha, "log-normal", n, alpha, interval, note, fit=fit)
    why = ("the log-normal tail needs positive scores" if not np.all(cal > 0) else
           f"calibrate on at least {MIN_TAIL_SCANS} good scans")
    note = (f"{_rate_and_interval(alpha_used, interval)}: {what} are too few for alpha={alpha:g}, so the threshold "
            f"is the largest of their scores, at the smallest reachable rate {alpha_used:.3g}; {why}")
    return Threshold(float(held.max()), alpha, "conformal", n_h, alpha_used, interval, note,
                     alpha_used=alpha_used, fit={**fit, "scores": held.tolist()})


def _site_threshold(cal, roles, alpha):
    """:func:`fit_threshold` with real good scans of the inspection's own sensor ('site' scores): split-conformal on
    them alone when there are enough; else the log-normal tail, its level their mean log score, its spread pooled
    within every role's group around the group's own mean (the model's calibration scans give the tail's shape, the
    site's scans where it lies); else the largest site score at the smallest reachable rate."""
    site = cal[roles == "site"]
    others = cal[roles != "site"]
    other_roles = roles[roles != "site"]
    n_s, n = len(site), len(cal)
    fit, need = {}, math.ceil(1 / alpha - 1 - _TOL)
    model_out = cal[np.isin(roles, ("held-back", "fold"))]
    positive = bool(np.all(cal > 0))
    if len(model_out) and positive:
        # how much higher the site's good scans score than the model's own out-of-sample calibration scans
        fit["site_shift"] = float(np.log(site).mean() - np.log(model_out).mean())
    shift = ("" if "site_shift" not in fit else
             f" (they score {_shift_words(-fit['site_shift'])} than the model's own calibration scans)")
    what = _scans(n_s, "good scan") + " of the inspection's own sensor"
    if allowed_exceedances(n_s, alpha) >= 0:
        k = allowed_exceedances(n_s, alpha)
        predicted, interval = min(1.0, (k + 1) / (n_s + 1)), conformal_far_interval(n_s, alpha)
        note = f"{_rate_and_interval(predicted, interval)}: set exactly (split-conformal) by the {what}"
        return Threshold(conformal_threshold(site, alpha), alpha, "conformal", n_s, predicted, interval, note,
                         fit={**fit, "scores": site.tolist(), "level_from": "site"})
    df = n_s - 1 + sum(int(np.sum(other_roles == r)) - 1 for r in np.unique(other_roles))
    if positive and df >= MIN_TAIL_SCANS - 1 and n_s >= 1:
        m, sd, _, df = _log_fit(site, others, other_roles)
        fit.update(mean=m, sd=sd, n_level=n_s, df=df, level_from="site")
        interval = lognormal_far_interval(n_s, alpha, df=df)
        note = (f"{_rate_and_interval(alpha, interval)}: its level is set by the {what}{shift}, fewer than the "
                f"{need} an exact threshold at alpha={alpha:g} needs, and its spread by them and the model's "
                f"{len(others)} calibration scores (a log-normal fit); more good scans of the line narrow the "
                f"interval")
        return Threshold(float(math.exp(m + _tail_factor(n_s, df, alpha) * sd)), alpha, "log-normal", n, alpha,
                         interval, note, fit=fit)
    reach = 1 / (n_s + 1)
    interval = conformal_far_interval(n_s, reach)
    note = (f"{_rate_and_interval(reach, interval)}: the {what} are too few for alpha={alpha:g}, so the threshold "
            f"is the largest of their scores, at the smallest reachable rate {reach:.3g}")
    return Threshold(float(site.max()), alpha, "conformal", n_s, reach, interval, note, alpha_used=reach,
                     fit={**fit, "scores": site.tolist(), "level_from": "site"})


def calibration_outlook(n_heldback, n_training, alpha=DEFAULT_ALPHA, folds=0):
    """What calibrating on a model's good scans will give, said before the model is trained: '' when the threshold
    will be exact, else one line in plain words (how many scans calibrate, what that means for the threshold, what
    ``--calibration-folds`` or more scans would give). ``train_latent.py`` says it at the start of a training.

    Parameters
    ----------
    n_heldback : int
        Good scans held back from training (or the validation split's), the calibration's out-of-sample scans.
    n_training : int
        Good scans the model trains on: cross-fitted for the spread of the threshold's tail, or scored out of sample
        by fold models.
    alpha : float
        The false-alarm rate the threshold will be drawn at.
    folds : int
        Fold models the training adds (``--calibration-folds``; 0: none).

    Returns
    -------
    str
    """
    alpha = check_alpha(alpha)
    n_out, n_crossed = (n_heldback + n_training, 0) if folds else (n_heldback, n_training)
    if n_out == 0:
        return (f"no good scan is held back from the {n_training} the model trains on: it cannot calibrate a "
                f"threshold on scans it saw; hold some back (--calibration-fraction), add fold models "
                f"(--calibration-folds 2) or calibrate later on other good scans (`nsspr-inspect calibrate --data "
                f"GOOD_SCANS`)")
    basis, _, interval, _ = _plan(n_out, n_crossed, alpha)
    if basis == "conformal":
        return ""
    need = math.ceil(1 / alpha - 1 - _TOL)
    total = n_heldback + n_training
    lo, hi = (format_rate(v) for v in interval)
    line = (f"few good scans for the threshold: of the {total} good scans {n_training} train the model and "
            f"{n_heldback} {'is' if n_heldback == 1 else 'are'} held back to calibrate it")
    if folds:
        line += f", and {folds} fold models score the {n_training} training scans as new"
    line += (f"; an exact threshold at alpha={alpha:g} needs {need} scans no model trained on, so with {n_out} it "
             + ("will be extrapolated from a log-normal fit of their scores" if basis == "log-normal" else
                "can only be the largest of their scores, at a false-alarm rate far above alpha")
             + f": its own false-alarm rate will lie anywhere between {lo} and {hi} ({100 * FAR_INTERVAL_LEVEL:.0f} "
             f"% interval), and scans scoring near it will be told 'uncertain' (rescan)")
    if not folds and n_training >= 2:
        k = min(2, n_training)
        f_basis, _, f_interval, _ = _plan(total, 0, alpha)
        if f_basis == "conformal":
            gives = "make it exact"
        else:
            gives = (f"narrow that to {format_rate(f_interval[0])} to {format_rate(f_interval[1])} (all {total} "
                     f"scored out of sample)")
        line += f". --calibration-folds {k} would {gives}, at the cost of training {k} fold models"
    more = max(0, need - n_out)
    if more:
        line += (f"; {more} more good scans {'scored by fold models' if folds else 'held back'} would make it "
                 f"exact")
    return line
