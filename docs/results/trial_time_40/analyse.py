"""Where a trial's wall time goes (issue 40, item 5), from finished sweep trials: sweep.py's trial.json (started,
ended), the run's metrics.json (the training loop's wall time and first transition, the evaluations' wall times)
and its train.log (whether the prior's evaluation ran in this trial or came from the cache).

    python docs/results/trial_time_40/analyse.py SWEEP_DIR... --json timings.json

Phases: setup (process start to the first transition: imports, Warp's kernel cache, the prior, the VAE and probe,
the env), training (the loop: physics, camera, updates; metrics training.wall_s), evaluation (the policy on the
128 episodes), prior evaluation (a = 0 on the same episodes: once per configuration, cached), and the rest (writing
the checkpoint and the metrics, the paired statistics).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def trial_phases(run_dir: Path) -> dict | None:
    trial, metrics = run_dir / "trial.json", run_dir / "metrics.json"
    if not (trial.exists() and metrics.exists()):
        return None
    t, m = json.loads(trial.read_text()), json.loads(metrics.read_text())
    if t.get("state") != "done":
        return None
    log = (run_dir / "train.log").read_text(errors="replace") if (run_dir / "train.log").exists() else ""
    total = t["ended_unix"] - t["started_unix"]
    setup = m["training"]["first_transition_unix"] - t["started_unix"]
    train = m["training"]["wall_s"]
    evaluation = m.get("wall_s", 0.0)
    prior_cached = "the prior's evaluation: reused" in log
    prior = 0.0 if prior_cached or "prior_eval" not in m else m["prior_eval"]["wall_s"]
    return {"run": str(run_dir), "method": m["method"], "label": m.get("label"), "seed": m["seed"],
            "transitions": m["training"]["transitions"], "total_s": total, "setup_s": setup, "train_s": train,
            "eval_s": evaluation, "prior_eval_s": prior, "prior_eval_cached": prior_cached,
            "rest_s": total - setup - train - evaluation - prior,
            "loop_transitions_per_s": m["training"]["loop_transitions_per_s"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sweeps", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    rows = [r for sweep in args.sweeps for d in sorted(sweep.glob("*/seed*")) if (r := trial_phases(d))]
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(f"{r['method']}+{r['label']}" if r["label"] else r["method"], []).append(r)
    print("| configuration | trials | total min | setup min | training min (transitions/s) | evaluation min | "
          "prior evaluation min (ran in) | rest min |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, rs in groups.items():
        med = {k: statistics.median(r[k] / 60 for r in rs) for k in ("total_s", "setup_s", "train_s", "eval_s",
                                                                      "rest_s")}
        ran = [r["prior_eval_s"] / 60 for r in rs if r["prior_eval_s"]]
        rate = statistics.median(r["loop_transitions_per_s"] for r in rs)
        print(f"| {name} | {len(rs)} | {med['total_s']:.1f} | {med['setup_s']:.1f} | {med['train_s']:.1f} "
              f"({rate:.1f}) | {med['eval_s']:.1f} | {statistics.median(ran) if ran else 0:.1f} ({len(ran)}) | "
              f"{med['rest_s']:.1f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
