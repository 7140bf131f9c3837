"""Paired comparisons of two policies evaluated on the same episodes, and an evaluation seed.

`seed_evaluation(env, eval_seed)` puts an env at the start of a fixed sequence of evaluation
episodes: its generator is reseeded and every world reset, so any two policies evaluated after it
(in one env, one after the other, or in two envs of the same configuration, trained or not) see
bitwise the same initial states and target-frame noise, episode by episode and world by world
(the env draws all its randomness from that generator, at resets; `evaluate` runs whole episodes).

`paired_gain(a, b)`: the mean of the per-episode differences a - b over the episodes both
policies ran, with a percentile bootstrap interval that resamples episodes in pairs (the pairing
removes the between-episode variance the two share: a start both solve or both miss adds nothing).

`cached_evaluation(cache_dir, key, compute)`: an evaluation that only its inputs and the code decide
(a KGRL run's prior, a = 0, on the episodes of an eval seed: the same for every training seed and
variant of a configuration) is computed once and reused; the key holds every input, a digest of
the package's sources, so a changed env, kernel or scene evaluates anew, and the processor of the
key's device, so a cache copied to a machine of another CPU model (whose float32 results seat
other episodes) evaluates anew too.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["EVAL_SEED", "seed_evaluation", "paired_gain", "world_outcomes", "cached_evaluation", "source_digest"]

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


_SOURCE_DIGEST: str | None = None


def source_digest() -> str:
    """sha256 over the package's Python, kernel and USD scene sources (vkgrl_newton, its kernels and
    assets_usd): what an evaluation's outcome depends on besides its inputs. Computed once per process."""
    global _SOURCE_DIGEST
    if _SOURCE_DIGEST is None:
        import vkgrl_newton
        import vkgrl_newton.assets_usd
        import vkgrl_newton.kernels

        h = hashlib.sha256()
        for pkg in (vkgrl_newton, vkgrl_newton.kernels, vkgrl_newton.assets_usd):
            root = Path(pkg.__file__).parent
            for f in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".usda") and p.is_file()):
                h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
        _SOURCE_DIGEST = h.hexdigest()
    return _SOURCE_DIGEST


def _nan_for_null(obj):
    if obj is None:
        return math.nan
    if isinstance(obj, dict):
        return {k: _nan_for_null(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_for_null(v) for v in obj]
    return obj


def _stored_result(path: Path, key: dict) -> dict | None:
    """The result stored in `path` for exactly `key`, or None (damaged, or written for other inputs)."""
    try:
        stored = json.loads(path.read_text())
        return _nan_for_null(stored["result"]) if stored.get("key") == key else None
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError):
        return None


def cached_evaluation(cache_dir, key: dict, compute, log=print, what: str = "the prior's evaluation") -> tuple[dict, bool]:
    """(compute(), False) the first time for `key` (a JSON-able dict of every input), (the stored
    result, True) after: the file `cache_dir/evaluations/<sha>.json` (strict JSON; its NaN, stored as
    null, come back as NaN: no field of an `evaluate` result is None). Made under the entry's lock
    (vkgrl_newton.cache): runs that start together evaluate once. A damaged file, or one of another
    processor (`processor_name` of the key's device), is evaluated anew."""
    from .._io import atomic_write_text, strict_json
    from ..cache import entry_lock
    from ..runtime import processor_name
    from ..signals import phase

    full = {**key, "source_digest": source_digest(), "processor": processor_name(key.get("device", "cpu"))}
    digest = hashlib.sha256(json.dumps(full, sort_keys=True).encode()).hexdigest()
    path = Path(cache_dir) / "evaluations" / f"{digest[:24]}.json"
    with entry_lock(path, log=log, what=what):
        if path.exists():
            stored = _stored_result(path, full)
            if stored is not None:
                log(f"{what}: reused {path} (same inputs, sources and processor)")
                return stored, True
            log(f"{what}: {path} is damaged or of other inputs; evaluating anew")
        with phase(f"computing {what}", "none of it is cached: the next run computes it anew"):
            result = compute()
        atomic_write_text(path, strict_json({"key": full, "result": result}), overwrite=True)
    return result, False
