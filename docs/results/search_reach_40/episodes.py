"""Episode by episode: what the firmer-search residual gains and loses against its own base (a = 0).

Reads the run copies of report_seeds0-9 (each run's final evaluation and its a = 0 on the same 128 episodes) and
prints, per seed, the base's failures the policy seats and the base's successes it loses, then over seeds.
Usage: python docs/results/search_reach_40/episodes.py [> episodes.txt]
"""
import json
from pathlib import Path

import numpy as np

RUNS = Path(__file__).parent / "report_seeds0-9" / "runs" / "PegInsert_factory_4d_kgrl+residual_press2.5"


def seated(per_episode: list[dict]) -> np.ndarray:
    """Success of each episode in evaluation order (the worlds of each round, round after round)."""
    return np.array([w for r in per_episode for w in r["world_success"]], dtype=bool)


def main() -> None:
    policy, base = [], None
    for run in sorted(RUNS.glob("seed*"), key=lambda p: int(p.name[4:])):
        m = json.loads((run / "metrics.json").read_text())
        p, a = seated(m["per_episode"]), seated(m["prior_eval"]["per_episode"])
        assert base is None or (a == base).all(), "a = 0 differs between seeds: not paired"
        base = a
        policy.append(p)
        print(f"{run.name}: {p.mean():.3f}; of the base's {int((~a).sum())} failures seated {int((p & ~a).sum())}, "
              f"of its {int(a.sum())} successes lost {int((~p & a).sum())}")
    s = np.array(policy)
    gained, lost = (s & ~base).sum(1), (~s & base).sum(1)
    print(f"over {len(s)} seeds: gained {gained.mean():.1f} (range {gained.min()}-{gained.max()}), "
          f"lost {lost.mean():.1f} (range {lost.min()}-{lost.max()}) episodes of 128")
    print(f"the base's failures some seed seats: {int((~base & s.any(0)).sum())} of {int((~base).sum())}; "
          f"its successes every seed keeps: {int((base & s.all(0)).sum())} of {int(base.sum())}; "
          f"episodes no seed seats: {int((~s.any(0)).sum())}")
    print(f"a policy that kept every base success and gained as these do: {(base.sum() + gained.mean()) / 128:.3f}")


if __name__ == "__main__":
    main()
