"""The residual recipe against the quick preset's default (reach_keep_prior), seed by seed on the same 128 episodes
and the same machine (issue 40: "what wins becomes the quick preset's recipe"). The recipe's runs are
docs/results/base_floor4_40's (the same options given one by one; `--kgrl-recipe residual` was that RunConfig, tests/
test_kgrl_base.py; kgrl's is `--kgrl-recipe residual --kgrl-search-press 1` since 46bd6e0); the default's are this
folder's report. Student-t over seeds, sign and Wilcoxon tests
(vkgrl_newton.results.seeds.over_seeds); each run's own a = 0 beside it.

    python docs/results/recipe_40/analyse.py        (finished seeds only)
"""
import json
from pathlib import Path

import numpy as np

from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds

HERE = Path(__file__).parent
RECIPE = HERE.parent / "base_floor4_40" / "report" / "runs"
DEFAULT = HERE / "report" / "runs"
ARMS = {"kgrl": ("PegInsert_factory_4d_kgrl+base_centre_search_seat5_floor4_s0.2", "PegInsert_factory_4d_kgrl"),
        "vision_kgrl": ("PegInsert_factory_4d_vision_kgrl+base_cl_seat5_floor4_s0.2", "PegInsert_factory_4d_vision_kgrl")}


def episodes(per_episode) -> np.ndarray:
    """(rounds * worlds,) success, round-major."""
    return np.concatenate([np.asarray(r["world_success"], dtype=float) for r in per_episode])


def runs(root: Path, name: str) -> dict[int, dict]:
    out = {}
    for p in (root / name).glob("seed*"):
        if (p / "metrics.json").exists():
            m = json.loads((p / "metrics.json").read_text())
            out[int(p.name[4:])] = {"policy": episodes(m["per_episode"]), "a0": episodes(m["prior_eval"]["per_episode"]),
                                    "cpu": m.get("cpu"), "eval_seed": m["eval_seed"]}
    return out


prior = json.loads((HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json").read_text())
rec = prior["controllers"]["prior"]["records"]
kmp = np.array([float(r["success"]) for r in sorted(rec, key=lambda r: (r["round"], r["world"]))])
print(f"KMP prior (GMR, no floors, this machine: {prior['cpu']}): {int(kmp.sum())} / {kmp.size} = {kmp.mean():.3f}")
found = {}
for method, (recipe_name, default_name) in ARMS.items():
    r, d = runs(RECIPE, recipe_name), runs(DEFAULT, default_name)
    found[method] = (r, d)
    seeds = sorted(set(r) & set(d))
    print(f"\n{method}: seeds {seeds} (residual {sorted(r)}, default {sorted(d)})")
    if not seeds:
        continue
    assert len({x["eval_seed"] for x in (*r.values(), *d.values())}) == 1, "one set of evaluation episodes"
    for label, group in (("residual", r), ("reach_keep_prior (default)", d)):
        a0 = {k: v["a0"].mean() for k, v in group.items()}
        rates = [group[k]["policy"].mean() for k in seeds]
        print(f"  {label}: policy per seed {', '.join(f'{v:.3f}' for v in rates)}, mean {np.mean(rates):.3f}; "
              f"its a = 0 {', '.join(sorted(set(f'{v:.3f}' for v in a0.values())))}")
        g = over_seeds([group[k]["policy"].mean() - group[k]["a0"].mean() for k in seeds])
        print(f"    minus its a = 0: mean {g['mean']:+.3f}, t {format_t(g)}, {format_tests(g)}: {g['verdict']}")
        g = over_seeds([group[k]["policy"].mean() - kmp.mean() for k in seeds])
        print(f"    minus the KMP prior: mean {g['mean']:+.3f}, t {format_t(g)}, {format_tests(g)}: {g['verdict']}")
    diff = [r[k]["policy"].mean() - d[k]["policy"].mean() for k in seeds]
    s = over_seeds(diff)
    print(f"  residual minus default, per seed {', '.join(f'{v:+.3f}' for v in diff)}: mean {s['mean']:+.3f}, "
          f"t {format_t(s)}, {format_tests(s)}: {s['verdict']}")

# vision minus blind within each recipe, seed by seed (claims.md C3)
for i, label in ((0, "residual"), (1, "reach_keep_prior (default)")):
    v, b = found["vision_kgrl"][i], found["kgrl"][i]
    seeds = sorted(set(v) & set(b))
    if len(seeds) >= 2:
        diff = [v[k]["policy"].mean() - b[k]["policy"].mean() for k in seeds]
        s = over_seeds(diff)
        print(f"\nvision_kgrl minus kgrl, {label}, seeds {seeds}: per seed {', '.join(f'{x:+.3f}' for x in diff)}: mean "
              f"{s['mean']:+.3f}, t {format_t(s)}, {format_tests(s)}: {s['verdict']}")
