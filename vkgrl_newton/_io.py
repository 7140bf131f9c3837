"""File helpers shared by everything that writes user-visible data."""

from __future__ import annotations

import os
import tempfile
import zipfile
import zlib
from pathlib import Path

import numpy as np

__all__ = ["atomic_write", "atomic_savez", "atomic_write_text", "load_npz", "NPZ_READ_ERRORS"]

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


def atomic_savez(path, overwrite: bool, **arrays) -> Path:
    """An npz file written with `atomic_write` (same overwrite rule)."""
    return atomic_write(path, overwrite, lambda f: np.savez(f, **arrays), suffix=".tmp.npz")


def atomic_write_text(path, text: str, overwrite: bool = False) -> Path:
    """A UTF-8 text file written with `atomic_write` (never overwrites by default)."""
    return atomic_write(path, overwrite, lambda f: f.write(text.encode("utf-8")))


def load_npz(path, what: str, required: tuple[str, ...]) -> dict:
    """Read every array of an npz file into memory; a missing, damaged or incomplete file
    raises FileNotFoundError / ValueError naming the file and what it should have been."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except NPZ_READ_ERRORS as e:
        raise ValueError(f"{path}: not a readable {what} file ({type(e).__name__}: {e})") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{path}: not a {what} file; missing keys {missing}")
    return arrays
