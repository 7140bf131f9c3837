"""Learning curves of train/run.py runs: mean +- std over seeds, one line per method (thesis Figs. 6.11-6.18).

    python train/plot_runs.py runs/train/PegInsert_*_factory_4d_seed* --out runs/plots/peg_factory_4d.png

Reads each run's tensorboard scalars (episode reward, success rate, mean contact force) and its
config.json; runs are grouped by method (and by --no-time-obs), each group's curves are put on a
common grid of env transitions (linear interpolation, up to the shortest run of the group) and
drawn as mean +- one standard deviation across its seeds. The output PNG is never overwritten.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton._io import atomic_write  # noqa: E402

PANELS = (("episode/reward", "episode reward"), ("episode/success_rate", "success rate"),
          ("episode/mean_contact_force", "mean contact force (N)"))


def read_run(run_dir: Path) -> tuple[dict, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """(config, {tag: (transitions, values)}) of one run directory."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    config_path = run_dir / "config.json"
    if not config_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a train/run.py run directory (no config.json)")
    config = json.loads(config_path.read_text())
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
    label = config["method"]
    return label if config.get("time_obs", True) else label + " (no time obs)"


def mean_std(runs: list[tuple[np.ndarray, np.ndarray]], points: int = 100):
    """Common grid up to the shortest run; (grid, mean, std) across runs."""
    end = min(steps[-1] for steps, _ in runs)
    start = max(steps[0] for steps, _ in runs)
    grid = np.linspace(start, end, points) if end > start else np.array([end])
    stacked = np.stack([np.interp(grid, steps, values) for steps, values in runs])
    return grid, stacked.mean(0), stacked.std(0)


def plot(run_dirs: list[Path], out: Path, title: str | None = None) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list[dict]] = defaultdict(list)
    titles = set()
    for run_dir in run_dirs:
        config, curves = read_run(run_dir)
        groups[group_label(config)].append(curves)
        titles.add(f"{config['task']} {config['env']} {config['action_dim']}D")
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 3.8))
    summary = {}
    for label, members in sorted(groups.items()):
        summary[label] = {"seeds": len(members)}
        for ax, (tag, name) in zip(axes, PANELS):
            runs = [c[tag] for c in members if tag in c and len(c[tag][0])]
            if not runs:
                continue
            grid, mean, std = mean_std(runs)
            line, = ax.plot(grid, mean, label=f"{label} (n={len(runs)})")
            ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
            summary[label][tag] = {"final_mean": float(mean[-1]), "final_std": float(std[-1])}
    for ax, (_, name) in zip(axes, PANELS):
        ax.set_xlabel("env transitions")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title or " / ".join(sorted(titles)))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    atomic_write(out, overwrite=False, write=lambda f: f.write(buf.getvalue()), suffix=".png")
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="run directories of train/run.py")
    ap.add_argument("--out", type=Path, default=Path("runs/plots/learning_curves.png"), help="PNG (never overwritten)")
    ap.add_argument("--title", default=None)
    args = ap.parse_args(argv)
    if args.out.exists():
        ap.error(f"--out {args.out} exists; choose another path (files are never overwritten)")
    for d in args.run_dirs:
        if not (d / "config.json").exists():
            ap.error(f"{d} is not a train/run.py run directory (no config.json)")
    summary = plot(args.run_dirs, args.out, args.title)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
