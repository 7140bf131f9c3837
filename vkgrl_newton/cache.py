"""The cache of prerequisites that runs share (`runs/cache/<task>/`): scripted demonstrations and
the KMP tables fitted to them, task-camera image sets and the VAEs trained on them.

A run records what it learned from by path and sha256 (`file_sha256`); resuming or evaluating
it checks the file is still the same (`check_unchanged`).

Many runs start at once in a sweep, all on an empty cache. Each entry is prepared under a lock
of its own (`<entry>.lock`, an OS file lock through the `filelock` package: released when the
process dies, so a killed run never leaves the cache locked): the first run prepares it, the
others wait, then find it made and reuse it.
"""

from __future__ import annotations

import hashlib
from contextlib import contextmanager
from pathlib import Path

from filelock import FileLock, Timeout

__all__ = ["entry_lock", "lock_path", "file_sha256", "check_unchanged", "check_run_files"]


def lock_path(entry) -> Path:
    """The lock file of a cache entry (a file or a directory): beside it, `<name>.lock`."""
    entry = Path(entry)
    return entry.with_name(entry.name + ".lock")


@contextmanager
def entry_lock(entry, log=print, what: str | None = None):
    """Hold the lock of cache entry `entry` for the block; says once when it has to wait.

    Inside the block, test whether the entry exists before making it: another run may have made
    it while this one waited."""
    path = lock_path(entry)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(str(path))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        log(f"waiting for another run preparing {what or Path(entry).name} ({path})")
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def file_sha256(path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_unchanged(path, recorded_sha256: str, what: str) -> None:
    """ValueError naming both hashes when the file at `path` is not the one a run recorded
    (FileNotFoundError when it is gone)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path}, recorded by the run, does not exist")
    now = file_sha256(path)
    if now != recorded_sha256:
        raise ValueError(f"{what} {path} has changed since the run recorded it: sha256 recorded {recorded_sha256}, "
                         f"now {now}")


def check_run_files(meta: dict, demos=None, vae=None, probe=None) -> None:
    """The files a run's meta records by sha256 (its KMP prior's demonstrations, its VAE, its near-hole
    probe) are the given ones, unchanged; a file not given (None) is not checked. Errors as `check_unchanged`."""
    if "prior" in meta and demos is not None:
        check_unchanged(demos, meta["prior"]["demos_sha256"], "the KMP prior's demonstrations")
    vision = meta.get("vision", {})
    if "vae_sha256" in vision and vae is not None:
        check_unchanged(vae, vision["vae_sha256"], "the VAE")
    if "probe_sha256" in vision and probe is not None:
        check_unchanged(probe, vision["probe_sha256"], "the near-hole probe")
