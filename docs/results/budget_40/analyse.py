"""Issue 40 item 5: what the residual recipe reaches at 50k, 100k, 150k and 200k transitions on PegInsert Factory 4D,
seed by seed on the same 128 episodes (eval seed 10000), against its a = 0 (the base controller), the KMP prior, its
own 30k level (docs/results/base_floor4_40: the same RunConfig, seeds paired), the ceiling and the thesis.

Each trial is one 200k run (`--keep-at 50000 100000 150000`, grids here); its kept policies are scored afterwards on
the run's own evaluation episodes by train/evaluate.py (tests/test_keep_at.py: the same episodes as metrics.json's):

    python docs/results/budget_40/analyse.py evaluate SWEEP_DIR ...   # each kept policy not yet scored -> kept/
    python docs/results/budget_40/analyse.py                          # the tables (analysis.txt) and curves_*.png

Two machines ran it: an Intel Xeon (the sessions up to 2026-12-07 15:18) and an AMD EPYC (from 15:39). The same
episodes seat differently on the two (float32 rounding through chaotic contact: docs/results/intel_prior_40), so each
trial is paired only with evaluations of its own machine: its kept policies (scored there), its a = 0 and the KMP
prior of that machine, and its 30k point (the Intel seeds: the 30k study's run of the same RunConfig and seed; the
AMD seeds: the policy the run kept at 30 000, the same training step for step). A seed is named by machine and number
(i0 = Intel seed 0, a1 = AMD seed 1); the differences over seeds pool both machines, each difference within one.

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

KEPT = HERE / "kept"  # kept/<arm>/[amd_]seed<S>/at_<N>.json: evaluate.py's results for the kept policies
INTEL, AMD = "Intel(R) Xeon(R) Processor", "AMD EPYC"  # runtime.cpu_model() on the two machines
KEPT_PREFIX = {INTEL: "", AMD: "amd_"}  # the seed directories under kept/ by machine (the same seed ran on both)
# train/report.py's copies of the finished runs, by the machine that trained and evaluated them (these runs trained
# at commits whose metrics.json did not name the processor yet)
REPORTS = {HERE / "report" / "runs": INTEL, HERE / "report_amd" / "runs": AMD}
KMP_PRIOR = {  # the KMP prior (GMR, no floors) on the same 128 episodes, per machine
    INTEL: HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json",
    AMD: HERE.parent / "ceiling_40" / "PegInsert.json",
}
AT_30K = HERE.parent / "base_floor4_40" / "report_seeds0-9" / "runs"
ARMS = {  # this study's run name, the Intel runs of the same RunConfig at 30k, the thesis's level at ~1M
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
    from vkgrl_newton.runtime import cpu_model

    here = cpu_model()
    if here not in KEPT_PREFIX:
        sys.exit(f"analyse.py: this machine ({here}) is neither of the study's ({', '.join(KEPT_PREFIX)}): add it to "
                 "KEPT_PREFIX, REPORTS and KMP_PRIOR (its KMP prior on these episodes) first")
    for sweep in sweeps:
        for ckpt in sorted(sweep.glob("*/seed*/checkpoints/at_*.pt")):
            run_dir = ckpt.parents[1]
            config = json.loads((run_dir / "config.json").read_text())
            out = KEPT / run_dir.parent.name / f"{KEPT_PREFIX[here]}{run_dir.name}" / f"{ckpt.stem}.json"
            if out.exists():
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, str(ROOT / "train" / "evaluate.py"), "--checkpoint", str(ckpt),
                   "--num-envs", str(config["num_envs"]), "--episodes", str(config["eval_episodes"]),
                   "--eval-seed", str(config["eval_seed"]), "--json", str(out), "--cache-dir", str(CACHE)]
            print(" ".join(cmd), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def machine_of(result: dict) -> str:
    """The processor an evaluate.py result was made on: its `processor` field; the results before the field were all
    made on the Intel machine."""
    return result.get("processor", INTEL)


def label(key: tuple[str, int]) -> str:
    return f"{'i' if key[0] == INTEL else 'a'}{key[1]}"


def points(arm: str) -> tuple[dict[int, dict[tuple, np.ndarray]], dict[tuple, np.ndarray]]:
    """{transitions: {(machine, seed): per-episode success}} over the kept policies, the finished runs and the 30k
    runs of the Intel seeds this study ran; and {(machine, seed): a = 0's per-episode success} (the base controller,
    from the runs' metrics.json: the finished run's, else the Intel 30k run's of the same RunConfig, whose a = 0 is
    the same controller on the same machine)."""
    name, at_30k, _ = ARMS[arm]
    by_budget: dict[int, dict[tuple, np.ndarray]] = {}
    a0: dict[tuple, np.ndarray] = {}
    for report, machine in REPORTS.items():
        for run in sorted((report / name).glob("seed*")):
            m = json.loads((run / "metrics.json").read_text())
            key = (m.get("processor", machine), int(run.name[4:]))
            by_budget.setdefault(int(m["training"]["transitions"]), {})[key] = success(m["per_episode"])
            a0[key] = success(m["prior_eval"]["per_episode"])
    for f in sorted((KEPT / name).glob("*seed*/at_*.json")):
        result = json.loads(f.read_text())
        prefix, seed = f.parent.name.split("seed")
        if KEPT_PREFIX[machine_of(result)] != prefix:
            raise SystemExit(f"analyse.py: {f} was evaluated on {machine_of(result)}, not the machine its directory "
                             "names")
        key = (machine_of(result), int(seed))
        by_budget.setdefault(int(f.stem[3:]), {})[key] = success(result["per_episode"])
    ran = {key for runs in by_budget.values() for key in runs if key[0] == INTEL}
    for run in sorted(at_30k.glob("seed*")):  # (the Intel 30k study's runs)
        key = (INTEL, int(run.name[4:]))
        if key in ran:  # the Intel seeds this study ran
            m = json.loads((run / "metrics.json").read_text())
            by_budget.setdefault(int(m["training"]["transitions"]), {})[key] = success(m["per_episode"])
            a0.setdefault(key, success(m["prior_eval"]["per_episode"]))
    return dict(sorted(by_budget.items())), a0


def kmp_prior() -> dict[str, np.ndarray]:
    """{machine: the KMP prior's per-episode success on the 128 episodes}, round-major."""
    out = {}
    for machine, path in KMP_PRIOR.items():
        rec = json.loads(path.read_text())["controllers"]["prior"]["records"]
        out[machine] = np.array([float(r["success"]) for r in sorted(rec, key=lambda r: (r["round"], r["world"]))])
    return out


def analyse() -> None:
    kmp = kmp_prior()
    lines = [f"KMP prior (GMR, no floors) on {m}: {int(k.sum())} / {k.size} = {k.mean():.3f}" for m, k in kmp.items()]
    for arm, (name, _, thesis) in ARMS.items():
        by_budget, a0 = points(arm)
        if not a0:
            lines.append(f"\n{arm}: no kept policy or finished run yet")
            continue
        base = np.mean([v.mean() for v in a0.values()])
        lines.append(f"\n{arm} ({name}): a = 0 (its base controller) {base:.3f} over the seeds with one "
                     f"({', '.join(f'{label(k)} {v.mean():.3f}' for k, v in sorted(a0.items()))}); "
                     f"the thesis {thesis:.3f} at ~1M")
        for n, runs in by_budget.items():
            keys = sorted(runs)
            rates = [runs[k].mean() for k in keys]
            row = (f"  {n // 1000:>3}k, seeds [{', '.join(label(k) for k in keys)}]: {np.mean(rates):.3f} "
                   f"(per seed {', '.join(f'{r:.3f}' for r in rates)})")
            paired = [k for k in keys if k in a0]
            if len(paired) >= 2:
                g = over_seeds([runs[k].mean() - a0[k].mean() for k in paired])
                row += f"; minus a = 0 {g['mean']:+.3f} t {format_t(g)} {format_tests(g)}: {g['verdict']}"
            if len(keys) >= 2:
                g = over_seeds([runs[k].mean() - kmp[k[0]].mean() for k in keys])
                row += f"; minus the KMP prior {g['mean']:+.3f} t {format_t(g)}: {g['verdict']}"
            if n != 30_000 and 30_000 in by_budget:
                both = sorted(set(keys) & set(by_budget[30_000]))
                if len(both) >= 2:
                    g = over_seeds([runs[k].mean() - by_budget[30_000][k].mean() for k in both])
                    row += (f"; minus 30k (seeds [{', '.join(label(k) for k in both)}]) {g['mean']:+.3f} "
                            f"t {format_t(g)} {format_tests(g)}: {g['verdict']}")
            lines.append(row)
        plot(arm, by_budget, base, kmp, thesis)
    text = "\n".join(lines)
    print(text)
    (HERE / "analysis.txt").write_text(text + "\n")


def plot(arm: str, by_budget: dict, base: float, kmp: dict[str, np.ndarray], thesis: float) -> None:
    """The training episodes' success (curves.jsonl, mean over seeds) and the paired points (mean, t-interval)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = ARMS[arm][0]
    fig, ax = plt.subplots(figsize=(7, 4))
    grid = np.linspace(0, max(by_budget), 200)
    curves = []
    for run in sorted(run for report in REPORTS for run in (report / name).glob("seed*")):
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
    machines = {k[0] for runs in by_budget.values() for k in runs}
    lines = [(CEILING, "privileged oracle and demonstrator (ceiling_40, AMD)", "k", "-"),
             (base, "a = 0 (its base controller), mean over seeds", "C2", "--")]
    lines += [(k.mean(), f"KMP prior ({m.split()[0]})", "C3", ":" if m == INTEL else (0, (1, 3)))
              for m, k in kmp.items() if m in machines]
    for y, text, color, ls in lines + [(thesis, "thesis (~1M)", "k", "-.")]:
        ax.axhline(y, color=color, ls=ls, lw=1, label=f"{text} {y:.3f}")
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
