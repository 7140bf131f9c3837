"""The prior on the same 128 episodes, AMD (ceiling_40) against Intel (this folder), episode by episode.

    python docs/results/intel_prior_40/compare.py
"""
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
amd = json.loads((HERE.parent / "ceiling_40" / "PegInsert.json").read_text())
intel = json.loads((HERE / "PegInsert_prior_intel.json").read_text())
a, b = amd["controllers"]["prior"]["records"], intel["controllers"]["prior"]["records"]
assert [(r["round"], r["world"]) for r in a] == [(r["round"], r["world"]) for r in b]
print(f"AMD: {amd['cpu']}; Intel: {intel['cpu']}; {len(a)} episodes, eval seed {amd['eval_seed']} / {intel['eval_seed']}")


def col(recs, key):
    return np.array([r[key] for r in recs], dtype=float)


noise = np.abs(col(b, "obs_noise_mm") - col(a, "obs_noise_mm")).max()
print(f"the episode's draws (target observation noise): max difference {noise:.4f} mm")
d = np.abs(col(b, "offset_start_mm") - col(a, "offset_start_mm")).max(axis=1)
print(f"the held part's settled in-hand offset at the episode's start: differs > 0.01 mm in {(d > 0.01).sum()}, "
      f"> 0.1 mm in {(d > 0.1).sum()}, max {d.max():.2f} mm, median {np.median(d):.4f} mm")
for key in ("landing_lateral_mm", "lateral_final_mm"):
    print(f"{key}: median AMD {np.median(col(a, key)):.2f}, Intel {np.median(col(b, key)):.2f} mm")
sa, sb = col(a, "success").astype(bool), col(b, "success").astype(bool)
print(f"success AMD {sa.sum()}, Intel {sb.sum()}; both {(sa & sb).sum()}, AMD only {(sa & ~sb).sum()}, "
      f"Intel only {(~sa & sb).sum()}")
