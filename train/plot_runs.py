"""Learning curves of train/run.py runs: mean +- std over seeds, one line per method (thesis Figs. 6.11-6.18).

    python train/plot_runs.py runs/train/PegInsert_*_factory_4d_seed* --out runs/plots/peg_factory_4d.png

Reads each run's curves.jsonl (or, for older runs, its tensorboard scalars: episode reward,
success rate, mean contact force) and its config.json; runs are grouped by method (and by
--no-time-obs), each group's curves are put on a common grid of env transitions (linear
interpolation, up to the shortest run of the group) and drawn as mean +- one standard deviation
across its seeds (vkgrl_newton/results/plots.py). The output PNG is never overwritten.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton._io import one_line, output_path_error, read_json_object  # noqa: E402
from vkgrl_newton.results.curves import CURVE_KEYS, read_curves  # noqa: E402
from vkgrl_newton.results.plots import plot, read_run_config  # noqa: E402


def check_run_files(run_dir: Path) -> None:
    """ValueError in one line naming the file when a run's config.json or curves.jsonl is damaged."""
    config = read_json_object(run_dir / "config.json", "run's config.json")
    if not isinstance(config.get("method"), str) or not isinstance(config.get("label"), (str, type(None))):
        raise ValueError(f"{run_dir / 'config.json'} is damaged: its method (or label) is not a name")
    read_run_config(run_dir)  # task, env, action_dim: what the plot's titles and groups read
    try:
        for row in read_curves(run_dir):
            if not all(isinstance(row[k], (int, float)) and not isinstance(row[k], bool) for k in CURVE_KEYS):
                raise ValueError("a row holds a value that is not a number")
    except (ValueError, TypeError, AttributeError) as e:  # (a row that is no JSON object)
        raise ValueError(one_line(f"{run_dir / 'curves.jsonl'} is damaged ({e})")) from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="run directories of train/run.py")
    ap.add_argument("--out", type=Path, default=Path("runs/plots/learning_curves.png"), help="PNG (never overwritten)")
    ap.add_argument("--title", default=None)
    args = ap.parse_args(argv)
    if why := output_path_error(args.out, "--out", what="files"):  # (exists, or cannot be written)
        ap.error(why)
    for d in args.run_dirs:
        if not (d / "config.json").exists():
            ap.error(f"{d} is not a train/run.py run directory (no config.json)")
        try:  # what results/plots.py reads, checked before any plotting: a damaged file is one line
            check_run_files(d)
        except ValueError as e:
            ap.error(str(e))
    summary = plot(args.run_dirs, args.out, args.title)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
