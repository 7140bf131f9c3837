"""Demonstration sets: the npz file format, validation, and a synthetic demonstrator.

File format (npz, no pickles), one row per recorded control step of every demonstration:
    s            (T,)   float64  normalized time, per demonstration from 0 to 1
    eta          (T, 6) float64  relative pose of thesis 5.5: [p_tcp - p_target (m), log(q_ref^-1 q_tcp) (rad)]
    demo_lengths (D,)   int64    rows per demonstration, in order; sums to T
    task         str             task name (vkgrl_newton.tasks)
    psi_ref      float           reference yaw of q_ref used for eta (rad)
    action_dim   int             4 if roll and pitch were held at the reference, else 6
    source       str             'synthetic' or the recorder's name (e.g. 'scripted'); optional
    format_version int           DEMO_FORMAT_VERSION (1); optional, a file without it is read as 1

Rotation vectors must be continuous along each demonstration: log() wraps at an angle of
pi, so a recorder applies `pose.unwrap_rotation_vectors` per demonstration (a jump of more
than pi between samples is rejected).

The synthetic demonstrator draws task-shaped insertions (align above the target, descend,
insert or thread, hold) with the initial-state spread of thesis Table 5.2, the 1 mm target
noise of eq. 5.23 and per-demonstration timing variation. It exists so that the KMP
pipeline runs and can be inspected before the simulator exists; it is not physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .._io import atomic_savez, load_npz, one_line
from ..rotations import quat_from_euler_xyz
from ..tasks import get_task
from .pose import pose_to_eta, unwrap_rotation_vectors

__all__ = ["DemoSet", "synthetic_demos"]

DEMO_FORMAT_VERSION = 1


@dataclass(frozen=True)
class DemoSet:
    s: np.ndarray
    eta: np.ndarray
    demo_lengths: np.ndarray
    task: str
    psi_ref: float
    action_dim: int
    source: str = "synthetic"

    def __post_init__(self):
        s, eta, lengths = self.s, self.eta, self.demo_lengths
        if lengths.ndim != 1 or lengths.shape[0] == 0:
            raise ValueError("demo_lengths: the demonstration set is empty (no demonstrations)")
        if (lengths < 2).any():
            raise ValueError(f"demo_lengths: every demonstration needs >= 2 samples, got {lengths.tolist()}")
        if s.ndim != 1 or eta.ndim != 2 or eta.shape != (s.shape[0], 6):
            raise ValueError(f"s must be (T,) and eta (T, 6); got s {s.shape}, eta {eta.shape}")
        if int(lengths.sum()) != s.shape[0]:
            raise ValueError(f"demo_lengths sum to {int(lengths.sum())} but there are {s.shape[0]} samples")
        if not (np.isfinite(s).all() and np.isfinite(eta).all()):
            raise ValueError("s / eta contain NaN or inf")
        if (s < 0).any() or (s > 1).any():
            raise ValueError("s: normalized time must lie in [0, 1]")
        if self.action_dim not in (4, 6):
            raise ValueError(f"action_dim must be 4 or 6, got {self.action_dim}")
        cuts = np.cumsum(lengths)[:-1]
        for i, (seg, eta_seg) in enumerate(zip(np.split(s, cuts), np.split(eta, cuts))):
            if (np.diff(seg) < 0).any():
                raise ValueError(f"s: time decreases inside demonstration {i}")
            if abs(seg[0]) > 1e-9 or abs(seg[-1] - 1.0) > 1e-9:
                raise ValueError(
                    f"s: demonstration {i} runs from {seg[0]:.6g} to {seg[-1]:.6g}; time must be "
                    "normalized per demonstration to start at 0 and end at 1"
                )
            jump = np.linalg.norm(np.diff(eta_seg[:, 3:], axis=0), axis=1)
            if jump.size and jump.max() > math.pi:
                raise ValueError(
                    f"eta: the rotation vector of demonstration {i} jumps by {jump.max():.3g} rad between "
                    "samples (log wrapped at pi); unwrap it with vkgrl_newton.kmp.pose.unwrap_rotation_vectors"
                )
        if self.action_dim == 4 and np.abs(eta[:, 3:5]).max() > 1e-9:
            raise ValueError("eta: action_dim is 4 but roll/pitch (eta[:, 3:5]) are not at the reference (zero)")

    @property
    def num_demos(self) -> int:
        return int(self.demo_lengths.shape[0])

    def split(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per-demonstration (s, eta) pairs."""
        cuts = np.cumsum(self.demo_lengths)[:-1]
        return list(zip(np.split(self.s, cuts), np.split(self.eta, cuts)))

    def save(self, path) -> Path:
        """Write atomically; never overwrites an existing file (demonstrations are user data)."""
        return atomic_savez(
            path,
            overwrite=False,
            format_version=np.int64(DEMO_FORMAT_VERSION),
            s=self.s,
            eta=self.eta,
            demo_lengths=self.demo_lengths,
            task=np.str_(self.task),
            psi_ref=np.float64(self.psi_ref),
            action_dim=np.int64(self.action_dim),
            source=np.str_(self.source),
        )

    @classmethod
    def load(cls, path) -> "DemoSet":
        """Read a demonstration file; FileNotFoundError if missing, ValueError (one line naming the
        file) if damaged, of another format version or invalid."""
        data = load_npz(path, "demonstration", ("s", "eta", "demo_lengths", "task", "psi_ref", "action_dim"))
        try:
            if "format_version" in data:
                version = _whole(data["format_version"], "format_version")
                if version != DEMO_FORMAT_VERSION:
                    raise ValueError(f"format_version {version}, this code reads {DEMO_FORMAT_VERSION}")
            for name in ("s", "eta"):
                if data[name].dtype.kind not in "iuf":  # a float cast would drop an imaginary part or read text
                    raise ValueError(f"{name} is {data[name].dtype}, not numbers")
            lengths = data["demo_lengths"]
            if lengths.dtype.kind not in "iu":  # a float cast of NaN or 1e30 is an arbitrary integer
                raise ValueError(f"demo_lengths is {lengths.dtype}, not whole numbers")
            task = _text(data["task"], "task")
            get_task(task)  # an unknown task: ValueError naming the known ones
            psi = data["psi_ref"]
            psi_ref = float(psi.reshape(-1)[0]) if psi.size == 1 and psi.dtype.kind in "iuf" else None
            if psi_ref is None or not math.isfinite(psi_ref):
                raise ValueError(f"psi_ref must be one finite number, got {psi.dtype} {psi.shape}")
            return cls(
                s=np.asarray(data["s"], dtype=np.float64),
                eta=np.asarray(data["eta"], dtype=np.float64),
                demo_lengths=np.asarray(lengths, dtype=np.int64).reshape(-1),
                task=task,
                psi_ref=psi_ref,
                action_dim=_whole(data["action_dim"], "action_dim"),
                source=_text(data["source"], "source") if "source" in data else "unknown",
            )
        except (TypeError, ValueError, KeyError, IndexError, OverflowError) as e:
            raise ValueError(one_line(f"{path}: invalid demonstration file: {e}")) from None


