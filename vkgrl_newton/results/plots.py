"""Learning curves of train/run.py runs: mean +- std over seeds, one line per method (thesis
Figs. 6.11-6.18); the one plotting path of train/plot_runs.py and train/report.py.

Each group's curves are put on a common grid of env transitions (linear interpolation, up to the
shortest run of the group) and drawn as mean +- one standard deviation (numpy's, ddof 0) across
its seeds. The success panel also draws the levels a learned curve is read against (`reference_levels`): the
thesis's final success of each method, the KMP prior's (a = 0) on the runs' evaluation episodes, and the task's
ceiling measured on those episodes (results.ceiling: the privileged scripted demonstrator and oracle, the blind
search). The curve itself is the training episodes' success (stochastic actions, changing episodes); the levels
are final evaluations: a curve near a level is comparable to it, not equal.
"""

from __future__ import annotations

import io
from collections import defaultdict
from pathlib import Path

import numpy as np

from vkgrl_newton._io import atomic_write, read_json_object, short_repr
from vkgrl_newton.results.curves import CURVES_FILE, read_curves

PANELS = (("episode/reward", "episode reward"), ("episode/success_rate", "success rate"),
          ("episode/mean_contact_force", "mean contact force (N)"))  # tensorboard tags (train/run.py)
PANEL_CURVE_KEYS = ("episode_reward", "success_rate", "mean_contact_force")  # the same in curves.jsonl


# what plot() reads of a run's config.json, and the types it must have (label and time_obs may be absent)
CONFIG_KINDS = {"task": str, "env": str, "action_dim": int, "method": str, "label": (str, type(None)),
                "time_obs": bool}
OPTIONAL_CONFIG_KEYS = ("label", "time_obs")


def read_run_config(run_dir: Path) -> dict:
    """A run's config.json; FileNotFoundError if missing, ValueError in one line naming the file if it is
    not a UTF-8 JSON object or lacks (or mistypes) what the curves are grouped and titled by (CONFIG_KINDS)."""
    config_path = Path(run_dir) / "config.json"
    if not config_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a train/run.py run directory (no config.json)")
    config = read_json_object(config_path, "run's config.json")
    for key, kind in CONFIG_KINDS.items():
        if key not in config:
            if key in OPTIONAL_CONFIG_KEYS:
                continue
            raise ValueError(f"{config_path} is damaged: it has no {key!r}")
        value = config[key]
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is int):
            raise ValueError(f"{config_path} is damaged: its {key} is {short_repr(value)}")
    return config


