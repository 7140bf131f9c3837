"""Paired comparisons of two policies evaluated on the same episodes, and an evaluation seed.

`seed_evaluation(env, eval_seed)` puts an env at the start of a fixed sequence of evaluation
episodes: its generator is reseeded and every world reset, so any two policies evaluated after it
(in one env, one after the other, or in two envs of the same configuration, trained or not) see
bitwise the same initial states and target-frame noise, episode by episode and world by world
(the env draws all its randomness from that generator, at resets; `evaluate` runs whole episodes).

`paired_gain(a, b)`: the mean of the per-episode differences a - b over the episodes both
policies ran, with a percentile bootstrap interval that resamples episodes in pairs (the pairing
removes the between-episode variance the two share: a start both solve or both miss adds nothing).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["EVAL_SEED", "seed_evaluation", "paired_gain", "world_outcomes"]

# The default evaluation seed of train/run.py and train/evaluate.py: one set of evaluation episodes
# for every training seed of a configuration, apart from the training seeds' own draws (0, 1, ...).
EVAL_SEED = 10_000


def seed_evaluation(env, eval_seed: int) -> None:
    """Reseed the env's generator with eval_seed and reset every world (see the module docstring)."""
    env.generator.manual_seed(int(eval_seed))
    env.reset()


def world_outcomes(result: dict, key: str = "world_success") -> np.ndarray:
    """An `evaluate` result's per-episode, per-world values (rounds x worlds, NaN where a world's
    episode did not count), flattened in evaluation order."""
    rows = [e[key] for e in result["per_episode"]]
    return np.asarray(rows, dtype=np.float64).reshape(-1)


def paired_gain(a, b, reps: int = 10_000, seed: int = 0, confidence: float = 0.95) -> dict:
    """Mean of a - b over the pairs where both are finite, and its percentile-bootstrap interval.

    a, b: per-episode outcomes in the same episode order (e.g. `world_outcomes` of two
    evaluations after `seed_evaluation` with one seed). Returns {"mean", "ci_low", "ci_high",
    "n_pairs", "a_mean", "b_mean", "confidence", "reps"}; means are None (not NaN: strict JSON)
    when no pair is complete.
    """
    a, b = np.asarray(a, dtype=np.float64).reshape(-1), np.asarray(b, dtype=np.float64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"paired_gain: {a.size} outcomes against {b.size}; the two evaluations must run the "
                         "same episodes (same eval seed, worlds and episode count)")
    if reps < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(f"paired_gain: reps={reps} must be >= 1 and confidence={confidence} in (0, 1)")
    keep = np.isfinite(a) & np.isfinite(b)
    d = a[keep] - b[keep]
    out = {"n_pairs": int(d.size), "confidence": confidence, "reps": int(reps)}
    if d.size == 0:
        return {**out, "mean": None, "ci_low": None, "ci_high": None, "a_mean": None, "b_mean": None}
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, d.size, size=(reps, d.size))
    means = d[idx].mean(axis=1)
    tail = 100.0 * (1.0 - confidence) / 2.0
    lo, hi = np.percentile(means, [tail, 100.0 - tail])
    return {**out, "mean": float(d.mean()), "ci_low": float(lo), "ci_high": float(hi),
            "a_mean": float(a[keep].mean()), "b_mean": float(b[keep].mean())}


def format_gain(name: str, gain: dict, digits: int = 3) -> str:
    """'name +0.123 [+0.050, +0.190] (n pairs)' or 'name n/a'."""
    if gain.get("mean") is None or any(isinstance(gain[k], float) and math.isnan(gain[k])
                                       for k in ("mean", "ci_low", "ci_high")):
        return f"{name} n/a"
    f = f"{{:+.{digits}f}}"
    return (f"{name} {f.format(gain['mean'])} [{f.format(gain['ci_low'])}, {f.format(gain['ci_high'])}] "
            f"({gain['n_pairs']} paired episodes)")
