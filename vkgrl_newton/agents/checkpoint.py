"""Training checkpoints: written atomically, read with clear errors, checked against the run.

A training checkpoint is one `torch.save` file (a dict of tensors, numbers, strings, lists and
dicts, so that `torch.load(weights_only=True)` reads it):

    format   CHECKPOINT_FORMAT
    meta     what the run is (task, method, env, action_dim, obs_dim, time_obs, preset, seed,
             num_envs, the SAC config): a resumed run must match it (`check_meta`)
    counters transitions (env transitions summed over worlds), env_steps, updates, episodes
    agent    SAC.state_dict(): networks, targets, temperature, optimizers, normalizer, replay
             buffer, generator
    rng      torch's global RNG, the env's torch generator and numpy bit-generator state,
             the warm-up action generator

Writing and reading are vkgrl_newton._io's generic checkpoint functions (atomic: a crash at any
moment leaves either the old checkpoint or the new one, never a torn file); `load_checkpoint`
here asks for the keys above by default.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from .. import _io
from .._io import CHECKPOINT_FORMAT, check_meta, save_checkpoint

__all__ = ["CHECKPOINT_FORMAT", "TRAINING_KEYS", "META_KEYS", "save_checkpoint", "load_checkpoint", "check_meta"]

TRAINING_KEYS = ("format", "meta", "counters", "agent", "rng")  # what a training checkpoint holds
# what resume and evaluate read from meta by name (run/resolve.py, run/evaluate.py): present in every run's meta
META_KEYS = {"task": str, "method": str, "env": str, "action_dim": int, "time_obs": bool}
_KINDS = {"meta": dict, "counters": dict, "agent": dict, "rng": dict, "plan": dict}
# replay buffers hold what the env gave, and are not weights: NaN there is not a damaged file
_NOT_WEIGHTS = ("buffer", "prior_buffer")


def load_checkpoint(path, map_location="cpu", required: Sequence[str] = TRAINING_KEYS,
                    hint: str = "resume from another one or start a new run directory") -> dict:
    """`_io.load_checkpoint` asking for a training checkpoint's keys unless `required` says otherwise.

    A training checkpoint (the default `required`) is also checked for what its readers index
    without looking: meta's identity fields, whole-number counters, and finite weights (NaN or inf in
    the agent's networks or optimizers is a ValueError naming the file and the entry)."""
    payload = _io.load_checkpoint(path, map_location=map_location, required=required, hint=hint, kinds=_KINDS)
    if tuple(required) != TRAINING_KEYS:
        return payload
    meta = payload["meta"]
    for key, kind in META_KEYS.items():
        if key not in meta:
            raise ValueError(f"checkpoint {path} is damaged: its meta has no {key!r}")
        if not isinstance(meta[key], kind) or (kind is int and isinstance(meta[key], bool)):
            raise ValueError(f"checkpoint {path} is damaged: meta {key!r} is {_io.short_repr(meta[key])}, "
                             f"not a {kind.__name__}")
    for key in ("prior", "vision", "sac", "ppo"):
        if key in meta and not isinstance(meta[key], dict):
            raise ValueError(f"checkpoint {path} is damaged: meta {key!r} is a {type(meta[key]).__name__}, not a dict")
    for key, file_key in (("prior", "demos"), ("vision", "vae")):
        if key in meta and not isinstance(meta[key].get(file_key), str):
            raise ValueError(f"checkpoint {path} is damaged: meta {key!r} names no {file_key} file")
    # counts are whole numbers; wall_s (the run's training seconds so far) is a float
    bad = {k: v for k, v in payload["counters"].items()
           if not (type(v) is int or (k == "wall_s" and type(v) is float and math.isfinite(v))) or v < 0}
    if bad:
        raise ValueError(f"checkpoint {path} is damaged: counters {_io.short_repr(bad)} are not whole numbers >= 0 "
                         "(wall_s: seconds >= 0)")
    _io.check_finite(payload["agent"], path, "agent", skip=_NOT_WEIGHTS)
    return payload
