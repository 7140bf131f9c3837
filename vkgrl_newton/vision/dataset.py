"""The on-disk image set a task's VAE is trained on (thesis Table 5.5: 130,000 images per task).

One directory per set:

    images.npy    uint8 (N, R, R, 3) camera images, read memory-mapped (256^2 x 3 B = 192 KiB
                  each: 130k images are 25 GB, more than the RAM)
    state.npy     float32 (N, 4) privileged state per image, as the collector passes it (the
                  relative target pose x, y, z, yaw of the fixed part in the TCP/target frame);
                  used only to probe the latent (`vision.probe`), never to train the VAE
    episode.npy   int32 (N,) episode id per image
    geometry.npy  float32 (N, 13) the frame's geometry in the world (`GEOMETRY_COLUMNS`: held part,
                  fixed tip, the image's frame), for the near-hole probe; NaN rows where the
                  collector gave none (format 2; format-1 sets have no such file)
    pixels.npy    float32 (N, 12) privileged pixel measurements of the fixed and the held part
                  (`PIXEL_COLUMNS`, from shape-index and depth renders; NaN where a part is not
                  in view or none were given), the near-hole probe's baseline (format 2)
    split.npy     uint8 (N,) 0 = train, 1 = validation, drawn per EPISODE: consecutive frames of
                  one episode are near-duplicates, and a split by frame would leak them into the
                  validation set
    meta.json     format, task, resolution, count, val_fraction, the split's episode counts and
                  seed, plus the collector's own fields (source description, camera, ...)

`ImageSetWriter` fills images.npy in chunks through a memmap under a temporary name and, on
`close()`, renames it and writes the other files, meta.json last, each to a temporary name first.
A directory without meta.json is therefore an unfinished set, and `ImageSet` says so. The writer
never writes into a non-empty directory: a set is never overwritten, or mixed with another.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from .._io import atomic_write, atomic_write_text, check_npy_size, one_line, short_repr

__all__ = ["IMAGESET_FORMAT", "IMAGESET_FILES", "ImageSetWriter", "ImageSet", "STATE_DIM", "GEOMETRY_COLUMNS",
           "PIXEL_COLUMNS"]

IMAGESET_FORMAT = 2  # 2 added geometry.npy and pixels.npy; format 1 is still read (without them)
STATE_DIM = 4  # x, y, z, yaw
# world frame, m; the image's frame is the optical frame: +x image right, +y image down, +z forward
GEOMETRY_COLUMNS = ("held_x", "held_y", "held_z", "fixed_tip_x", "fixed_tip_y", "fixed_tip_z",
                    "camera_x", "camera_y", "camera_z", "camera_qx", "camera_qy", "camera_qz", "camera_qw")
# per part: pixel centroid (u right, v down, px, pixel centres at +0.5), pixel count, and the mean
# of its pixels' 3D points (depth x ray direction) in the optical frame, m
PIXEL_COLUMNS = tuple(f"{part}_{k}" for part in ("fixed", "held") for k in ("u", "v", "count", "px", "py", "pz"))
IMAGESET_FILES = ("images.npy", "state.npy", "episode.npy", "split.npy", "meta.json")
_FORMAT2_FILES = ("geometry.npy", "pixels.npy")
_PARTIAL = "images.npy.partial"
_RESERVED = ("format", "task", "resolution", "count", "val_fraction", "seed", "num_episodes", "num_val_episodes",
             "num_train", "num_val")


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


class ImageSetWriter:
    """Writes an image set of exactly `num_images` images, `add`ed in chunks, then `close()`.

    Usable as a context manager: a clean exit closes the set, an exception leaves it unfinished
    (no meta.json), never half-labelled as complete.
    """

    def __init__(self, out_dir, num_images: int, resolution: int, task: str, val_fraction: float = 0.1,
                 seed: int = 0, meta_extra: Mapping | None = None) -> None:
        self.out_dir = Path(out_dir)
        for name, v in (("num_images", num_images), ("resolution", resolution)):
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"ImageSetWriter: {name}={v!r}; allowed: an integer >= 1")
        num_images, resolution = int(num_images), int(resolution)
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"ImageSetWriter: val_fraction={val_fraction!r}; allowed: [0, 1)")
        extra = dict(meta_extra or {})
        clash = sorted(set(extra) & set(_RESERVED))
        if clash:
            raise ValueError(f"ImageSetWriter: meta_extra may not set {clash} (the writer's own fields)")
        self.meta = {"format": IMAGESET_FORMAT, "task": str(task), "resolution": resolution, "count": num_images,
                     "val_fraction": float(val_fraction), "seed": int(seed), **extra}
        json.dumps(self.meta)  # not serializable -> TypeError now, not after hours of collecting
        if self.out_dir.exists():
            if not self.out_dir.is_dir():
                raise FileExistsError(f"image set path {self.out_dir} exists and is not a directory")
            if any(self.out_dir.iterdir()):
                raise FileExistsError(f"image set directory {self.out_dir} is not empty; image sets are never "
                                      "overwritten: choose a new directory (or delete this one)")
        else:
            self.out_dir.mkdir(parents=True)
        self.num_images, self.resolution = num_images, resolution
        self._images = np.lib.format.open_memmap(self.out_dir / _PARTIAL, mode="w+", dtype=np.uint8,
                                                 shape=(num_images, resolution, resolution, 3))
        self._state = np.zeros((num_images, STATE_DIM), np.float32)
        self._episode = np.zeros(num_images, np.int32)
        self._geometry = np.full((num_images, len(GEOMETRY_COLUMNS)), np.nan, np.float32)
        self._pixels = np.full((num_images, len(PIXEL_COLUMNS)), np.nan, np.float32)
        self.count = 0
        self.closed = False

    def add(self, images, state, episode_ids, geometry=None, pixels=None) -> None:
        """Append n images: uint8 (n, R, R, 3), state (n, 4), integer episode ids (n,), and
        optionally geometry (n, 13) (finite) and pixel measurements (n, 12) (NaN allowed: a part
        out of view); numpy arrays or tensors."""
        if self.closed:
            raise RuntimeError(f"image set {self.out_dir} is closed")
        images, state, episode_ids = _numpy(images), _numpy(state), _numpy(episode_ids)
        n, r = images.shape[0] if images.ndim else 0, self.resolution
        if images.dtype != np.uint8 or images.shape != (n, r, r, 3):
            raise ValueError(f"ImageSetWriter.add: images must be uint8 (n, {r}, {r}, 3), got {images.dtype} "
                             f"{images.shape}")
        if state.shape != (n, STATE_DIM) or not np.isfinite(state).all():
            raise ValueError(f"ImageSetWriter.add: state must be finite (n, {STATE_DIM}) = ({n}, {STATE_DIM}), "
                             f"got {state.shape}")
        if episode_ids.shape != (n,) or not np.issubdtype(episode_ids.dtype, np.integer):
            raise ValueError(f"ImageSetWriter.add: episode_ids must be integers ({n},), got {episode_ids.dtype} "
                             f"{episode_ids.shape}")
        i32 = np.iinfo(np.int32)
        if n and not (i32.min <= episode_ids.min() and episode_ids.max() <= i32.max):
            raise ValueError("ImageSetWriter.add: episode_ids do not fit int32")
        if self.count + n > self.num_images:
            raise ValueError(f"ImageSetWriter.add: {self.count} + {n} images exceed num_images={self.num_images}")
        sl = slice(self.count, self.count + n)
        if geometry is not None:
            geometry = _numpy(geometry)
            if geometry.shape != (n, len(GEOMETRY_COLUMNS)) or not np.isfinite(geometry).all():
                raise ValueError(f"ImageSetWriter.add: geometry must be finite ({n}, {len(GEOMETRY_COLUMNS)}), "
                                 f"got {geometry.shape}")
            self._geometry[sl] = geometry
        if pixels is not None:
            pixels = _numpy(pixels)
            if pixels.shape != (n, len(PIXEL_COLUMNS)):
                raise ValueError(f"ImageSetWriter.add: pixels must be ({n}, {len(PIXEL_COLUMNS)}), got {pixels.shape}")
            self._pixels[sl] = pixels
        self._images[sl], self._state[sl], self._episode[sl] = images, state, episode_ids
        self.count += n

    def close(self) -> Path:
        """Finish the set: the per-episode split, then every file under its final name. Returns the directory."""
        if self.closed:
            return self.out_dir
        if self.count != self.num_images:
            raise ValueError(f"image set {self.out_dir}: {self.count} of num_images={self.num_images} images "
                             "written; the set stays unfinished (no meta.json)")
        split, n_ep, n_val_ep = self._split()
        self._images.flush()
        del self._images  # close the mapping before the rename
        partial = self.out_dir / _PARTIAL
        with open(partial, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(partial, self.out_dir / "images.npy")
        for name, arr in (("state.npy", self._state), ("episode.npy", self._episode), ("split.npy", split),
                          ("geometry.npy", self._geometry), ("pixels.npy", self._pixels)):
            atomic_write(self.out_dir / name, False, lambda f, a=arr: np.save(f, a), suffix=".tmp.npy")
        self.meta.update(num_episodes=n_ep, num_val_episodes=n_val_ep, num_train=int((split == 0).sum()),
                         num_val=int((split == 1).sum()))
        atomic_write_text(self.out_dir / "meta.json", json.dumps(self.meta, indent=2) + "\n")  # last: "complete"
        self.closed = True
        return self.out_dir

    def _split(self) -> tuple[np.ndarray, int, int]:
        """Validation episodes: round(val_fraction * episodes), at least 1 if val_fraction > 0 and
        at most all but one, drawn without replacement with `seed`."""
        episodes = np.unique(self._episode)
        frac = self.meta["val_fraction"]
        n_val = 0
        if frac > 0:
            if len(episodes) < 2:
                raise ValueError(f"image set {self.out_dir}: val_fraction={frac} needs at least 2 episodes, "
                                 f"got {len(episodes)}")
            n_val = min(max(1, round(frac * len(episodes))), len(episodes) - 1)
        val_eps = np.random.default_rng(self.meta["seed"]).permutation(episodes)[:n_val]
        return np.isin(self._episode, val_eps).astype(np.uint8), len(episodes), n_val

    def __enter__(self) -> ImageSetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()


def _peek_format(d: Path):
    """meta.json's format, or None when it cannot be read (the full check follows in ImageSet)."""
    try:
        return json.loads((d / "meta.json").read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        return None


def _load_npy(path: Path, mmap_mode=None) -> np.ndarray:
    """One .npy array; ValueError for anything else np.load would return (an npz archive), or for a
    header that declares more data than the file holds (numpy would allocate it first)."""
    with open(path, "rb") as f:
        check_npy_size(f, path.stat().st_size, path.name)
    arr = np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
    if not isinstance(arr, np.ndarray):
        arr.close()
        raise ValueError(f"{path.name} is an npz archive, not one .npy array")
    return arr


class ImageSet:
    """A finished image set, read back; `images` stays on disk (memmap), the rest is loaded.

    `resolution` / `task`, when given, must match the set's (ValueError otherwise).
    """

    def __init__(self, directory, resolution: int | None = None, task: str | None = None) -> None:
        self.dir = d = Path(directory)
        if not d.is_dir():
            raise FileNotFoundError(f"image set directory {d} does not exist; collect one with ImageSetWriter")
        fmt_files = IMAGESET_FILES + (_FORMAT2_FILES if _peek_format(d) != 1 else ())
        missing = [f for f in fmt_files if not (d / f).is_file()]
        if missing:
            why = " (the writer did not finish: images.npy.partial is there)" if (d / _PARTIAL).exists() else ""
            raise FileNotFoundError(f"image set {d} is incomplete: missing {', '.join(missing)}{why}")
        name = "meta.json"
        try:
            self.meta = json.loads((d / name).read_bytes().decode("utf-8"))
            loaded = {}
            for name in fmt_files[1:4] + (_FORMAT2_FILES if (d / "geometry.npy").is_file() else ()):
                loaded[name] = _load_npy(d / name)
            name = "images.npy"
            self.images = _load_npy(d / name, mmap_mode="r")
        except (OSError, ValueError, EOFError, MemoryError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError: ValueErrors
            raise ValueError(one_line(f"image set {d} has a damaged file: {name} ({type(e).__name__}: {e})")) from None
        self.state, self.episode, self.split = (loaded[f] for f in ("state.npy", "episode.npy", "split.npy"))
        self.geometry, self.pixels = loaded.get("geometry.npy"), loaded.get("pixels.npy")  # format 1: not collected
        fmt = self.meta.get("format") if isinstance(self.meta, dict) else None
        if type(fmt) is not int or fmt not in (1, IMAGESET_FORMAT):
            raise ValueError(f"image set {d}: meta.json has format {short_repr(fmt)}, this code reads 1 and "
                             f"{IMAGESET_FORMAT}")
        for key, kind in (("count", int), ("resolution", int), ("task", str)):
            value = self.meta.get(key)
            if not isinstance(value, kind) or isinstance(value, bool) or (kind is int and value < 0):
                raise ValueError(f"image set {d}: meta.json's {key} is {short_repr(value)}, not a "
                                 f"{'whole number >= 0' if kind is int else 'string'}")
        n, r = self.meta["count"], self.meta["resolution"]
        expected = {"images.npy": (self.images, np.uint8, (n, r, r, 3)),
                    "state.npy": (self.state, np.float32, (n, STATE_DIM)),
                    "episode.npy": (self.episode, np.int32, (n,)), "split.npy": (self.split, np.uint8, (n,))}
        if self.geometry is not None:
            expected["geometry.npy"] = (self.geometry, np.float32, (n, len(GEOMETRY_COLUMNS)))
            expected["pixels.npy"] = (self.pixels, np.float32, (n, len(PIXEL_COLUMNS)))
        for name, (arr, dtype, shape) in expected.items():
            if arr.dtype != dtype or arr.shape != shape:
                raise ValueError(f"image set {d}: {name} is {arr.dtype} {arr.shape}, "
                                 f"meta.json says {np.dtype(dtype)} {shape}")
        if not np.isfinite(self.state).all():  # (geometry and pixels are NaN by design where unknown)
            raise ValueError(f"image set {d}: state.npy holds NaN or inf")
        if not np.isin(self.split, (0, 1)).all():
            raise ValueError(f"image set {d}: split.npy holds values other than 0 (train) and 1 (validation)")
        if resolution is not None and resolution != r:
            raise ValueError(f"image set {d} has resolution {r}, requested {resolution}")
        if task is not None and task != self.meta["task"]:
            raise ValueError(f"image set {d} is of task {self.meta['task']!r}, requested {task!r}")
        self.train_idx = np.flatnonzero(self.split == 0)
        self.val_idx = np.flatnonzero(self.split == 1)

    @property
    def has_geometry(self) -> bool:
        """Every image has its frame's geometry (a format-2 set whose collector gave it)."""
        return self.geometry is not None and bool(np.isfinite(self.geometry).all())

    @property
    def resolution(self) -> int:
        return int(self.meta["resolution"])

    @property
    def task(self) -> str:
        return str(self.meta["task"])

    def __len__(self) -> int:
        return int(self.meta["count"])
