"""The README's tables from the JSON files beside it (tools/ceiling.py's output).

    python docs/results/ceiling_40/tables.py [--reclassify] [FILE.json ...]

--reclassify: each record's category again from the current `classify` (pure: from the record's own numbers),
written back into the file with the controllers' counts (after a change of the rules, no physics rerun).

Per task and controller: success at the last step and at any step, the failure categories; per pair of
runs of one controller on the same episodes (a perturbation study), how many outcomes flip.
"""

import json
import math
import sys
from pathlib import Path

from vkgrl_newton._io import atomic_write_text, strict_json
from vkgrl_newton.tools.ceiling import CATEGORIES, category_counts, classify

HERE = Path(__file__).parent
SHORT = {"success": "ok", "seated_then_lost": "lost", "seated_but_test_missed": "test", "tilted_or_slipped_in_grasp": "grasp",
         "time_out_inserting": "slow", "held_above_seat": "held", "jammed_in_hole": "jam-in", "jammed_on_chamfer": "jam-ch",
         "time_out_searching": "off", "other": "other"}


def reclassify(path: Path) -> None:
    d = json.loads(path.read_text())
    for c in d["controllers"].values():
        for r in c["records"]:
            r["category"] = classify({k: (float("nan") if v is None else v) for k, v in r.items()})
        c["categories"] = category_counts(c["records"])
    atomic_write_text(path, strict_json(d, indent=1) + "\n", overwrite=True)


def table(path: Path) -> None:
    d = json.loads(path.read_text())
    print(f"\n{d['task']} ({path.name}; {d['episodes_per_world']} x {d['num_envs']} episodes, eval seed {d['eval_seed']}"
          f"{', kp +%d ulp' % d['perturb_kp_ulp'] if d['perturb_kp_ulp'] else ''})")
    print("| controller | success (last step) | success (any step) | " + " | ".join(SHORT[c] for c in CATEGORIES) + " |")
    print("|---|---:|---:|" + "---:|" * len(CATEGORIES))
    for name, c in d["controllers"].items():
        n = c["episodes"]
        cats = " | ".join(str(c["categories"][k]) for k in CATEGORIES)
        print(f"| {name} | {c['n_success']}/{n} ({c['success']:.3f}) | {c['n_success_any']}/{n} ({c['success_any']:.3f}) "
              f"| {cats} |")


def flips(a_path: Path, b_path: Path, name: str = "prior") -> None:
    a = json.loads(a_path.read_text())["controllers"][name]["records"]
    b = json.loads(b_path.read_text())["controllers"][name]["records"]
    for key in ("success", "success_any"):
        xa = [r[key] for r in a]
        xb = [r[key] for r in b]
        gained = sum(1 for u, v in zip(xa, xb) if v and not u)
        lost = sum(1 for u, v in zip(xa, xb) if u and not v)
        n = len(xa)
        f = (gained + lost) / n
        print(f"{name} {key}: {sum(xa)} -> {sum(xb)} of {n}; flipped {gained + lost} ({gained} gained, {lost} lost), "
              f"flip rate {f:.3f}; sd of a rate difference ~ sqrt(f / n) = {math.sqrt(f / n):.3f}; "
              f"n for +-0.02 at 95 %: {math.ceil(f * (1.96 / 0.02) ** 2)}")


if __name__ == "__main__":
    args = sys.argv[1:]
    fix = "--reclassify" in args
    paths = [Path(p) for p in args if p != "--reclassify"] or sorted(HERE.glob("*.json"))
    for p in paths:
        if fix:
            reclassify(p)
        table(p)
    base, pert = HERE / "PegInsert.json", HERE / "PegInsert_prior_kp_ulp1.json"
    if base.exists() and pert.exists() and "prior" in json.loads(base.read_text())["controllers"]:
        print()
        flips(base, pert)
