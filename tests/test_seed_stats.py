"""vkgrl_newton.results.seeds.over_seeds on hand data against independent computations: the Student-t
interval from numpy's mean and sd and a t quantile read from a table, the sign test and the Wilcoxon
signed-rank test by enumerating every sign pattern; one seed, equal seeds and all-zero seeds; the verdict
rule; and train/report.py's --from-stats on a stats.json written here (issue 40)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from scripts import load_script

from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds, seeds_needed

HAND = [0.05, 0.1, -0.02, 0.08, 0.12]
T975 = {2: 4.302653, 3: 3.182446, 4: 2.776445}  # t(0.975, df) from a printed table, not from scipy


def t_interval(x) -> tuple[float, float]:
    x = np.asarray(x, dtype=np.float64)
    half = T975[len(x) - 1] * x.std(ddof=1) / math.sqrt(len(x))
    return x.mean() - half, x.mean() + half


def sign_p(x) -> float:
    """Two-sided exact sign test: the share of the 2^n equally likely sign patterns of the nonzero values
    at least as far from n/2 positives as the one observed."""
    x = [v for v in x if v != 0]
    n, pos = len(x), sum(v > 0 for v in x)
    patterns = list(itertools.product((0, 1), repeat=n))
    return sum(abs(sum(p) - n / 2) >= abs(pos - n / 2) for p in patterns) / len(patterns)


def wilcoxon_p(x) -> float:
    """Two-sided Wilcoxon signed-rank p by enumeration: zeros dropped, |x| ranked (ties averaged), the
    positive rank sum of every sign pattern against the observed one's distance from its mean."""
    x = np.array([v for v in x if v != 0], dtype=np.float64)
    order = np.abs(x)
    ranks = np.array([np.mean([j + 1 for j, w in enumerate(np.sort(order)) if w == v]) for v in order])
    observed = ranks[x > 0].sum()
    centre = ranks.sum() / 2
    sums = [sum(r for r, s in zip(ranks, p) if s) for p in itertools.product((0, 1), repeat=len(x))]
    return float(np.mean([abs(s - centre) >= abs(observed - centre) - 1e-12 for s in sums]))


def test_hand_data_against_independent_references():
    s = over_seeds(HAND)
    lo, hi = t_interval(HAND)
    assert s["n_seeds"] == 5 and s["mean"] == pytest.approx(0.066)
    assert s["sd"] == pytest.approx(np.std(HAND, ddof=1))
    assert (s["t_low"], s["t_high"]) == pytest.approx((lo, hi), abs=1e-6)
    assert (s["sign_positive"], s["sign_negative"], s["sign_zeros"]) == (4, 1, 0)
    assert s["sign_p"] == pytest.approx(sign_p(HAND)) and sign_p(HAND) == pytest.approx(12 / 32)
    assert s["wilcoxon_p"] == pytest.approx(wilcoxon_p(HAND)) and wilcoxon_p(HAND) == pytest.approx(4 / 32)
    # the percentile bootstrap excludes 0 here, the t-interval does not: the verdict follows the t-interval
    assert s["ci_low"] > 0 and s["t_low"] < 0 < s["t_high"]
    assert s["verdict"] == "not established" and s["not_measurable"] == ""
    assert format_t(s) == "[-0.002, +0.134]" and format_tests(s) == "sign 4+/1- p 0.375; Wilcoxon p 0.125"


@pytest.mark.parametrize("values", [[0.1, 0.3, 0.2, 0.25], [0.02, -0.01, 0.0, 0.05], [-0.0078125, 0.0703125,
                                    -0.0078125, -0.03125, -0.0078125]])
def test_ties_zeros_and_other_lengths_against_enumeration(values):
    """Tied |values| and a zero seed: the Wilcoxon p is still the enumeration's (zeros dropped)."""
    s = over_seeds(values)
    assert (s["t_low"], s["t_high"]) == pytest.approx(t_interval(values), abs=1e-6)
    assert s["sign_p"] == pytest.approx(sign_p(values))
    assert s["wilcoxon_p"] == pytest.approx(wilcoxon_p(values))
    assert s["sign_zeros"] == sum(v == 0 for v in values)


def test_the_verdict_follows_the_t_interval():
    up = [0.1, 0.3, 0.2, 0.25]
    assert over_seeds(up)["verdict"] == "beats" and t_interval(up)[0] > 0
    assert over_seeds([-v for v in up])["verdict"] == "loses"
    assert over_seeds([0.1, -0.1, 0.05])["verdict"] == "not established"


