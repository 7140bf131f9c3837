"""Issue 40, "what would close the rest" of the blind arm: does the blind base's spiral reach far enough?

The blind residual (`--kgrl-recipe residual` for kgrl: a policy added to the `centre_search` controller) seats
0.78 of the episodes whose unseen landing error |e| is under 1.44 mm and 0.19 of those over 2 mm
(base_floor4_40/unseen_error.py); the search controller alone times out searching above 2 mm. This probe runs that
base controller, exactly as the recipe builds it (the prior's tables pressed 5 mm at the seat, `--kgrl-seat-press 5`;
the action path's 4 mm / 25 mm reach floors; envs.evaluation.task_search_params), on the same 128 episodes (eval
seed 10000) with one search setting changed at a time, and sets each beside |e|. No learning: what a = 0 reaches.

    python docs/results/search_reach_40/probe.py --variants base speed0.6 ... --json OUT.json   # a new file

Each variant is ~7 min on one core (tools/ceiling.py's recorder: success and the failure category per episode).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE.parent / "base_floor4_40"))

# one change each from the recipe's base (SearchParams: pitch 1.2 mm a turn, 0.3 mm a step along the spiral, z
# commanded 1 mm below the TCP while searching, the search begins once blocked at step >= 60 of 150)
VARIANTS = {
    "base": {},
    "speed0.15": {"speed_mm": 0.15},
    "press2.5": {"press_mm": 2.5},
    "speed0.45": {"speed_mm": 0.45},
    "speed0.6": {"speed_mm": 0.6},
    "pitch1.6": {"pitch_mm": 1.6},
    "nmin30": {"n_min": 30},
}
SEAT_PRESS_MM = 5.0  # the recipe's --kgrl-seat-press
EDGES_MM = (0.89, 1.44, 2.02)  # unseen_error.txt's quartiles of |e| on these episodes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--eval-seed", type=int, default=10_000,
                    help="the episodes (10000: every study's; another: held-out episodes for a setting chosen on those)")
    ap.add_argument("--cache-dir", default=str(ROOT / "runs" / "cache"))
    ap.add_argument("--json", type=Path, required=True, help="output, a new file (rewritten after each variant)")
    args = ap.parse_args(argv)
    if args.json.exists():
        ap.error(f"--json {args.json}: exists; name a new file")

    from vkgrl_newton.runtime import configure_warp, cpu_model

    configure_warp()
    import torch

    from unseen_error import unseen_error
    from vkgrl_newton._io import atomic_write_text, strict_json
    from vkgrl_newton.envs.evaluation import ORACLE_PUSH_MM, KMPCentrePolicy, task_search_params
    from vkgrl_newton.kmp.tables import with_seat_press
    from vkgrl_newton.tools.ceiling import build, run_controller, summary

    torch.set_num_threads(1)
    env, tables, _ = build("PegInsert", 16, args.cache_dir)
    tables = with_seat_press(tables, SEAT_PRESS_MM * 1e-3)
    out = {"cpu": cpu_model(), "eval_seed": args.eval_seed, "episodes": 128, "seat_press_mm": SEAT_PRESS_MM,
           "command": "python docs/results/search_reach_40/probe.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "variants": {}}
    for name in args.variants:
        params = dataclasses.replace(task_search_params("PegInsert"), **VARIANTS[name])
        policy = KMPCentrePolicy.with_floors(tables, env, params, push_mm=ORACLE_PUSH_MM, spiral=True)
        t0 = time.perf_counter()
        records, _ = run_controller(env, policy, 8, args.eval_seed, "PegInsert")
        err = unseen_error(records)
        ok = np.array([float(r["success"]) for r in sorted(records, key=lambda r: (r["round"], r["world"]))])
        bins = np.digitize(err, EDGES_MM)
        s = {**summary(records), "params": dataclasses.asdict(params),
             "by_quartile_of_unseen_error": [float(ok[bins == i].mean()) for i in range(4)],
             "wall_s": round(time.perf_counter() - t0, 1), "records": records}
        out["variants"][name] = s
        print(f"{name}: {s['n_success']}/128 = {s['success']:.3f}, by quartile of |e| "
              f"{', '.join(f'{v:.3f}' for v in s['by_quartile_of_unseen_error'])}; {s['categories']}; "
              f"{s['wall_s']:.0f} s", flush=True)
        atomic_write_text(args.json, strict_json(out, indent=1) + "\n", overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
