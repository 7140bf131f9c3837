"""File helpers shared by everything that writes user-visible data.

Checkpoints (`save_checkpoint` / `load_checkpoint`): one `torch.save` file holding a dict of
tensors, numbers, strings, lists and dicts (so that `torch.load(weights_only=True)` reads it),
with "format" = CHECKPOINT_FORMAT added; each kind of checkpoint (a training run's,
vkgrl_newton.agents.checkpoint; a VAE's, vkgrl_newton.vision.vae) names the top-level keys it
must hold. Written with `atomic_write`: a crash at any moment leaves either the old checkpoint or
the new one, never a torn file.

Reading a user's file: every loader (`load_checkpoint`, `load_npz`, `read_json_object` here, and the
loaders of each kind built on them: DemoSet.load, KMPTables.load, load_vae, ImageSet, train/sweep.py's
grid) turns any damage -- another kind of file, a truncated one, missing or mistyped keys, wrong shapes,
NaN or inf where numbers must be finite, a foreign format version -- into one ValueError whose message
is one line naming the file (FileNotFoundError when it is missing). That is the one error type the
CLIs turn into `prog: error: <line>` and exit 2 (argparse's `ap.error`), and the gymnasium ids into
their one-line ValueError; tests/test_loader_fuzz.py fuzzes every loader against it.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["atomic_write", "current_umask", "atomic_savez", "atomic_write_text", "strict_json", "load_npz", "NPZ_READ_ERRORS",
           "CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint", "check_meta", "one_line", "short_repr",
           "read_json_object", "check_finite", "check_npy_size", "output_path_error"]

CHECKPOINT_FORMAT = 1

# What np.load / reading a member of a damaged npz raises besides ValueError (MemoryError: a header
# that declares an array larger than the memory, before its data is read).
NPZ_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error, MemoryError)


def one_line(text, limit: int = 300) -> str:
    """`text` as one line of at most `limit` characters: a refusal's message is one line."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def short_repr(value, limit: int = 80) -> str:
    """repr(value) as one short line (a damaged file's value may be a large tensor or a long string)."""
    return one_line(repr(value), limit)


def check_finite(obj, path, where: str, skip: tuple[str, ...] = ()) -> None:
    """ValueError naming the file and the entry when a float tensor or array inside `obj` (nested
    dicts, lists, tuples) holds NaN or inf (plain numbers are settings, not weights: not checked).
    Entries named in `skip` are not looked into."""
    import torch

    if isinstance(obj, dict):
        for k, v in obj.items():
            if k not in skip:
                check_finite(v, path, f"{where}.{k}", skip)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            check_finite(v, path, f"{where}[{i}]", skip)
    elif isinstance(obj, torch.Tensor):
        if (obj.is_floating_point() or obj.is_complex()) and not bool(torch.isfinite(obj).all()):
            raise ValueError(f"{path}: {where} holds NaN or inf")
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc" and not np.isfinite(obj).all():
            raise ValueError(f"{path}: {where} holds NaN or inf")