def test_one_seed_equal_seeds_and_zero_seeds_are_not_measurable():
    one = over_seeds([0.1])
    assert one["n_seeds"] == 1 and one["mean"] == pytest.approx(0.1)
    assert all(one[k] is None for k in ("sd", "t_low", "t_high", "ci_low", "ci_high", "sign_p", "wilcoxon_p"))
    assert one["verdict"] == "not established" and "one seed" in one["not_measurable"]
    assert format_t(one) == "one seed: none" and format_tests(one) == "sign not measurable; Wilcoxon not measurable"
    # equal seeds: no spread, so no t-interval (a point would claim certainty); the sign test still counts
    equal = over_seeds([0.1, 0.1, 0.1])
    assert equal["sd"] == 0.0 and equal["t_low"] is None and equal["verdict"] == "not established"
    assert equal["sign_p"] == pytest.approx(sign_p([0.1] * 3)) == pytest.approx(0.25)
    zeros = over_seeds([0.0, 0.0, 0.0])
    assert zeros["mean"] == 0.0 and zeros["sign_p"] is None and zeros["wilcoxon_p"] is None
    assert "every seed 0" in zeros["not_measurable"] and zeros["verdict"] == "not established"
    none = over_seeds([math.nan])
    assert none["n_seeds"] == 0 and none["mean"] is None
    # NaN seeds (no complete episode pair) are dropped, as the bootstrap drops them
    assert over_seeds(HAND + [math.nan])["t_low"] == pytest.approx(over_seeds(HAND)["t_low"])
    json.dumps(over_seeds([0.1]), allow_nan=False)  # strict JSON: None, never NaN


def test_seeds_needed_rule():
    assert seeds_needed(17.0) == 10 and seeds_needed(30.0) == 10 and seeds_needed(30.1) == 5
    assert seeds_needed(None) is None and seeds_needed(math.nan) is None


def test_report_from_stats_pairs_gain_rows_and_restats_pairs(tmp_path):
    """--from-stats on a stats.json written here: each gain row and method pair gets the statistics, two
    gain rows over the same prior are differenced seed by seed (by id where recorded, else in run order)."""
    report_py = load_script("report")
    old = tmp_path / "old"
    old.mkdir()
    gain = lambda method, values, ids=None, prior=0.14: {  # noqa: E731
        "task": "PegInsert", "env": "factory", "action_dim": 4, "method": method, "prior_success": prior,
        "seed_gains": values, **({"seed_ids": ids} if ids else {})}
    stats = {"prior_gain": [gain("kgrl+x", [0.0, 0.1, 0.2]), gain("vision_kgrl+x", [0.2, 0.3, 0.5]),
                            gain("kgrl+other_prior", [0.0, 0.1, 0.2], prior=0.5)],
             "method_pairs": [{"task": "PegInsert", "env": "factory", "action_dim": 4, "a": "sac", "b": "sac+d",
                               "seeds": [0, 1], "seed_differences": [0.03, 0.01]}]}
    (old / "stats.json").write_text(json.dumps(stats))
    out = tmp_path / "restat"
    assert report_py.main(["--from-stats", str(old), "--out", str(out), "--reps", "200"]) == 0
    rows = json.loads((out / "seed_stats.json").read_text())["rows"]
    names = [r["name"] for r in rows]
    assert names == ["kgrl+x", "vision_kgrl+x", "kgrl+other_prior", "sac+d - sac", "vision_kgrl+x - kgrl+x"]
    diff = rows[-1]
    assert diff["values"] == pytest.approx([0.2, 0.2, 0.3]) and diff["paired_by"] == "run order"
    assert (diff["seed_stats"]["t_low"], diff["seed_stats"]["t_high"]) == pytest.approx(
        t_interval([0.2, 0.2, 0.3]), abs=1e-6)
    assert diff["seed_stats"]["verdict"] == "beats"
    assert rows[3]["seed_stats"]["t_low"] < 0 and rows[3]["seed_stats"]["verdict"] == "not established"
    md = (out / "seed_stats.md").read_text()
    assert "vision_kgrl+x - kgrl+x (gains' difference, by run order)" in md and "| **beats** |" in md
    # seed ids recorded: only shared seeds pair
    stats["prior_gain"] = [gain("kgrl+x", [0.0, 0.1, 0.2], ids=[0, 1, 2]), gain("vision_kgrl+x", [0.3, 0.5], ids=[1, 2])]
    (old / "stats.json").write_text(json.dumps(stats))
    out2 = tmp_path / "restat2"
    report_py.main(["--from-stats", str(old), "--out", str(out2)])
    diff = json.loads((out2 / "seed_stats.json").read_text())["rows"][-1]
    assert diff["seeds"] == [1, 2] and diff["values"] == pytest.approx([0.2, 0.3]) and diff["paired_by"] == "seed id"
