"""Training checkpoints: written atomically, read with clear errors, checked against the run.

A checkpoint is one `torch.save` file (a dict of tensors, numbers, strings, lists and dicts, so
that `torch.load(weights_only=True)` reads it):

    format   CHECKPOINT_FORMAT
    meta     what the run is (task, method, env, action_dim, obs_dim, time_obs, preset, seed,
             num_envs, the SAC config): a resumed run must match it
    counters transitions (env transitions summed over worlds), env_steps, updates, episodes
    agent    SAC.state_dict(): networks, targets, temperature, optimizers, normalizer, replay
             buffer, generator
    rng      torch's global RNG, the env's torch generator and numpy bit-generator state,
             the warm-up action generator

Writing goes to a temporary file in the same directory, fsync, then `os.replace`: a crash at
any moment leaves either the old checkpoint or the new one, never a torn file.

Other kinds of checkpoint (the VAE of `vkgrl_newton.vision.vae`) use the same two functions and
pass `load_checkpoint` the top-level keys that their kind must hold.
"""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = ["CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint", "check_meta"]

CHECKPOINT_FORMAT = 1
_REQUIRED = ("format", "meta", "counters", "agent", "rng")


def save_checkpoint(path, payload: dict) -> Path:
    """Write `payload` (with "format" added) to `path` atomically; replaces an older checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format": CHECKPOINT_FORMAT, **payload}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path, map_location="cpu", required: Sequence[str] = _REQUIRED,
                    hint: str = "resume from another one or start a new run directory") -> dict:
    """Read a checkpoint; FileNotFoundError if missing, ValueError (naming the file) if it is
    damaged, not a checkpoint of this project, or of another format version.

    `required`: the top-level keys this kind of checkpoint must hold (default: a training run's;
    "format" is always required). `hint`: what to do about a damaged file, for the message.
    """
    path = Path(path)
    required = ("format", *(k for k in required if k != "format"))
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, OSError, ValueError) as e:
        first = (str(e).strip().splitlines() or [""])[0][:200]
        raise ValueError(f"checkpoint {path} is damaged or not a checkpoint ({type(e).__name__}: {first}); "
                         f"{hint}") from None
    if not isinstance(payload, dict) or any(k not in payload for k in required):
        missing = [k for k in required if not isinstance(payload, dict) or k not in payload]
        raise ValueError(f"checkpoint {path} is not a vkgrl-newton checkpoint of the expected kind "
                         f"(missing {missing})")
    if payload["format"] != CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint {path} has format {payload['format']}, this code reads {CHECKPOINT_FORMAT}")
    return payload


def check_meta(saved: dict, current: dict, path) -> None:
    """ValueError naming every field in which the checkpoint's run differs from this one."""
    saved, current = _flat(saved), _flat(current)
    diff = [f"{k}: checkpoint {saved.get(k)!r}, now {current.get(k)!r}"
            for k in sorted(set(saved) | set(current)) if saved.get(k) != current.get(k)]
    if diff:
        raise ValueError(f"checkpoint {path} belongs to a different run; " + "; ".join(diff))


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = tuple(v) if isinstance(v, list) else v
    return out