def read_json_object(path, what: str) -> dict:
    """A JSON object read from a user's file; FileNotFoundError if missing, ValueError (one line naming
    the file) if it is not a readable UTF-8 JSON object or holds bare NaN / Infinity (not JSON: strict_json
    writes null)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} {path} does not exist")

    def refuse_constant(name):
        raise ValueError(f"bare {name} (not JSON)")

    try:
        value = json.loads(path.read_bytes().decode("utf-8"), parse_constant=refuse_constant)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:  # JSONDecodeError is a ValueError
        raise ValueError(one_line(f"{path}: not a readable {what} (a JSON object): {type(e).__name__}: {e}")) from None
    if not isinstance(value, dict):
        raise ValueError(f"{path}: not a {what}: a JSON {type(value).__name__}, not an object")
    return value


def output_path_error(path, flag: str, may_exist: bool = False, what: str = "results") -> str | None:
    """Why a command cannot write its output at `path` (a file, or a directory it makes), in one line naming
    `flag`, or None. Checked before any work, so that nothing is computed and then lost at the end: `path`
    exists (unless `may_exist`: then an existing directory must take new files), a part of its path is a file,
    or the deepest existing directory on it does not take a new file (tried: a probe file is made and removed;
    permissions alone do not say it for root, /proc or a read-only mount)."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        if not may_exist:
            return f"{flag} {path} exists; choose another path ({what} are never overwritten)"
        if not path.is_dir():
            return f"{flag} {path} is a file; give a directory"
        where = path
    else:
        where = path.parent
        while not where.exists() and where != where.parent:
            where = where.parent
        if not where.is_dir():
            return f"{flag} {path}: {where} is a file, not a directory"
    try:
        fd, probe = tempfile.mkstemp(dir=where, prefix=".write-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        return f"{flag} {path}: cannot write in {where} ({e.strerror or type(e).__name__})"
    return None


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
        _check_npz_sizes(path)
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except NPZ_READ_ERRORS as e:
        raise ValueError(one_line(f"{path}: not a readable {what} file ({type(e).__name__}: {e})")) from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{path}: not a {what} file; missing keys {missing}")
    return arrays


def _check_npz_sizes(path: Path) -> None:
    """ValueError for a member whose .npy header declares more data than the member holds: numpy would
    allocate the declared size before reading (a damaged header can ask for terabytes)."""
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.filename.endswith(".npy"):
                with zf.open(info) as f:
                    check_npy_size(f, info.file_size, f"member {info.filename}")


def check_npy_size(f, size: int, what: str) -> None:
    """ValueError unless the .npy header at `f`'s position declares at most `size` bytes of data
    (`size`: what the file or archive member holds, header included)."""
    try:
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read_header(f)
    except Exception as e:  # numpy parses the header as a Python literal: a damaged one fails in many ways (TokenError...)
        raise ValueError(f"{what}: not a readable .npy array ({type(e).__name__}: {e})") from None
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > size:
        raise ValueError(f"{what} declares {shape} {dtype} ({nbytes} bytes) but holds {size} bytes")


def save_checkpoint(path, payload: dict) -> Path:
    """Write `payload` (with "format" added) to `path` atomically; replaces an older checkpoint."""
    import torch  # here, not at the top: the CLIs import this module before parsing their arguments

    return atomic_write(path, overwrite=True, write=lambda f: torch.save({"format": CHECKPOINT_FORMAT, **payload}, f))


def load_checkpoint(path, map_location="cpu", required: Sequence[str] = (),
                    hint: str = "resume from another one or start a new run directory",
                    kinds: Mapping[str, type | tuple[type, ...]] | None = None) -> dict:
    """Read a checkpoint; FileNotFoundError if missing, ValueError (one line naming the file) if it
    is damaged, not a checkpoint of this project, or of another format version.

    `required`: the top-level keys this kind of checkpoint must hold ("format" is always
    required). `hint`: what to do about a damaged file, for the message. `kinds`: the type each
    top-level key must have where present (e.g. {"meta": dict}), so that callers may index them.
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
        raise ValueError(one_line(f"checkpoint {path} is damaged or not a checkpoint ({type(e).__name__}: {first}); "
                                  f"{hint}", 600)) from None
    if not isinstance(payload, dict) or any(k not in payload for k in required):
        missing = [k for k in required if not isinstance(payload, dict) or k not in payload]
        raise ValueError(f"checkpoint {path} is not a vkgrl-newton checkpoint of the expected kind "
                         f"(missing {missing})")
    fmt = payload["format"]
    if type(fmt) is not int or fmt != CHECKPOINT_FORMAT:  # (a tensor's != is no bool; True == 1)
        raise ValueError(f"checkpoint {path} has format {short_repr(fmt)}, this code reads {CHECKPOINT_FORMAT}")
    for key, kind in (kinds or {}).items():
        if key in payload and not isinstance(payload[key], kind):
            names = " or ".join(t.__name__ for t in (kind if isinstance(kind, tuple) else (kind,)))
            raise ValueError(f"checkpoint {path} is damaged: its {key!r} is a {type(payload[key]).__name__}, "
                             f"not a {names}")
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
