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
# runtime.processor_name() on the two machines; the results made before it existed (processor-less) are the Intel's
INTEL, AMD = "Intel(R) Xeon(R) Processor (family 6 model 207)", "AMD EPYC (family 25 model 1)"
MACHINES = {  # per machine: its short name, its seed directories' prefix under kept/ (the same seed ran on both),
    # the KMP prior (GMR, no floors) on the same 128 episodes, made there from that machine's own demonstrations
    INTEL: ("i", "", HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json"),
    AMD: ("a", "amd_", HERE / "PegInsert_prior_amd.json"),
}
# train/report.py's copies of the finished runs, by the machine that trained and evaluated them (these runs trained
# at commits whose metrics.json did not name the processor yet)
REPORTS = {HERE / "report" / "runs": INTEL, HERE / "report_amd" / "runs": AMD,
           HERE / "report_amd_100k" / "runs": AMD,  # (the AMD 100k runs: report.py keeps one plan per directory)
           HERE / "report_amd_vision_100k" / "runs": AMD}
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
BUDGETS = (30_000, 50_000, 100_000, 150_000, 200_000)  # the points of the curve
CEILING = 1.0  # the privileged oracle and the scripted demonstrator on these 128 episodes (docs/results/ceiling_40)
CACHE = ROOT / "runs" / "cache"  # (the cache the runs were trained with: their prior, VAE and probe)


def success(per_episode) -> np.ndarray:
    """(rounds * worlds,) success, round-major."""
    return np.concatenate([np.asarray(r["world_success"], dtype=float) for r in per_episode])


def evaluate(sweeps: list[Path]) -> None:
    """Score every kept policy of the sweeps' trials that has no result yet, one at a time (a core each)."""
    from vkgrl_newton.runtime import processor_name

    here = processor_name()
    known(here, "this machine")
    for sweep in sweeps:
        for ckpt in sorted(sweep.glob("*/seed*/checkpoints/at_*.pt")):
            run_dir = ckpt.parents[1]
            config = json.loads((run_dir / "config.json").read_text())
            out = KEPT / run_dir.parent.name / f"{MACHINES[here][1]}{run_dir.name}" / f"{ckpt.stem}.json"
            if out.exists():
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, str(ROOT / "train" / "evaluate.py"), "--checkpoint", str(ckpt),
                   "--num-envs", str(config["num_envs"]), "--episodes", str(config["eval_episodes"]),
                   "--eval-seed", str(config["eval_seed"]), "--json", str(out), "--cache-dir", str(CACHE)]
            print(" ".join(cmd), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def known(machine: str, what) -> str:
    if machine not in MACHINES:
        sys.exit(f"analyse.py: {what} ran on {machine}, neither of the study's machines ({', '.join(MACHINES)}): "
                 "add it to MACHINES (with its KMP prior on these episodes) and REPORTS first")
    return machine


def machine_of(result: dict, what) -> str:
    """The processor a result was made on: its `processor` field; the results from before the field were all made
    on the Intel machine."""
    return known(result.get("processor", INTEL), what)


def label(key: tuple[str, int]) -> str:
    return f"{MACHINES[key[0]][0]}{key[1]}"


def points(arm: str) -> tuple[dict[int, dict[tuple, np.ndarray]], dict[tuple, np.ndarray]]:
    """{transitions: {(machine, seed): per-episode success}} over the kept policies, the finished runs and the 30k
    runs of the Intel seeds this study ran; and {(machine, seed): a = 0's per-episode success} (the base controller,
    from the runs' metrics.json: the finished run's, else the Intel 30k run's of the same RunConfig, else another
    seed's finished run on the same machine: a = 0 is the same controller there, whatever the training seed). A
    finished run's final policy is a point only at one of BUDGETS (not a run finished early at a session's end)."""
    name, at_30k, _ = ARMS[arm]
    by_budget: dict[int, dict[tuple, np.ndarray]] = {}
    a0: dict[tuple, np.ndarray] = {}
    for report, machine in REPORTS.items():
        for run in sorted((report / name).glob("seed*")):
            m = json.loads((run / "metrics.json").read_text())
            if m.get("processor", machine) != machine:
                sys.exit(f"analyse.py: {run} ran on {m['processor']}, not {machine}, the machine of its report")
            key = (machine, int(run.name[4:]))
            n = int(m["training"]["transitions"])
            if n in BUDGETS:  # (a run finished early, at a session's end, gives its a = 0 but no budget point)
                by_budget.setdefault(n, {})[key] = success(m["per_episode"])
            a0[key] = success(m["prior_eval"]["per_episode"])
    for f in sorted((KEPT / name).glob("*seed*/at_*.json")):
        result = json.loads(f.read_text())
        prefix, seed = f.parent.name.split("seed")
        machine = machine_of(result, f)
        if MACHINES[machine][1] != prefix:
            sys.exit(f"analyse.py: {f} was evaluated on {machine}, not the machine its directory names")
        key = (machine, int(seed))
        by_budget.setdefault(int(f.stem[3:]), {})[key] = success(result["per_episode"])
    ran = {key for runs in by_budget.values() for key in runs if key[0] == INTEL}
    for run in sorted(at_30k.glob("seed*")):  # (the Intel 30k study's runs)
        key = (INTEL, int(run.name[4:]))
        if key in ran:  # the Intel seeds this study ran
            m = json.loads((run / "metrics.json").read_text())
            by_budget.setdefault(int(m["training"]["transitions"]), {})[key] = success(m["per_episode"])
            a0.setdefault(key, success(m["prior_eval"]["per_episode"]))
    # a = 0 has no training seed (train.py's prior_evaluation_key: one cached evaluation per configuration and
    # machine), so a seed whose run has not finished takes it from another seed's run on the same machine
    for machine in {k[0] for k in a0}:
        same = [v for k, v in a0.items() if k[0] == machine]
        if any(not np.array_equal(v, same[0], equal_nan=True) for v in same):
            raise SystemExit(f"analyse.py: {arm}'s runs on {machine} disagree on a = 0: not one configuration")
        for key in {k for runs in by_budget.values() for k in runs if k[0] == machine}:
            a0.setdefault(key, same[0])
    return dict(sorted(by_budget.items())), a0


def kmp_prior() -> dict[str, np.ndarray]:
    """{machine: the KMP prior's per-episode success on the 128 episodes}, round-major."""
    out = {}
    for machine, (_, _, path) in MACHINES.items():
        if not path.exists():  # (not measured yet on that machine)
            continue
        rec = json.loads(path.read_text())["controllers"]["prior"]["records"]
        out[machine] = np.array([float(r["success"]) for r in sorted(rec, key=lambda r: (r["round"], r["world"]))])
    return out


def analyse() -> None:
    kmp = kmp_prior()
    lines = [f"KMP prior (GMR, no floors) on {m}: {int(k.sum())} / {k.size} = {k.mean():.3f}" for m, k in kmp.items()]
    for arm, (name, _, thesis) in ARMS.items():
        by_budget, a0 = points(arm)
        if not by_budget:
            lines.append(f"\n{arm}: no kept policy or finished run yet")
            continue
        lines.append(f"\n{arm} ({name}): a = 0 (its base controller) "
                     f"{', '.join(f'{label(k)} {v.mean():.3f}' for k, v in sorted(a0.items())) or 'not yet'}; "
                     f"the thesis {thesis:.3f} at ~1M")
        for n, runs in by_budget.items():
            keys = sorted(runs)
            per_machine = "; ".join(
                f"{MACHINES[m][0]} {np.mean([runs[k].mean() for k in keys if k[0] == m]):.3f}"
                for m in MACHINES if any(k[0] == m for k in keys))
            row = (f"  {n // 1000:>3}k, seeds [{', '.join(label(k) for k in keys)}]: per seed "
                   f"{', '.join(f'{runs[k].mean():.3f}' for k in keys)} (mean by machine {per_machine})")
            # the differences: each within its seed's machine, pooled over both
            paired = [k for k in keys if k in a0]
            if len(paired) >= 2:
                g = over_seeds([runs[k].mean() - a0[k].mean() for k in paired])
                row += f"; minus a = 0 {g['mean']:+.3f} t {format_t(g)} {format_tests(g)}: {g['verdict']}"
            paired = [k for k in keys if k[0] in kmp]
            if len(paired) >= 2:
                g = over_seeds([runs[k].mean() - kmp[k[0]].mean() for k in paired])
                row += f"; minus the KMP prior {g['mean']:+.3f} t {format_t(g)}: {g['verdict']}"
            if n != 30_000 and 30_000 in by_budget:
                both = sorted(set(keys) & set(by_budget[30_000]))
                if len(both) >= 2:
                    g = over_seeds([runs[k].mean() - by_budget[30_000][k].mean() for k in both])
                    row += (f"; minus 30k (seeds [{', '.join(label(k) for k in both)}]) {g['mean']:+.3f} "
                            f"t {format_t(g)} {format_tests(g)}: {g['verdict']}")
            lines.append(row)
        plot(arm, by_budget, a0, kmp, thesis)
    text = "\n".join(lines)
    print(text)
    (HERE / "analysis.txt").write_text(text + "\n")


def plot(arm: str, by_budget: dict, a0: dict, kmp: dict[str, np.ndarray], thesis: float) -> None:
    """Per machine (their levels differ: each fits its own prior): the training episodes' success (curves.jsonl,
    mean over that machine's finished runs) and the paired points (mean over its seeds, t-interval), its a = 0 and
    its KMP prior; the ceiling and the thesis beside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = ARMS[arm][0]
    fig, ax = plt.subplots(figsize=(7, 4))
    grid = np.linspace(0, max(by_budget), 200)
    for i, (machine, (short, _, _)) in enumerate(MACHINES.items()):
        color, word = f"C{2 * i}", machine.split(" (")[0].replace("(R)", "")
        curves = []
        runs = [run for report, m in REPORTS.items() if m == machine for run in (report / name).glob("seed*")]
        for run in sorted(runs):
            rows = [json.loads(x) for x in (run / "curves.jsonl").read_text().splitlines() if x.strip()]
            t = np.array([r["transitions"] for r in rows], dtype=float)
            x = np.array([r["success_rate"] for r in rows], dtype=float)
            # the mean over 20 neighbouring evaluations, over fewer at the ends (not zeros padded in)
            sm = np.convolve(x, np.ones(20), mode="same") / np.convolve(np.ones_like(x), np.ones(20), mode="same")
            curves.append(np.interp(grid, t, sm))  # (held at the last value past it: the run ends a step short of N)
        if curves:
            ax.plot(grid, np.nanmean(curves, axis=0), color=color, lw=0.8, alpha=0.5,
                    label=f"{word}: training episodes (stochastic), {len(curves)} run(s)")
        xs, means, lo, hi = [], [], [], []
        for n, runs in by_budget.items():
            rates = [v.mean() for k, v in runs.items() if k[0] == machine]
            if not rates:
                continue
            stats = over_seeds(rates)
            xs.append(n)
            means.append(stats["mean"])
            lo.append(stats["mean"] - (stats["t_low"] if stats.get("t_low") is not None else stats["mean"]))
            hi.append((stats["t_high"] if stats.get("t_high") is not None else stats["mean"]) - stats["mean"])
        if not xs:
            continue
        ax.errorbar(xs, means, yerr=[lo, hi], fmt="o-", color=color, capsize=3,
                    label=f"{word} ({short}*): the same 128 episodes, mean and t 95 % over its seeds")
        base = [v.mean() for k, v in a0.items() if k[0] == machine]
        if base:
            ax.axhline(base[0], color=color, ls="--", lw=1, label=f"{word}: a = 0 (its base controller) {base[0]:.3f}")
        if machine in kmp:
            ax.axhline(kmp[machine].mean(), color=color, ls=":", lw=1,
                       label=f"{word}: KMP prior {kmp[machine].mean():.3f}")
    for y, text, ls in ((CEILING, "privileged oracle and demonstrator (ceiling_40)", "-"),
                        (thesis, "thesis (~1M)", "-.")):
        ax.axhline(y, color="k", ls=ls, lw=1, label=f"{text} {y:.3f}")
    ax.set(xlabel="transitions", ylabel="success rate", ylim=(0, 1.02), title=f"PegInsert Factory 4D, {arm}")
    ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / f"curves_{arm}.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    if sys.argv[1:2] == ["evaluate"]:
        evaluate([Path(p) for p in sys.argv[2:]])
    else:
        analyse()
