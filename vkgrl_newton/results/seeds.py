"""Statistics over seeds of per-seed paired differences (one value per seed: a run's gain over its
prior, or method B minus method A on the same episodes), and the rule for what they may claim.

With 3-10 seeds a percentile bootstrap is too narrow (it never reaches past the seeds' own range),
so `over_seeds` gives beside it a Student-t interval of the mean, an exact two-sided sign test and a
Wilcoxon signed-rank test (exact enumeration for small n), all scipy's. The verdict follows the
t-interval alone: "beats" when its lower bound is above 0, "loses" when its upper bound is below 0,
else "not established" (also whenever the t-interval cannot be formed: one seed, or seeds all equal).

`seeds_needed(trial_minutes)`: a headline claim rests on >= 10 seeds where a trial costs <= 30 min,
>= 5 where it costs more (issue 40).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from vkgrl_newton.results.paired import paired_gain

__all__ = ["over_seeds", "seeds_needed", "format_t", "format_tests", "VERDICTS", "NOT_MEASURABLE"]

VERDICTS = ("beats", "loses", "not established")
NOT_MEASURABLE = "not measurable"
# 2**n sign patterns are enumerated for the Wilcoxon p-value up to this n (exact with tied |d|); above it,
# scipy's own choice (its normal approximation for large n)
WILCOXON_EXACT_MAX_N = 16


def seeds_needed(trial_minutes: float | None) -> int | None:
    """Seeds a headline claim needs: 10 where a trial costs <= 30 min, 5 where more; None if unknown."""
    if trial_minutes is None or not math.isfinite(trial_minutes):
        return None
    return 10 if trial_minutes <= 30.0 else 5


def over_seeds(values, confidence: float = 0.95, reps: int = 2000, seed: int = 0) -> dict:
    """Over-seeds statistics of per-seed differences (NaN seeds dropped).

    Returns a strict-JSON dict (None where a figure cannot be formed):
      n_seeds, mean, sd (ddof 1), confidence;
      t_low, t_high: the Student-t interval mean +- t(1 - alpha/2, n-1) sd / sqrt(n) (scipy.stats.t);
      ci_low, ci_high: the percentile bootstrap over seeds (`paired_gain` against zeros, as report.py has
        always printed it);
      sign_positive, sign_negative, sign_zeros, sign_p: the exact two-sided sign test (scipy.stats.binomtest,
        p = 1/2) on positive against negative seeds, zeros dropped;
      wilcoxon_statistic, wilcoxon_p: the Wilcoxon signed-rank test (scipy.stats.wilcoxon), zeros dropped,
        its p-value by enumerating every sign pattern for n <= 16 (exact, ties included);
      verdict: "beats" | "loses" | "not established" (the t-interval's bounds against 0);
      not_measurable: why a figure is None ("" where all are there).
    """
    d = np.asarray(values, dtype=np.float64).reshape(-1)
    d = d[np.isfinite(d)]
    n = int(d.size)
    out = {"n_seeds": n, "mean": None, "sd": None, "confidence": confidence, "t_low": None, "t_high": None,
           "ci_low": None, "ci_high": None, "sign_positive": int((d > 0).sum()), "sign_negative": int((d < 0).sum()),
           "sign_zeros": int((d == 0).sum()), "sign_p": None, "wilcoxon_statistic": None, "wilcoxon_p": None,
           "verdict": "not established", "not_measurable": ""}
    if n == 0:
        return {**out, "not_measurable": f"no seed: {NOT_MEASURABLE}"}
    out["mean"] = float(d.mean())
    if n < 2:  # one seed has no spread: no interval and no test
        return {**out, "not_measurable": f"one seed: intervals and tests {NOT_MEASURABLE}"}
    # equal seeds have sd 0 exactly (numpy's mean of [0.1] * 3 is not 0.1, and its sd not 0)
    out["sd"] = 0.0 if np.all(d == d[0]) else float(d.std(ddof=1))
    boot = paired_gain(d, np.zeros_like(d), reps=reps, seed=seed, confidence=confidence)
    out["ci_low"], out["ci_high"] = boot["ci_low"], boot["ci_high"]
    why = []
    if out["sd"] > 0.0:
        lo, hi = stats.t.interval(confidence, n - 1, loc=out["mean"], scale=stats.sem(d))
        out["t_low"], out["t_high"] = float(lo), float(hi)
        out["verdict"] = "beats" if lo > 0.0 else "loses" if hi < 0.0 else "not established"
    else:  # a degenerate [mean, mean] would claim certainty from seeds that merely coincide
        why.append(f"all seeds equal: t-interval {NOT_MEASURABLE}")
    nonzero = d[d != 0.0]
    if nonzero.size == 0:
        why.append(f"every seed 0: sign and Wilcoxon tests {NOT_MEASURABLE}")
    else:
        out["sign_p"] = float(stats.binomtest(out["sign_positive"], int(nonzero.size), 0.5).pvalue)
        if nonzero.size == 1:  # both sign patterns are as extreme: W = 0, exact p = 1 (scipy wants two)
            out["wilcoxon_statistic"], out["wilcoxon_p"] = 0.0, 1.0
        else:
            method = (stats.PermutationMethod(n_resamples=np.inf) if nonzero.size <= WILCOXON_EXACT_MAX_N
                      else "auto")
            w = stats.wilcoxon(nonzero, method=method)
            out["wilcoxon_statistic"], out["wilcoxon_p"] = float(w.statistic), float(w.pvalue)
    return {**out, "not_measurable": "; ".join(why)}


def format_t(s: dict, digits: int = 3) -> str:
    """The t-interval as '[-0.009, +0.171]', or why there is none."""
    if s["t_low"] is None:
        return "one seed: none" if s["n_seeds"] == 1 else "seeds equal: none" if s["sd"] == 0 else "none"
    return f"[{s['t_low']:+.{digits}f}, {s['t_high']:+.{digits}f}]"


def format_tests(s: dict) -> str:
    """'sign 4+/1- p 0.375; Wilcoxon p 0.125', 'not measurable' where a test cannot be formed."""
    sign = (NOT_MEASURABLE if s["sign_p"] is None
            else f"{s['sign_positive']}+/{s['sign_negative']}- p {s['sign_p']:.3g}")
    wil = NOT_MEASURABLE if s["wilcoxon_p"] is None else f"p {s['wilcoxon_p']:.3g}"
    return f"sign {sign}; Wilcoxon {wil}"
