"""Per-seed comparisons of base_floor4_40 (issue 40): each arm against its base (the run's a = 0), against the KMP
prior measured on the same machine and episodes (docs/results/intel_prior_40), and the camera arm against the blind
arm seed by seed. Student-t over seeds, sign and Wilcoxon tests (vkgrl_newton.results.seeds.over_seeds).

    python docs/results/base_floor4_40/analyse.py [RUNS_DIR ...]   (default: report/runs; finished seeds only)
"""
import json
import sys
from pathlib import Path

import numpy as np

from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds

HERE = Path(__file__).parent
roots = [Path(a) for a in sys.argv[1:]] or [HERE / "report" / "runs"]
ARMS = {"camera": "PegInsert_factory_4d_vision_kgrl+base_cl_seat5_floor4_s0.2",
        "blind": "PegInsert_factory_4d_kgrl+base_centre_search_seat5_floor4_s0.2"}


def episodes(per_episode) -> np.ndarray:
    """(rounds * worlds,) success in ceiling order (round-major)."""
    return np.concatenate([np.asarray(r["world_success"], dtype=float) for r in per_episode])


prior = json.loads((HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json").read_text())
rec = prior["controllers"]["prior"]["records"]
kmp = np.array([float(r["success"]) for r in sorted(rec, key=lambda r: (r["round"], r["world"]))])
print(f"KMP prior (GMR, this machine: {prior['cpu']}): {int(kmp.sum())} / {kmp.size} = {kmp.mean():.3f}")

per = {}
for arm, name in ARMS.items():
    seeds = sorted((p for r in roots for p in (r / name).glob("seed*") if (p / "metrics.json").exists()),
                   key=lambda p: int(p.name[4:]))
    rows = []
    for s in seeds:
        m = json.loads((s / "metrics.json").read_text())
        pol, base = episodes(m["per_episode"]), episodes(m["prior_eval"]["per_episode"])
        assert pol.size == base.size == kmp.size
        rows.append((int(s.name[4:]), pol, base))
    per[arm] = {seed: pol for seed, pol, _ in rows}
    if not rows:
        continue
    base = rows[0][2]
    assert all(np.array_equal(b, base) for _, _, b in rows), "the base is one deterministic controller"
    print(f"\n{arm} ({name}), seeds {[r[0] for r in rows]}")
    print(f"  base (a = 0): {int(base.sum())} / {base.size} = {base.mean():.3f}")
    succ = [p.mean() for _, p, _ in rows]
    print("  policy per seed:", ", ".join(f"{v:.3f}" for v in succ), f"mean {np.mean(succ):.3f}")
    for what, ref in (("minus its base", base), ("minus the KMP prior", kmp)):
        d = [p.mean() - ref.mean() for _, p, _ in rows]
        s = over_seeds(d)
        print(f"  {what}: per seed {', '.join(f'{v:+.3f}' for v in d)}; mean {s['mean']:+.3f}, t {format_t(s)}, "
              f"{format_tests(s)}: {s['verdict']}")
    fixed = [int(((p == 1) & (base == 0)).sum()) for _, p, _ in rows]
    broken = [int(((p == 0) & (base == 1)).sum()) for _, p, _ in rows]
    print(f"  of the base's {int((base == 0).sum())} failures it seats {fixed}; of its {int(base.sum())} successes it "
          f"loses {broken}")

both = sorted(set(per["camera"]) & set(per["blind"]))
if len(both) >= 2:
    d = [per["camera"][k].mean() - per["blind"][k].mean() for k in both]
    s = over_seeds(d)
    print(f"\ncamera arm minus blind arm, seeds {both}: per seed {', '.join(f'{v:+.3f}' for v in d)}; mean "
          f"{s['mean']:+.3f}, t {format_t(s)}, {format_tests(s)}: {s['verdict']}")