def _whole(a: np.ndarray, name: str) -> int:
    """One whole number stored as a 0-d (or one-element) integer array."""
    if a.size != 1 or a.dtype.kind not in "iu":
        raise ValueError(f"{name} must be one whole number, got {a.dtype} {a.shape}")
    return int(a.reshape(-1)[0])


def _text(a: np.ndarray, name: str) -> str:
    """One string stored as a 0-d unicode array."""
    if a.size != 1 or a.dtype.kind != "U":
        raise ValueError(f"{name} must be one string, got {a.dtype} {a.shape}")
    return str(a.reshape(-1)[0])


def _min_jerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def _blend(s, s0, s1, a, b):
    """Minimum-jerk move from a to b over s in [s0, s1] (a, b broadcast over trailing dims)."""
    w = _min_jerk((s - s0) / max(s1 - s0, 1e-9))[:, None]
    return a + (b - a) * w


# Task shapes (m, rad): TCP height above the target frame when hovering, at the end of the
# motion, and the yaw turned while seating (NutThread threads the nut, 2 mm per turn).
_SHAPES = {
    "PegInsert": dict(z_hover=0.037, z_end=0.0074, seat_turn=0.0, align_yaw_to_target=False),
    "GearMesh": dict(z_hover=0.025, z_end=0.002, seat_turn=0.0, align_yaw_to_target=True),
    "NutThread": dict(z_hover=0.004, z_end=0.004 - 0.002 * (120.0 / 360.0), seat_turn=math.radians(-120.0),
                      align_yaw_to_target=False),
}


