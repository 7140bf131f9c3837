"""Issue 40 item 5: what the residual recipe reaches at 50k, 100k, 150k and 200k transitions on PegInsert Factory 4D,
seed by seed on the same 128 episodes (eval seed 10000), against its a = 0 (the base controller), the KMP prior, its
own 30k level (docs/results/base_floor4_40: the same RunConfig, seeds paired), the ceiling and the thesis.

Each trial is one 200k run (`--keep-at 50000 100000 150000`, grids here); its kept policies are scored afterwards on
the run's own evaluation episodes by train/evaluate.py (tests/test_keep_at.py: the same episodes as metrics.json's):

    python docs/results/budget_40/analyse.py evaluate SWEEP_DIR ...   # each kept policy not yet scored -> kept/
    python docs/results/budget_40/analyse.py                          # the tables (analysis.txt) and curves_*.png

Student-t over seeds, sign and Wilcoxon tests (vkgrl_newton.results.seeds.over_seeds); one seed shows nothing.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(ROOT))

from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds  # noqa: E402

KEPT = HERE / "kept"  # kept/<arm>/seed<S>/at_<N>.json: evaluate.py's results for the kept policies
REPORT = HERE / "report" / "runs"  # train/report.py's copies of the 200k runs
AT_30K = HERE.parent / "base_floor4_40" / "report_seeds0-9" / "runs"
ARMS = {  # this study's run name, the runs of the same RunConfig at 30k, the thesis's level at ~1M
    "vision_kgrl": ("PegInsert_factory_4d_vision_kgrl+residual",
                    AT_30K / "PegInsert_factory_4d_vision_kgrl+base_cl_seat5_floor4_s0.2", 0.993),
    # the press-1 recipe (before 46bd6e0): paused for the firmer search, one seed finished
    "kgrl": ("PegInsert_factory_4d_kgrl+residual",
             AT_30K / "PegInsert_factory_4d_kgrl+base_centre_search_seat5_floor4_s0.2", 0.797),
    # the residual recipe since 46bd6e0 (its blind search pressing 2.5 mm): the kgrl arm of item 5
    "kgrl_press": ("PegInsert_factory_4d_kgrl+residual_press2.5",
                   HERE.parent / "search_reach_40" / "report_seeds0-9" / "runs" /
                   "PegInsert_factory_4d_kgrl+residual_press2.5", 0.797),
}
CEILING = 1.0  # the privileged oracle and the scripted demonstrator on these 128 episodes (docs/results/ceiling_40)
CACHE = ROOT / "runs" / "cache"  # (the cache the runs were trained with: their prior, VAE and probe)


def success(per_episode) -> np.ndarray:
    """(rounds * worlds,) success, round-major."""
    return np.concatenate([np.asarray(r["world_success"], dtype=float) for r in per_episode])


def evaluate(sweeps: list[Path]) -> None:
    """Score every kept policy of the sweeps' trials that has no result yet, one at a time (a core each)."""
    for sweep in sweeps:
        for ckpt in sorted(sweep.glob("*/seed*/checkpoints/at_*.pt")):
            run_dir = ckpt.parents[1]
            config = json.loads((run_dir / "config.json").read_text())
            out = KEPT / run_dir.parent.name / run_dir.name / f"{ckpt.stem}.json"
            if out.exists():
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, str(ROOT / "train" / "evaluate.py"), "--checkpoint", str(ckpt),
                   "--num-envs", str(config["num_envs"]), "--episodes", str(config["eval_episodes"]),
                   "--eval-seed", str(config["eval_seed"]), "--json", str(out), "--cache-dir", str(CACHE)]
            print(" ".join(cmd), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def points(arm: str) -> tuple[dict[int, dict[int, np.ndarray]], dict[int, np.ndarray]]:
    """{transitions: {seed: per-episode success}} over the kept policies, the 200k finals and the 30k runs of the
    seeds this study ran; and {seed: a = 0's per-episode success} (the base controller, from the runs' metrics.json:
    the 200k run's, else the 30k run's of the same RunConfig, whose a = 0 is the same controller)."""
    name, at_30k, _ = ARMS[arm]
    by_budget: dict[int, dict[int, np.ndarray]] = {}
    a0: dict[int, np.ndarray] = {}
    for run in sorted((REPORT / name).glob("seed*")):
        m = json.loads((run / "metrics.json").read_text())
        seed = int(run.name[4:])
        by_budget.setdefault(int(m["training"]["transitions"]), {})[seed] = success(m["per_episode"])
        a0[seed] = success(m["prior_eval"]["per_episode"])
    for f in sorted((KEPT / name).glob("seed*/at_*.json")):
        n = int(f.stem[3:])
        by_budget.setdefault(n, {})[int(f.parent.name[4:])] = success(json.loads(f.read_text())["per_episode"])
    ran = {seed for runs in by_budget.values() for seed in runs}
    for run in sorted(at_30k.glob("seed*")):
        seed = int(run.name[4:])
        if seed in ran:  # the seeds this study ran
            m = json.loads((run / "metrics.json").read_text())
            by_budget.setdefault(int(m["training"]["transitions"]), {})[seed] = success(m["per_episode"])
            a0.setdefault(seed, success(m["prior_eval"]["per_episode"]))
    return dict(sorted(by_budget.items())), a0


def analyse() -> None:
    prior = json.loads((HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json").read_text())
    rec = prior["controllers"]["prior"]["records"]
    kmp = np.array([float(r["success"]) for r in sorted(rec, key=lambda r: (r["round"], r["world"]))])
    lines = [f"KMP prior (GMR, no floors, {prior['cpu']}): {int(kmp.sum())} / {kmp.size} = {kmp.mean():.3f}"]
    for arm, (name, _, thesis) in ARMS.items():
        by_budget, a0 = points(arm)
        if not a0:
            lines.append(f"\n{arm}: no kept policy or finished 200k run yet")
            continue
        base = np.mean([v.mean() for v in a0.values()])
        lines.append(f"\n{arm} ({name}): a = 0 (its base controller) {base:.3f}; the thesis {thesis:.3f} at ~1M")
        first = min(by_budget)
        for n, runs in by_budget.items():
            seeds = sorted(runs)
            rates = [runs[s].mean() for s in seeds]
            row = (f"  {n // 1000:>3}k, seeds {seeds}: {np.mean(rates):.3f} "
                   f"(per seed {', '.join(f'{r:.3f}' for r in rates)})")
            if len(seeds) >= 2:
                g = over_seeds([runs[s].mean() - a0[s].mean() for s in seeds])
                row += f"; minus a = 0 {g['mean']:+.3f} t {format_t(g)} {format_tests(g)}: {g['verdict']}"
                g = over_seeds([runs[s].mean() - kmp.mean() for s in seeds])
                row += f"; minus the KMP prior {g['mean']:+.3f} t {format_t(g)}: {g['verdict']}"
                both = sorted(set(seeds) & set(by_budget[first]))
                if n != first and len(both) >= 2:
                    g = over_seeds([runs[s].mean() - by_budget[first][s].mean() for s in both])
                    row += (f"; minus {first // 1000}k (seeds {both}) {g['mean']:+.3f} t {format_t(g)} "
                            f"{format_tests(g)}: {g['verdict']}")
            lines.append(row)
        plot(arm, by_budget, base, kmp.mean(), thesis)
    text = "\n".join(lines)
    print(text)
    (HERE / "analysis.txt").write_text(text + "\n")


def plot(arm: str, by_budget: dict, base: float, kmp: float, thesis: float) -> None:
    """The training episodes' success (curves.jsonl, mean over seeds) and the paired points (mean, t-interval)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = ARMS[arm][0]
    fig, ax = plt.subplots(figsize=(7, 4))
    grid = np.linspace(0, max(by_budget), 200)
    curves = []
    for run in sorted((REPORT / name).glob("seed*")):
        rows = [json.loads(x) for x in (run / "curves.jsonl").read_text().splitlines() if x.strip()]
        t = np.array([r["transitions"] for r in rows], dtype=float)
        x = np.array([r["success_rate"] for r in rows], dtype=float)
        # the mean over 20 neighbouring evaluations, over fewer at the ends (not zeros padded in)
        s = np.convolve(x, np.ones(20), mode="same") / np.convolve(np.ones_like(x), np.ones(20), mode="same")
        curves.append(np.interp(grid, t, s))  # (held at the last value past it: the run ends a step short of N)
    if curves:
        ax.plot(grid, np.nanmean(curves, axis=0), color="0.6", lw=1, label="training episodes (stochastic)")
    xs, means, lo, hi = [], [], [], []
    for n, runs in by_budget.items():
        stats = over_seeds([r.mean() for r in runs.values()])
        xs.append(n)
        means.append(stats["mean"])
        lo.append(stats["mean"] - (stats["t_low"] if stats.get("t_low") is not None else stats["mean"]))
        hi.append((stats["t_high"] if stats.get("t_high") is not None else stats["mean"]) - stats["mean"])
    ax.errorbar(xs, means, yerr=[lo, hi], fmt="o-", color="C0", capsize=3,
                label="the same 128 episodes: mean, t 95 % over seeds")
    for y, label, color, ls in ((CEILING, "privileged oracle and demonstrator (ceiling_40, AMD)", "k", "-"),
                                (base, "a = 0 (its base controller)", "C2", "--"), (kmp, "KMP prior", "C3", ":"),
                                (thesis, "thesis (~1M)", "k", "-.")):
        ax.axhline(y, color=color, ls=ls, lw=1, label=f"{label} {y:.3f}")
    ax.set(xlabel="transitions", ylabel="success rate", ylim=(0, 1.02), title=f"PegInsert Factory 4D, {arm}")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / f"curves_{arm}.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    if sys.argv[1:2] == ["evaluate"]:
        evaluate([Path(p) for p in sys.argv[2:]])
    else:
        analyse()