def read_run(run_dir: Path) -> tuple[dict, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """(config, {tag: (transitions, values)}) of one run directory: from its curves.jsonl, or
    from its tensorboard scalars for a run older than curves.jsonl. A damaged config.json or curves.jsonl
    is a ValueError in one line naming the file (read_run_config, results.curves.read_curves)."""
    run_dir = Path(run_dir)
    config = read_run_config(run_dir)
    if (run_dir / CURVES_FILE).exists():
        rows = read_curves(run_dir)
        steps = np.array([r["transitions"] for r in rows], dtype=np.float64)
        return config, {tag: (steps, np.array([r[key] for r in rows], dtype=np.float64))
                        for (tag, _), key in zip(PANELS, PANEL_CURVE_KEYS) if rows}
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    curves = {}
    for tag, _ in PANELS:
        if tag in acc.Tags()["scalars"]:
            events = acc.Scalars(tag)
            steps = np.array([e.step for e in events], dtype=np.float64)
            values = np.array([e.value for e in events], dtype=np.float64)
            order = np.argsort(steps, kind="stable")
            curves[tag] = (steps[order], values[order])
    return config, curves


def group_label(config: dict) -> str:
    """The line a run belongs to: its method, `<method>+<label>` for a labelled variant (run.py
    --label, as report.py's tables name it), and whether its policy saw time."""
    label = config["method"] + (f"+{config['label']}" if config.get("label") else "")
    return label if config.get("time_obs", True) else label + " (no time obs)"


def mean_std(runs: list[tuple[np.ndarray, np.ndarray]], points: int = 100):
    """Common grid up to the shortest run; (grid, mean, std) across runs."""
    end = min(steps[-1] for steps, _ in runs)
    start = max(steps[0] for steps, _ in runs)
    grid = np.linspace(start, end, points) if end > start else np.array([end])
    stacked = np.stack([np.interp(grid, steps, values) for steps, values in runs])
    return grid, stacked.mean(0), stacked.std(0)


def reference_levels(run_dirs: list[Path], configs: list[dict]) -> list[tuple[str, float, str]]:
    """(label, success rate, kind) of the levels drawn on the success panel, kind one of "thesis:<method>",
    "prior", "ceiling:<controller>"; [] unless every run is of one task, family and action space. The prior's
    level only where every run that has a metrics.json evaluated it on the same episodes with one result; the
    ceiling only where every run's evaluation is the ceiling's (eval seed and worlds)."""
    from vkgrl_newton.results.ceiling import ceiling_levels
    from vkgrl_newton.results.thesis import load_thesis_tables

    keys = {(c["task"], c["env"], c["action_dim"]) for c in configs}
    if len(keys) != 1:
        return []
    task, env, dim = keys.pop()
    levels = []
    thesis = load_thesis_tables()
    for method in sorted({c["method"] for c in configs}):
        mean, _ = thesis.get(("success_rate", task, method, env, dim), (float("nan"), float("nan")))
        if np.isfinite(mean):
            levels.append((f"thesis {method} (1 M transitions) {mean:.3f}", float(mean), f"thesis:{method}"))
    priors = set()
    for run_dir in run_dirs:
        path = Path(run_dir) / "metrics.json"
        if path.exists():
            metrics = read_json_object(path, "run's metrics.json")
            prior = metrics.get("prior_eval")
            rate = prior.get("success_rate") if isinstance(prior, dict) else None
            # a = 0 is the KMP prior, or with --kgrl-base that controller (metrics.json carries the run's meta)
            base = metrics.get("kgrl_base", "prior")
            priors.add((rate, base) if isinstance(rate, (int, float)) and not isinstance(rate, bool) else None)
    if len(priors) == 1 and None not in priors:
        rate, base = priors.pop()
        what = "KMP prior" if base == "prior" else f"{base} controller"
        levels.append((f"{what} (a = 0), final eval {float(rate):.3f}", float(rate), "prior"))
    evals = {(c.get("eval_seed"), c.get("num_envs")) for c in configs}
    if len(evals) == 1:
        seed, worlds = evals.pop()
        if isinstance(seed, int) and isinstance(worlds, int):
            for c in ceiling_levels(task, env, dim, seed, worlds):
                name = "blind search" if c.controller == "search" else f"{c.controller} (privileged)"
                levels.append((f"{name} {c.successes}/{c.episodes}", c.rate, f"ceiling:{c.controller}"))
    return levels


# line styles of the reference levels (the thesis's take the colour of their method's curve)
_LEVEL_STYLE = {"prior": dict(color="0.45", linestyle=":", linewidth=1.5),
                "ceiling:scripted": dict(color="black", linestyle="-", linewidth=0.8),
                "ceiling:oracle": dict(color="black", linestyle="-.", linewidth=1.2),
                "ceiling:search": dict(color="0.45", linestyle="-.", linewidth=1.2)}


def plot(run_dirs: list[Path], out: Path, title: str | None = None) -> dict:
    """Learning curves of the runs, one line per method (group_label), mean +- std over seeds,
    to the PNG `out` (never overwritten); returns each group's final mean and std per panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list[dict]] = defaultdict(list)
    titles = set()
    configs = []
    method_of = {}
    for run_dir in run_dirs:
        config, curves = read_run(run_dir)
        configs.append(config)
        groups[group_label(config)].append(curves)
        method_of[group_label(config)] = config["method"]
        titles.add(f"{config['task']} {config['env']} {config['action_dim']}D")
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 3.8))
    summary = {}
    colours = {}
    for label, members in sorted(groups.items()):
        summary[label] = {"seeds": len(members)}
        for ax, (tag, name) in zip(axes, PANELS):
            runs = [c[tag] for c in members if tag in c and len(c[tag][0])]
            if not runs:
                continue
            grid, mean, std = mean_std(runs)
            line, = ax.plot(grid, mean, label=f"{label} (n={len(runs)})")
            colours.setdefault(method_of[label], line.get_color())
            ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
            summary[label][tag] = {"final_mean": float(mean[-1]), "final_std": float(std[-1])}
    success_ax = axes[[tag for tag, _ in PANELS].index("episode/success_rate")]
    levels = reference_levels(run_dirs, configs)
    for label, rate, kind in levels:
        style = _LEVEL_STYLE.get(kind) or dict(color=colours.get(kind.split(":", 1)[1], "C7"), linestyle="--",
                                                linewidth=1.0)
        success_ax.axhline(rate, label=label, **style)
    summary["reference_levels"] = {kind: rate for _, rate, kind in levels}
    if levels:
        success_ax.set_ylim(-0.02, 1.02)
        success_ax.legend(fontsize=7, loc="best")
    for ax, (_, name) in zip(axes, PANELS):
        ax.set_xlabel("env transitions")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:  # runs without curves yet: no empty-legend warning
        axes[0].legend(fontsize=8)
    else:
        axes[0].text(0.5, 0.5, "no curve rows yet", ha="center", va="center", transform=axes[0].transAxes)
    fig.suptitle(title or " / ".join(sorted(titles)))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    atomic_write(out, overwrite=False, write=lambda f: f.write(buf.getvalue()), suffix=".png")
    return summary
