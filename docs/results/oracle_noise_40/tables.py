"""The README's table from the JSON files beside it and ceiling_40's (tools/ceiling.py's output).

    python docs/results/oracle_noise_40/tables.py

PegInsert Factory 4D, the 128 paired episodes (eval seed 10000). Per controller: success at the last step with
its exact (Clopper-Pearson) 95 % interval, episodes gained and lost against the prior with the exact McNemar
(binomial) p, the failure categories; for the oracle with a lateral bias of sigma per axis, the share of biases
inside the 0.807 mm catch, P(|b| < catch) = 1 - exp(-catch^2 / (2 sigma^2)) (Rayleigh): what it would seat if it
seated exactly the episodes whose bias lands the part inside the catch. For the blind controllers, success split
by whether the episode's observation noise on the target (x, y) is inside the catch.

Second table: the learned policies of the committed studies (30k transitions, seeds 0-4, the same episodes) against
each controller: per seed, its success minus the controller's on the same 128 episodes; over seeds, results.seeds'
Student-t interval, sign and Wilcoxon tests and verdict. A controller is deterministic on these episodes, so
the interval covers the spread over training seeds on these 128 episodes only: it leaves out how these episodes
sample the task (a rate on 128 episodes has a standard error of up to 0.044), as every paired number here does. kgrl and kgrl --obs-history 4 from their run copies;
vision_kgrl (older code) from its report's per-seed gains over the same prior.
"""

import json
import math
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds
from vkgrl_newton.tools.ceiling import CATEGORIES, CEILING_GEOMETRY

HERE = Path(__file__).parent
CEIL = HERE.parent / "ceiling_40"
SHORT = {"success": "ok", "seated_then_lost": "lost", "seated_but_test_missed": "test", "tilted_or_slipped_in_grasp": "grasp",
         "time_out_inserting": "slow", "held_above_seat": "held", "jammed_in_hole": "jam-in", "jammed_on_chamfer": "jam-ch",
         "time_out_searching": "off", "other": "other"}
ROWS = [  # (label, file, controller key, what it knows of the lateral error)
    ("prior", CEIL / "PegInsert.json", "prior", "nothing (a = 0)"),
    ("search", CEIL / "PegInsert.json", "search", "nothing: spiral about where blocked"),
    ("centre", HERE / "PegInsert_centre.json", "centre", "the observation: TCP over the observed target (1 mm noise)"),
    ("centre_search", HERE / "PegInsert_centre_search.json", "centre_search", "the observation: spiral about the observed target"),
    ("oracle, sigma 1.0 mm", HERE / "PegInsert_sigma1.0.json", "oracle", "true error + N(0, 1.0^2) bias per axis"),
    ("oracle, sigma 0.5 mm", HERE / "PegInsert_sigma0.5.json", "oracle", "true error + N(0, 0.5^2) bias per axis"),
    ("oracle, sigma 0.25 mm", HERE / "PegInsert_sigma0.25.json", "oracle", "true error + N(0, 0.25^2) bias per axis"),
    ("oracle, sigma 0", CEIL / "PegInsert_oracle.json", "oracle", "the true error"),
    ("oracle_latent", HERE / "PegInsert_latent.json", "oracle_latent",
     "the camera: the VAE latent through the near-hole probe (z privileged)"),
    ("centre_latent", HERE / "PegInsert_latent.json", "centre_latent",
     "the camera, nothing privileged: centre steering by the probe's estimate"),
]


