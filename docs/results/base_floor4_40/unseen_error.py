"""Issue 40: why the blind residual stops near 0.58 and the camera's near 0.92, episode by episode.

On PegInsert Factory 4D two things the proprioceptive policy never observes decide where the held peg lands: the
noise on the observed target frame (Factory's 1 mm obs noise; the policy aims at the observed target) and the
peg's in-hand offset from the TCP. A controller that brings the TCP onto the observed target lands the peg at
        e = noise_xy + R_x(pi) offset_xy = (noise_x + offset_x, noise_y - offset_y)
from the hole (the TCP points down, roll pi, and steers its yaw to 0 before the descent). Both come per episode
from the ceiling's records of the same 128 episodes (eval seed 10000; intel_prior_40, this study's machine), where
`obs_noise_mm` is the observed target minus the true tip and `offset_start_mm` the held origin in the TCP frame.

This script sets |e| beside each episode's success over the seeds of base_floor4_40 (report_seeds0-9): the blind
residual (10 seeds), the camera residual (5 seeds), their a = 0 base controllers and the KMP prior; it bins the
episodes by quartiles of |e|, gives Spearman's rank correlation over the 128 episodes, and draws
unseen_error.png. Nothing is trained or simulated here.

    python docs/results/base_floor4_40/unseen_error.py   # -> unseen_error.txt, unseen_error.png
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

HERE = Path(__file__).resolve().parent
RUNS = HERE / "report_seeds0-9" / "runs"
RECORDS = HERE.parent / "intel_prior_40" / "PegInsert_prior_intel.json"
ARMS = {"blind residual (kgrl)": "PegInsert_factory_4d_kgrl+base_centre_search_seat5_floor4_s0.2",
        "camera residual (vision_kgrl)": "PegInsert_factory_4d_vision_kgrl+base_cl_seat5_floor4_s0.2"}


def success(per_episode) -> np.ndarray:
    """(rounds * worlds,) success, round-major (the order of the ceiling's records sorted by round, world)."""
    return np.concatenate([np.asarray(r["world_success"], dtype=float) for r in per_episode])


def unseen_error(records) -> np.ndarray:
    """(E,) |e| mm, the landing error a TCP on the observed target gives (module docstring)."""
    rec = sorted(records, key=lambda r: (r["round"], r["world"]))
    noise = np.array([r["obs_noise_mm"][:2] for r in rec])
    offset = np.array([r["offset_start_mm"][:2] for r in rec])
    return np.linalg.norm(noise + offset * np.array([1.0, -1.0]), axis=1)


def main() -> None:
    data = json.loads(RECORDS.read_text())
    records = data["controllers"]["prior"]["records"]
    err = unseen_error(records)
    kmp = np.array([float(r["success"]) for r in sorted(records, key=lambda r: (r["round"], r["world"]))])
    edges = np.quantile(err, [0.25, 0.5, 0.75])
    bins = np.digitize(err, edges)
    labels = [f"<{edges[0]:.2f}", f"{edges[0]:.2f}-{edges[1]:.2f}", f"{edges[1]:.2f}-{edges[2]:.2f}",
              f">{edges[2]:.2f}"]
    rows: dict[str, np.ndarray] = {"KMP prior": kmp}
    for arm, name in ARMS.items():
        runs = sorted((RUNS / name).glob("seed*/metrics.json"))
        metrics = [json.loads(f.read_text()) for f in runs]
        rows[f"{arm}, a = 0 (its base)"] = success(metrics[0]["prior_eval"]["per_episode"])
        rows[f"{arm}, {len(runs)} seeds"] = np.mean([success(m["per_episode"]) for m in metrics], axis=0)
    lines = [f"PegInsert Factory 4D, the same 128 episodes (eval seed 10000); {data['cpu']}",
             "|e| = |noise_xy + R_x(pi) offset_xy| mm, the landing error the blind policy cannot observe "
             f"(median {np.median(err):.2f}, max {err.max():.2f}; the entry's catch {data['thresholds_mm']['catch']:.2f})",
             f"success by quartile of |e| (mm), 32 episodes each: {' | '.join(labels)}; Spearman rho over episodes"]
    for label, s in rows.items():
        rho, p = spearmanr(err, s)
        per_bin = ", ".join(f"{s[bins == i].mean():.3f}" for i in range(4))
        lines.append(f"  {label:<48} {s.mean():.3f}  by quartile {per_bin}  rho {rho:+.2f} (p {p:.1e})")
    blind = rows[f"blind residual (kgrl), {len(list((RUNS / ARMS['blind residual (kgrl)']).glob('seed*')))} seeds"]
    never = blind == 0
    lines.append(f"  the blind residual never seats {int(never.sum())} episodes (|e| median {np.median(err[never]):.2f} "
                 f"mm) and always seats {int((blind == 1).sum())} (|e| median {np.median(err[blind == 1]):.2f} mm)")
    text = "\n".join(lines)
    print(text)
    (HERE / "unseen_error.txt").write_text(text + "\n")
    plot(err, rows, edges)


def plot(err: np.ndarray, rows: dict[str, np.ndarray], edges: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    order = np.argsort(err)
    window = 16  # a running mean over 16 neighbouring episodes (by |e|)
    styles = ["C3:", "C2--", "C2-", "C0--", "C0-"]
    for (label, s), style in zip(rows.items(), styles):
        smooth = np.convolve(s[order], np.ones(window) / window, mode="valid")
        ax.plot(err[order][window // 2 - 1:window // 2 - 1 + smooth.size], smooth, style[:2], ls=style[2:],
                label=f"{label} ({s.mean():.3f})")
    for e in edges:
        ax.axvline(e, color="0.85", lw=0.8)
    ax.set(xlabel="|e|: landing error the blind policy cannot observe (mm)",
           ylabel="success (running mean of 16 episodes)", ylim=(-0.02, 1.02),
           title="PegInsert Factory 4D, 128 paired episodes")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(HERE / "unseen_error.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
