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

from collections.abc import Sequence

from .. import _io
from .._io import CHECKPOINT_FORMAT, check_meta, save_checkpoint

__all__ = ["CHECKPOINT_FORMAT", "TRAINING_KEYS", "save_checkpoint", "load_checkpoint", "check_meta"]

TRAINING_KEYS = ("format", "meta", "counters", "agent", "rng")  # what a training checkpoint holds


def load_checkpoint(path, map_location="cpu", required: Sequence[str] = TRAINING_KEYS,
                    hint: str = "resume from another one or start a new run directory") -> dict:
    """`_io.load_checkpoint` asking for a training checkpoint's keys unless `required` says otherwise."""
    return _io.load_checkpoint(path, map_location=map_location, required=required, hint=hint)
