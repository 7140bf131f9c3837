"""train/report.py on run directories with known metrics (written here): the hand-computed means,
stds, bold cells and dashes of Tables 6.1-6.4, the thesis's values beside ours, rliable's IQM and
probability of improvement against brute-force computations, the curves from curves.jsonl, and
the refusals (a mixed cell, a non-empty --out); the thesis data file against cells read by hand."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

from vkgrl_newton._io import strict_json
from vkgrl_newton.results.curves import CurveWriter, read_curves
from vkgrl_newton.results.thesis import load_thesis_tables

NAN = math.nan
# (action_dim, method) -> per seed (success, force, time to first success, reward)
RUNS = {
    (4, "sac"): [(0.2, 2.0, NAN, 10.0), (0.4, 2.0, NAN, 20.0), (0.6, 2.0, NAN, 30.0)],
    (4, "kgrl"): [(0.5, 1.0, 4.0, 50.0), (0.7, 1.0, NAN, 60.0), (0.9, 1.0, 6.0, 70.0)],
    (6, "sac"): [(0.0, 3.0, NAN, 0.0), (0.0, 3.0, NAN, 0.0), (0.0, 3.0, NAN, 0.0)],
    (6, "kgrl"): [(0.3, 0.5, 5.0, 40.0), (0.3, 0.5, 5.0, 40.0), (0.3, 0.5, 5.0, 40.0)],
}


@pytest.fixture(scope="module")
def report_py():
    return load_script("report")


def write_run(root: Path, dim: int, method: str, seed: int, values, total_steps: int = 30_000) -> Path:
    d = root / f"PegInsert_factory_{dim}d_{method}" / f"seed{seed}"
    d.mkdir(parents=True)
    success, force, ttfs, reward = values
    config = {"task": "PegInsert", "method": method, "env": "factory", "action_dim": dim, "seed": seed,
              "num_envs": 16, "preset": "quick", "time_obs": True, "obs_dim": 8, "sac": {"batch_size": 256},
              "total_steps": total_steps, "checkpoint_every": 4800, "device": "cpu"}
    (d / "config.json").write_text(json.dumps(config))
    metrics = {"success_rate": success, "mean_contact_force": force, "mean_episode_reward": reward,
               "time_to_first_success_s": None if math.isnan(ttfs) else ttfs, "training": {}}
    (d / "metrics.json").write_text(json.dumps(metrics))
    curves = CurveWriter(d)
    for i in range(1, 4):
        curves.append(transitions=2400 * i, episode_reward=reward * i / 3, success_rate=success * i / 3,
                      success_rate_any=success, mean_contact_force=force, peak_contact_force=10 * force,
                      time_to_first_success_s=ttfs, wall_s=60.0 * i)
    return d


@pytest.fixture()
def runs(tmp_path) -> Path:
    root = tmp_path / "sweep"
    for (dim, method), seeds in RUNS.items():
        for seed, values in enumerate(seeds):
            write_run(root, dim, method, seed, values)
    return root


def iqm(values) -> float:
    """Interquartile mean: drop floor(n/4) from each end of the sorted scores."""
    v = np.sort(np.ravel(values))
    k = int(0.25 * len(v))
    return float(v[k:len(v) - k].mean())


def prob_improvement(xs: list, ys: list) -> float:
    """P(X > Y) per configuration over all seed pairs (ties 1/2), averaged over configurations."""
    per = [np.mean([1.0 if x > y else 0.5 if x == y else 0.0 for x in xc for y in yc]) for xc, yc in zip(xs, ys)]
    return float(np.mean(per))


def test_report_tables_stats_and_curves(report_py, runs, tmp_path):
    out = tmp_path / "report"
    assert report_py.main([str(runs), "--out", str(out), "--reps", "300"]) == 0
    rows = list(csv.DictReader((out / "results.csv").open()))
    cell = {(r["metric"], int(r["action_dim"]), r["method"]): r for r in rows}
    assert len(rows) == 4 * 4  # 4 metrics x 4 cells
    r = cell[("success_rate", 4, "sac")]
    assert int(r["n"]) == 3 and float(r["mean"]) == pytest.approx(0.4)
    assert float(r["std"]) == pytest.approx(math.sqrt((0.2**2 + 0 + 0.2**2) / 3))  # ddof 0
    r = cell[("success_rate", 4, "kgrl")]
    assert float(r["thesis_mean"]) == 0.797 and float(r["thesis_std"]) == 0.071
    assert float(r["difference"]) == pytest.approx(0.7 - 0.797)
    r = cell[("time_to_first_success_s", 4, "kgrl")]  # over the seeds that succeeded
    assert int(r["n"]) == 2 and float(r["mean"]) == pytest.approx(5.0) and float(r["std"]) == pytest.approx(1.0)
    assert int(cell[("time_to_first_success_s", 4, "sac")]["n"]) == 0

    md = (out / "tables.md").read_text()
    table = {t.split(":")[0]: t for t in md.split("## Table ")[1:]}
    success, force, ttfs = table["6.2"], table["6.3"], table["6.4"]
    sac_row = next(ln for ln in success.splitlines() if ln.startswith("| PegInsert | sac"))
    kgrl_row = next(ln for ln in success.splitlines() if ln.startswith("| PegInsert | kgrl"))
    assert "**0.700 ± 0.163** (n=3) [0.797 ± 0.071; -0.097]" in kgrl_row  # best success: bold
    assert "0.400 ± 0.163 (n=3) [0.535 ± 0.066; -0.135]" in sac_row and "**" not in sac_row
    assert "**0.500 ± 0.000**" in next(ln for ln in force.splitlines() if "| kgrl" in ln)  # lowest force
    sac_ttfs = next(ln for ln in ttfs.splitlines() if ln.startswith("| PegInsert | sac"))
    assert sac_ttfs.split(" | ")[2] == "— (n=3) [3.606 ± 2.144; —]"  # no seed succeeded: a dash, no difference
    tex = (out / "tables.tex").read_text()
    assert tex.count("\\begin{tabular}") == 4 and "\\textbf{0.700 $\\pm$ 0.163}" in tex

    stats = json.loads((out / "stats.json").read_text())
    sac = [v[0] for d in (4, 6) for v in RUNS[(d, "sac")]]
    kgrl = [v[0] for d in (4, 6) for v in RUNS[(d, "kgrl")]]
    assert stats["iqm"]["sac"]["value"] == pytest.approx(iqm(sac))
    assert stats["iqm"]["kgrl"]["value"] == pytest.approx(iqm(kgrl))
    lo, hi = stats["iqm"]["kgrl"]["ci95"]
    assert lo <= stats["iqm"]["kgrl"]["value"] <= hi
    p = stats["probability_of_improvement"]["kgrl>sac"]
    want = prob_improvement([[v[0] for v in RUNS[(d, "kgrl")]] for d in (4, 6)],
                            [[v[0] for v in RUNS[(d, "sac")]] for d in (4, 6)])
    assert p["value"] == pytest.approx(want) and want == pytest.approx((8 / 9 + 1) / 2)
    assert "vision_kgrl>kgrl" not in stats["probability_of_improvement"]  # no vision runs
    for name in ("stats.png", "curves_PegInsert_factory_4d.png", "curves_PegInsert_factory_6d.png"):
        assert (out / name).stat().st_size > 10_000, name

    # the report never overwrites: a non-empty --out is refused
    with pytest.raises(SystemExit):
        report_py.main([str(runs), "--out", str(out)])


def test_report_refuses_a_cell_mixing_budgets(report_py, runs, tmp_path, capsys):
    write_run(runs, 4, "sac", 7, (0.1, 1.0, NAN, 1.0), total_steps=60_000)
    with pytest.raises(SystemExit):
        report_py.main([str(runs), "--out", str(tmp_path / "report")])
    err = capsys.readouterr().err
    assert "PegInsert/factory/4/sac" in err and "total_steps (30000 vs 60000)" in err and "seed7" in err
    with pytest.raises(SystemExit):
        report_py.main([str(tmp_path / "nothing_here"), "--out", str(tmp_path / "r2")])
    assert "does not exist" in capsys.readouterr().err


def test_thesis_tables_match_cells_read_by_hand():
    t = load_thesis_tables()
    assert len(t) == 4 * 3 * 4 * 4  # 4 tables x 3 tasks x 4 methods x 4 columns
    assert t[("success_rate", "GearMesh", "vision_kgrl", "factory", 4)] == (0.886, 0.022)
    assert t[("mean_episode_reward", "NutThread", "sac", "forge", 6)] == (-0.46, 0.24)
    assert t[("mean_contact_force", "PegInsert", "vision_sac", "forge", 6)] == (6.095, 0.248)
    assert t[("time_to_first_success_s", "NutThread", "kgrl", "factory", 6)] == (7.935, 0.338)
    assert all(math.isnan(v) for v in t[("time_to_first_success_s", "GearMesh", "sac", "factory", 6)])
    dashes = [k for k, (m, _) in t.items() if math.isnan(m)]
    assert sorted(dashes) == sorted([("time_to_first_success_s", "GearMesh", "sac", "factory", 6),
                                     ("time_to_first_success_s", "GearMesh", "vision_sac", "factory", 6),
                                     ("time_to_first_success_s", "NutThread", "sac", "forge", 4),
                                     ("time_to_first_success_s", "NutThread", "sac", "forge", 6)])


def test_curves_resume_drops_the_replayed_rows(tmp_path):
    w = CurveWriter(tmp_path)
    row = dict(episode_reward=1.0, success_rate=0.5, success_rate_any=0.5, mean_contact_force=1.0,
               peak_contact_force=2.0, time_to_first_success_s=NAN, wall_s=1.0)
    for t in (2400, 4800, 7200):
        w.append(transitions=t, **row)
    with open(tmp_path / "curves.jsonl", "a") as f:  # a line cut by a kill mid-write
        f.write('{"transitions": 96')
    assert [r["transitions"] for r in read_curves(tmp_path)] == [2400, 4800, 7200]
    CurveWriter(tmp_path, resume_at=4800)  # the checkpoint was at 4800: 7200 and the cut line go
    assert [r["transitions"] for r in read_curves(tmp_path)] == [2400, 4800]
    assert math.isnan(read_curves(tmp_path)[0]["time_to_first_success_s"])
    with pytest.raises(ValueError, match="lacks"):
        w.append(transitions=1)


def test_prior_gain_table_from_paired_runs(report_py, tmp_path):
    """Labelled KGRL runs with known per-episode outcomes: their row is `kgrl+<label>`, the gain per
    seed is policy minus prior on the same episodes, its mean over seeds and the pooled gain match
    a hand computation, and a curve falling from 5k-10k to the last 5k shows in the two columns."""
    root = tmp_path / "sweep"
    policy = {0: [1, 1, 0, 0], 1: [1, 0, 0, 0], 2: [1, 1, 1, 0]}  # 2 rounds x 2 worlds, flattened
    prior = [1, 0, 0, 0]
    for seed, outcome in policy.items():
        d = write_run(root, 4, "kgrl+lab", seed, (np.mean(outcome), 1.0, NAN, 10.0), total_steps=15_000)
        config = json.loads((d / "config.json").read_text())
        (d / "config.json").write_text(json.dumps({**config, "method": "kgrl", "label": "lab"}))
        m = json.loads((d / "metrics.json").read_text())
        rounds = lambda v: [{"world_success": v[:2]}, {"world_success": v[2:]}]  # noqa: E731
        gain = float(np.mean(outcome) - np.mean(prior))
        m.update(per_episode=rounds(outcome), prior_eval={"success_rate": 0.25, "per_episode": rounds(prior)},
                 paired_gain={"success_rate": {"mean": gain, "ci_low": gain, "ci_high": gain, "n_pairs": 4}},
                 training={"wall_s": 900.0 + 60 * seed}, wall_s=300.0)  # trials of 20, 21 and 22 min
        (d / "metrics.json").write_text(json.dumps(m))
        (d / "curves.jsonl").unlink()
        curves = CurveWriter(d)
        for t, sr in ((4800, 0.0), (7200, 0.4), (9600, 0.6), (12000, 0.3), (14400, 0.1)):
            curves.append(transitions=t, episode_reward=0.0, success_rate=sr, success_rate_any=sr,
                          mean_contact_force=1.0, peak_contact_force=1.0, time_to_first_success_s=NAN, wall_s=1.0)
    out = tmp_path / "report"
    report_py.main([str(root), "--out", str(out), "--reps", "500"])
    stats = json.loads((out / "stats.json").read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}"))
    (row,) = stats["prior_gain"]
    assert row["method"] == "kgrl+lab" and row["seeds"] == 3
    assert row["seed_gains"] == pytest.approx([0.25, 0.0, 0.5])
    assert row["gain_over_seeds"]["mean"] == pytest.approx(0.25)
    pooled = np.array(sum(policy.values(), [])) - np.array(prior * 3)
    assert row["gain_pooled"]["mean"] == pytest.approx(pooled.mean()) and row["gain_pooled"]["n_pairs"] == 12
    assert 0.0 <= row["gain_over_seeds"]["ci_low"] <= 0.25 <= row["gain_over_seeds"]["ci_high"] <= 0.5
    # (5k, 10k]: rows 7200 and 9600 -> 0.5; the last 5k, (9400, 14400]: rows 9600, 12000, 14400 -> 1/3
    assert row["training_early"] == pytest.approx(0.5) and row["training_late"] == pytest.approx(1 / 3)
    text = (out / "prior_gain.md").read_text()
    assert "| kgrl+lab | 3 |" in text and "+0.250" in text
    # beside the bootstrap: the t-interval over the 3 seeds (t(0.975, 2) = 4.302653 from a table), the sign
    # and Wilcoxon tests, the verdict, and the seeds the rule asks (trials of <= 30 min: 10)
    s = row["seed_stats"]
    half = 4.302653 * np.std([0.25, 0.0, 0.5], ddof=1) / math.sqrt(3)
    assert (s["t_low"], s["t_high"]) == pytest.approx((0.25 - half, 0.25 + half), abs=1e-6)
    assert (s["sign_positive"], s["sign_negative"], s["sign_zeros"]) == (2, 0, 1) and s["sign_p"] == pytest.approx(0.5)
    assert s["verdict"] == "not established" and (s["ci_low"], s["ci_high"]) == (
        row["gain_over_seeds"]["ci_low"], row["gain_over_seeds"]["ci_high"])
    assert row["seed_ids"] == [0, 1, 2] and row["trial_minutes"] == 21.0 and row["seeds_needed"] == 10
    assert f"| [{0.25 - half:+.3f}, {0.25 + half:+.3f}] | sign 2+/0- p 0.5; Wilcoxon p 0.5 | not established |" in text
    assert "| 10 (21 min): 7 short |" in text


def test_method_pairs_difference_methods_on_the_same_episodes(report_py, tmp_path):
    """Labelled variants with known per-episode outcomes: B minus A per seed that both ran on the same
    episodes (left out: a seed only one ran, a seed evaluated with another eval seed or on another processor, a
    variant with another world count; the episodes either side lost to a blow-up, NaN), its mean over seeds, and all
    paired episodes
    pooled, against a hand computation; a run from before per-world outcomes were recorded pairs with
    nothing (and does not stop the report)."""
    root = tmp_path / "sweep"
    outcomes = {"a": {0: [1, 0, 0, 0], 1: [0, 0, 0, 0], 2: [1, 1, 0, 0], 3: [1, 1, 1, 1], 5: [1, 1, 0, 0]},
                "b": {0: [1, 1, NAN, 0], 1: [1, 1, 1, 0], 2: [1, 1, 1, 1], 4: [0, 0, 0, 0], 5: [0, 0, 1, 1]},
                "c": {0: [1, 1, 1, 1]}, "d": {0: [1, 1, 1, 1], 1: [0, 0, 0, 0]}}
    eval_seeds = {("a", 2): 7}  # seed 2 of a on other episodes than b's
    processors = {("b", 5): "AMD EPYC (family 25 model 1)"}  # seed 5 of b played on another CPU than a's (unnamed)
    num_envs = {"d": 4}  # d: 4 worlds x 1 round, 4 outcomes as a's and b's, but other episodes
    for label, runs in outcomes.items():
        for seed, outcome in runs.items():
            d = write_run(root, 4, f"sac+{label}", seed, (np.nanmean(outcome), 1.0, NAN, 10.0))
            config = json.loads((d / "config.json").read_text())
            (d / "config.json").write_text(json.dumps({**config, "method": "sac", "label": label,
                                                       "num_envs": num_envs.get(label, 2)}))
            m = json.loads((d / "metrics.json").read_text())
            if label == "c":  # an older run: per-episode summaries, no per-world outcomes, no eval seed
                m.update(per_episode=[{"success_rate": 1.0, "num_episodes": 2}] * 2)
            else:
                rounds = [{"world_success": outcome[:2]}, {"world_success": outcome[2:]}]
                m.update(per_episode=[{"world_success": outcome}] if label in num_envs else rounds,
                         eval_seed=eval_seeds.get((label, seed), 10000))
                if (label, seed) in processors:
                    m["processor"] = processors[(label, seed)]
            (d / "metrics.json").write_text(strict_json(m))  # (as run.py writes it: a lost episode, NaN, is null)
    out = tmp_path / "report"
    report_py.main([str(root), "--out", str(out), "--reps", "500"])
    stats = json.loads((out / "stats.json").read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}"))
    (row,) = stats["method_pairs"]
    assert (row["a"], row["b"], row["seeds"]) == ("sac+a", "sac+b", [0, 1])
    # seed 0 over its 3 complete episodes: b 2/3, a 1/3; seed 1: 3/4 - 0
    assert row["seed_differences"] == pytest.approx([1 / 3, 0.75])
    assert row["over_seeds"]["mean"] == pytest.approx((1 / 3 + 0.75) / 2)
    assert 1 / 3 <= row["over_seeds"]["ci_low"] <= row["over_seeds"]["mean"] <= row["over_seeds"]["ci_high"] <= 0.75
    assert row["pooled"]["mean"] == pytest.approx(4 / 7) and row["pooled"]["n_pairs"] == 7
    # the pooled means named as the pair's A and B (A: 1 of 7 paired episodes, B: 5 of 7)
    assert (row["pooled"]["a_mean"], row["pooled"]["b_mean"]) == pytest.approx((1 / 7, 5 / 7))
    assert "a_mean" not in row["over_seeds"] and "b_mean" not in row["over_seeds"]
    assert (row["a_success"], row["b_success"]) == pytest.approx(((1 / 3 + 0) / 2, (2 / 3 + 0.75) / 2))
    text = (out / "method_pairs.md").read_text()
    assert "| sac+a | sac+b | 2 | 0.167 | 0.708 | +0.542 [" in text
    # two seeds: t(0.975, 1) = 12.706205 (a table's), so wide that B's lead is not established
    s = row["seed_stats"]
    half = 12.706205 * np.std([1 / 3, 0.75], ddof=1) / math.sqrt(2)
    assert (s["t_low"], s["t_high"]) == pytest.approx(((1 / 3 + 0.75) / 2 - half, (1 / 3 + 0.75) / 2 + half), abs=1e-6)
    assert s["sign_p"] == pytest.approx(0.5) and s["verdict"] == "not established"
    assert "| sign 2+/0- p 0.5; Wilcoxon p 0.5 | not established |" in text and "beats" not in text.split("|---|")[-1]
    assert row["seeds_needed"] is None and "? (trial time not recorded)" in text  # these runs recorded none


def test_report_refuses_bad_reps_before_writing(report_py, runs, tmp_path, capsys):
    out = tmp_path / "r"
    with pytest.raises(SystemExit) as exc:
        report_py.main([str(runs), "--out", str(out), "--reps", "-5"])
    assert exc.value.code == 2 and "--reps -5" in capsys.readouterr().err and not out.exists()


def test_a_sac_field_a_run_predates_counts_at_its_default(report_py):
    """A run written before a SACConfig field existed shares a cell with one that records its default
    (as run.py --resume reads it), not with one that sets another value."""
    base = {"task": "PegInsert", "method": "kgrl", "env": "factory", "action_dim": 4, "seed": 0, "num_envs": 16,
            "sac": {"batch_size": 256}}
    newer = {**base, "seed": 1, "sac": {"batch_size": 256, "prior_reg": 0.0}}
    other = {**base, "seed": 2, "sac": {"batch_size": 256, "prior_reg": 1.0}}
    assert report_py.identity(base) == report_py.identity(newer)
    assert report_py.identity(base)["sac"]["prior_reg"] == 0.0 and report_py.identity(base)["sac"]["batch_size"] == 256
    assert report_py.identity(other) != report_py.identity(base)


def test_curves_draw_a_labelled_variant_as_its_own_line():
    from vkgrl_newton.results.plots import group_label

    base = {"method": "kgrl", "time_obs": True}
    assert group_label(base) == "kgrl" and group_label({**base, "label": "reach3"}) == "kgrl+reach3"
    assert group_label({**base, "label": "reach3", "time_obs": False}) == "kgrl+reach3 (no time obs)"


def test_a_report_reads_its_copy_of_the_runs_again(report_py, runs, tmp_path):
    """A report keeps a copy of the runs it read: given alone (the run directories gone) it yields
    the same tables and statistics; given with the runs themselves each run counts once; given with a
    later run, that run joins its cell; two runs sharing their last two path names get distinct copies."""
    first = tmp_path / "first"
    report_py.main([str(runs), "--out", str(first), "--reps", "300"])
    copy = first / "runs" / "PegInsert_factory_4d_kgrl" / "seed2"
    for f in ("config.json", "metrics.json", "curves.jsonl"):
        assert (copy / f).read_bytes() == (runs / "PegInsert_factory_4d_kgrl" / "seed2" / f).read_bytes()
    moved = tmp_path / "elsewhere"
    runs.rename(moved)  # the run directories are gone from where the report read them
    again = tmp_path / "again"
    report_py.main([str(first), "--out", str(again), "--reps", "300"])
    for f in ("results.csv", "tables.md"):
        assert (again / f).read_text() == (first / f).read_text(), f
    stats, stats_again = (json.loads((r / "stats.json").read_text()) for r in (first, again))
    for m in ("kgrl", "sac"):  # the point estimates (the intervals are resampled)
        assert stats_again["iqm"][m]["value"] == stats["iqm"][m]["value"]
    both = tmp_path / "both"
    report_py.main([str(moved), str(first), "--out", str(both), "--reps", "300"])
    assert (both / "results.csv").read_text() == (first / "results.csv").read_text()
    assert len(report_py.find_runs([moved, first])) == 12 and not any(
        report_py.is_archived(d) for d in report_py.find_runs([moved, first]))
    later = tmp_path / "later"
    write_run(later, 4, "kgrl", 3, (0.1, 1.0, NAN, 1.0))
    merged = tmp_path / "merged"
    report_py.main([str(first), str(later), "--out", str(merged), "--reps", "300"])
    r = next(r for r in csv.DictReader((merged / "results.csv").open())
             if (r["metric"], r["action_dim"], r["method"]) == ("success_rate", "4", "kgrl"))
    assert int(r["n"]) == 4 and float(r["mean"]) == pytest.approx((0.5 + 0.7 + 0.9 + 0.1) / 4)
    # the same <configuration>/seed<k> from two sweeps (another label, so not a twin): two copies
    other = tmp_path / "other_sweep"
    d = write_run(other, 4, "kgrl", 3, (0.3, 1.0, NAN, 1.0))
    config = json.loads((d / "config.json").read_text())
    (d / "config.json").write_text(json.dumps({**config, "label": "x"}))
    two = tmp_path / "two"
    report_py.main([str(later), str(other), "--out", str(two), "--reps", "300"])
    copies = sorted(p.parent.relative_to(two / "runs").as_posix() for p in (two / "runs").rglob("metrics.json"))
    assert copies == ["PegInsert_factory_4d_kgrl/seed3", "other_sweep__PegInsert_factory_4d_kgrl/seed3"]


def test_the_a_zero_level_names_the_runs_base(tmp_path):
    """The success panel's a = 0 line says what a = 0 was: the KMP prior, or the --kgrl-base controller."""
    import json

    from vkgrl_newton.results.plots import reference_levels

    configs = [{"task": "PegInsert", "env": "factory", "action_dim": 4, "method": "kgrl"}]
    for base, want in ((None, "KMP prior (a = 0), final eval 0.141"),
                       ("centre_latent", "centre_latent controller (a = 0), final eval 0.859")):
        runs = []
        for seed in (0, 1):
            run = tmp_path / f"{base}_{seed}"
            run.mkdir()
            metrics = {"prior_eval": {"success_rate": 0.859 if base else 0.141}}
            if base:
                metrics["kgrl_base"] = base
            (run / "metrics.json").write_text(json.dumps(metrics))
            runs.append(run)
        assert [lv[0] for lv in reference_levels(runs, configs) if lv[2] == "prior"] == [want]