def synthetic_demos(task: str, num_demos: int = 10, action_dim: int = 6, seed: int = 0) -> DemoSet:
    """Draw `num_demos` synthetic demonstrations of `task` on its control grid (see module doc)."""
    spec = get_task(task)
    if num_demos < 1:
        raise ValueError(f"num_demos must be >= 1, got {num_demos}")
    if action_dim not in (4, 6):
        raise ValueError(f"action_dim must be 4 or 6, got {action_dim}")
    shape = _SHAPES[spec.name]
    rng = np.random.default_rng(seed)
    n = spec.episode_steps + 1
    s = np.linspace(0.0, 1.0, n)
    all_eta = []
    for _ in range(num_demos):
        target_noise = rng.normal(0.0, 0.001, 3)  # eq. 5.23: the target frame is off by this
        start = np.array([0.0, 0.0, spec.hand_init_height]) + rng.uniform(-1, 1, 3) * np.array(spec.ee_pos_noise)
        yaw_half = 0.5 * (spec.ee_yaw_range[1] - spec.ee_yaw_range[0])
        yaw0 = spec.psi_ref + rng.uniform(-yaw_half, yaw_half)
        if shape["align_yaw_to_target"]:
            yaw1 = spec.psi_ref + rng.uniform(*spec.target_yaw_range)
        else:
            yaw1 = spec.psi_ref + 0.2 * (yaw0 - spec.psi_ref)  # turns most of the way to the reference
        s_align = 0.40 + rng.uniform(-0.05, 0.05)
        s_seat = 0.80 + rng.uniform(-0.05, 0.05)
        hover = np.array([0.0, 0.0, shape["z_hover"]])
        end = np.array([0.0, 0.0, shape["z_end"]])
        pos = np.where(s[:, None] < s_align, _blend(s, 0.0, s_align, start, hover), _blend(s, s_align, s_seat, hover, end))
        pos = pos - target_noise  # relative to the noisy target frame
        yaw = np.where(s < s_align, _blend(s, 0.0, s_align, np.array([yaw0]), np.array([yaw1]))[:, 0],
                       _blend(s, s_align, s_seat, np.array([yaw1]), np.array([yaw1 + shape["seat_turn"]]))[:, 0])
        if action_dim == 6:
            tilt0 = rng.uniform(-1, 1, 2) * math.radians(3.0)  # small roll/pitch error, removed while aligning
            tilt = _blend(s, 0.0, s_align, tilt0, np.zeros(2))
        else:
            tilt = np.zeros((n, 2))
        # sensor-like jitter so every step has some spread: 0.1 mm, 0.1 degree
        pos = pos + rng.normal(0.0, 1e-4, pos.shape)
        yaw = yaw + rng.normal(0.0, math.radians(0.1), n)
        if action_dim == 6:
            tilt = tilt + rng.normal(0.0, math.radians(0.1), tilt.shape)
        q_tcp = quat_from_euler_xyz(
            torch.as_tensor(math.pi + tilt[:, 0]), torch.as_tensor(tilt[:, 1]), torch.as_tensor(yaw)
        )
        eta = pose_to_eta(torch.as_tensor(pos), q_tcp, torch.zeros(3, dtype=torch.float64), spec.psi_ref).numpy()
        eta[:, 3:] = unwrap_rotation_vectors(eta[:, 3:])
        if action_dim == 4:
            eta[:, 3:5] = 0.0
        all_eta.append(eta)
    return DemoSet(
        s=np.tile(s, num_demos),
        eta=np.concatenate(all_eta),
        demo_lengths=np.full(num_demos, n, dtype=np.int64),
        task=spec.name,
        psi_ref=spec.psi_ref,
        action_dim=action_dim,
        source="synthetic",
    )