def main() -> None:
    catch = 1e3 * CEILING_GEOMETRY["PegInsert"].catch
    prior_rec = json.loads((CEIL / "PegInsert.json").read_text())["controllers"]["prior"]["records"]
    prior = [r["success"] for r in prior_rec]
    print("| controller | knows of the lateral error | success [exact 95 %] | Rayleigh P(b inside the catch) | gained / lost vs prior "
          "(McNemar p) | success, obs noise inside / outside the catch | " + " | ".join(SHORT[c] for c in CATEGORIES) + " |")
    print("|---|---|---|---:|---|---|" + "---:|" * len(CATEGORIES))
    for label, path, key, knows in ROWS:
        if not path.exists():
            print(f"| {label} | {knows} | not run | | | | " + " | ".join("" for _ in CATEGORIES) + " |")
            continue
        d = json.loads(path.read_text())
        rec = d["controllers"][key]["records"]
        # paired episode by episode: the same episodes in the same order (their observation noise identical)
        if [r["obs_noise_mm"] for r in rec] != [r["obs_noise_mm"] for r in prior_rec]:
            raise SystemExit(f"{path}: its episodes are not the prior's (ceiling_40/PegInsert.json)")
        s = np.array([r["success"] for r in rec])
        n, k = len(s), int(s.sum())
        ci = binomtest(k, n).proportion_ci(method="exact")
        sigma = d.get("oracle_lateral_noise_mm", 0.0) if key == "oracle" else None
        ray = f"{1 - math.exp(-catch ** 2 / (2 * sigma ** 2)):.3f}" if sigma else ""
        g = sum(1 for a, b in zip(prior, s) if b and not a)
        lo = sum(1 for a, b in zip(prior, s) if a and not b)
        p = binomtest(g, g + lo).pvalue if g + lo else 1.0
        on = np.array([math.hypot(*r["obs_noise_mm"][:2]) for r in rec]) < catch
        split = " / ".join(f"{s[m].mean():.3f} ({m.sum()})" if m.any() else "none" for m in (on, ~on))
        cats = " | ".join(str(d["controllers"][key]["categories"][c]) for c in CATEGORIES)
        print(f"| {label} | {knows} | {k}/{n} ({k / n:.3f}) [{ci.low:.3f}, {ci.high:.3f}] | {ray} | {g} / {lo} ({p:.2g}) "
              f"| {split} | {cats} |")


def learned() -> dict[str, list[float]]:
    """Per-seed final success (seeds 0-4) of the committed learned runs on these episodes."""
    res = HERE.parent
    out = {}
    for label, d in (("kgrl (quick default)", res / "kgrl_force_40/report/runs/PegInsert_factory_4d_kgrl+reach_keep_prior"),
                     ("kgrl --obs-history 4", res / "hist_time_40/report/runs/PegInsert_factory_4d_kgrl+obs_history_4")):
        runs = sorted(d.glob("seed*/metrics.json"), key=lambda f: int(f.parent.name[4:]))
        out[label] = [json.loads(f.read_text())["success_rate"] for f in runs]
    st = json.loads((res / "vision_kgrl_28e/report/stats.json").read_text())["prior_gain"][0]
    out["vision_kgrl (issue 28's code)"] = [st["prior_success"] + g for g in st["seed_gains"]]
    for label, d in (("vision_kgrl (today's code)", res / "vision_probe_40/report/runs/PegInsert_factory_4d_vision_kgrl+reach_keep_prior"),
                     ("vision_kgrl --vision-probe-obs", res / "vision_probe_40/report/runs/PegInsert_factory_4d_vision_kgrl+vision_probe")):
        runs = sorted(d.glob("seed*/metrics.json"), key=lambda f: int(f.parent.name[4:]))
        if len(runs) >= 2:  # (the study's seeds as they come in; the row says how many)
            out[label + ("" if len(runs) == 5 else f", seeds {', '.join(f.parent.name[4:] for f in runs)}")] = \
                [json.loads(f.read_text())["success_rate"] for f in runs]
    return out


def against() -> None:
    print("\n| learned (seeds 0-4) | per seed | minus centre (t) | minus search (t) | minus centre_search (t) | "
          "minus oracle sigma 1.0 (t) | minus oracle sigma 0.5 (t) | minus centre_latent (t) |")
    print("|---|---|---|---|---|---|---|---|")
    rows = {label: (path, key) for label, path, key, _ in ROWS}
    refs = []
    for label in ("centre", "search", "centre_search", "oracle, sigma 1.0 mm", "oracle, sigma 0.5 mm", "centre_latent"):
        path, key = rows[label]
        refs.append(float(np.mean([r["success"] for r in json.loads(path.read_text())["controllers"][key]["records"]]))
                    if path.exists() else None)
    for label, seeds in learned().items():
        cells = []
        for ref in refs:
            if ref is None:
                cells.append("not run")
                continue
            o = over_seeds(np.asarray(seeds) - ref)
            cells.append(f"{o['mean']:+.3f} {format_t(o)} {o['verdict']}; {format_tests(o)}")
        print(f"| {label} | {', '.join(f'{v:.3f}' for v in seeds)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
    against()
