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

from vkgrl_newton.results.plots import plot  # noqa: E402


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
