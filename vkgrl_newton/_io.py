"""File helpers shared by everything that writes user-visible data.

Checkpoints (`save_checkpoint` / `load_checkpoint`): one `torch.save` file holding a dict of
tensors, numbers, strings, lists and dicts (so that `torch.load(weights_only=True)` reads it),
with "format" = CHECKPOINT_FORMAT added; each kind of checkpoint (a training run's,
vkgrl_newton.agents.checkpoint; a VAE's, vkgrl_newton.vision.vae) names the top-level keys it
must hold. Written with `atomic_write`: a crash at any moment leaves either the old checkpoint or
the new one, never a torn file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["atomic_write", "current_umask", "atomic_savez", "atomic_write_text", "strict_json", "load_npz", "NPZ_READ_ERRORS",
           "CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint", "check_meta"]

CHECKPOINT_FORMAT = 1

# What np.load / reading a member of a damaged npz raises besides ValueError.
NPZ_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)


def atomic_write(path, overwrite: bool, write, suffix: str = ".tmp") -> Path:
    """Write a file atomically: `write(f)` fills a temporary binary file beside it, then rename.

    overwrite=False never replaces an existing file, also against a file created meanwhile
    (the final step is a hard link, which fails if the name exists): FileExistsError.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not overwrite and path.exists():
        raise FileExistsError(f"{path} exists and is not overwritten; choose another path")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=suffix)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())  # mkstemp makes 0600; a written file follows the umask like any other
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise FileExistsError(f"{path} exists and is not overwritten; choose another path") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def current_umask() -> int:
    """The process's umask, read without changing it (Linux: /proc; elsewhere set and restored)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_savez(path, overwrite: bool, **arrays) -> Path:
    """An npz file written with `atomic_write` (same overwrite rule)."""
    return atomic_write(path, overwrite, lambda f: np.savez(f, **arrays), suffix=".tmp.npz")


def atomic_write_text(path, text: str, overwrite: bool = False) -> Path:
    """A UTF-8 text file written with `atomic_write` (never overwrites by default)."""
    return atomic_write(path, overwrite, lambda f: f.write(text.encode("utf-8")))


def strict_json(obj, **kw) -> str:
    """json.dumps with NaN and +-inf written as null (bare NaN is not JSON: jq and JavaScript reject it)."""
    return json.dumps(_finite(obj), allow_nan=False, **kw)


def _finite(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def load_npz(path, what: str, required: tuple[str, ...]) -> dict:
    """Read every array of an npz file into memory; a missing, damaged or incomplete file
    raises FileNotFoundError / ValueError naming the file and what it should have been."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    if not path.is_file() or not zipfile.is_zipfile(path):  # (numpy's own message would suggest pickle)
        raise ValueError(f"{path}: not a readable {what} file (an .npz archive); this is "
                         f"{'a directory' if path.is_dir() else 'another kind of file, or a damaged one'}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except NPZ_READ_ERRORS as e:
        raise ValueError(f"{path}: not a readable {what} file ({type(e).__name__}: {e})") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{path}: not a {what} file; missing keys {missing}")
    return arrays


def save_checkpoint(path, payload: dict) -> Path:
    """Write `payload` (with "format" added) to `path` atomically; replaces an older checkpoint."""
    import torch  # here, not at the top: the CLIs import this module before parsing their arguments

    return atomic_write(path, overwrite=True, write=lambda f: torch.save({"format": CHECKPOINT_FORMAT, **payload}, f))


def load_checkpoint(path, map_location="cpu", required: Sequence[str] = (),
                    hint: str = "resume from another one or start a new run directory") -> dict:
    """Read a checkpoint; FileNotFoundError if missing, ValueError (naming the file) if it is
    damaged, not a checkpoint of this project, or of another format version.

    `required`: the top-level keys this kind of checkpoint must hold ("format" is always
    required). `hint`: what to do about a damaged file, for the message.
    """
    import torch

    path = Path(path)
    required = ("format", *(k for k in required if k != "format"))
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # any other kind of file breaks torch's unpickler in its own way (KeyError, IndexError, ...)
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
