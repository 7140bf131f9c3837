"""The KGRL fast path: per-step tables so that eta = m[n] + B[n] zeta (thesis eq. 4.36).

On the uniform control grid s_n = n dt (n = 0..n_steps, dt = KMP dt of Table 5.4) the KGRL
prediction at step n uses
  - the receding reference window s_n, s_n + dt, ..., s_n + h dt, each clamped to s <= 1
    (past the end the window keeps h+1 points and repeats s = 1, so GMR never extrapolates
    and the final pose is held ever more firmly);
  - the query s* = s_n and the null-space input s_hat = s* (the KGRL author's formulation).
Everything but zeta is then fixed per step index, so
    m[n] = k* A mu                                  (O,)
    B[n] = (beta/gamma) (k_hat* - k* A K_hat)       (O, O),  A = (K + gamma Sigma)^-1,
are computed once, batched over steps, in float64 with Cholesky. At run time a policy
action a in [-1, 1]^D is scaled to zeta = w * a (eq. 5.20) and eta = m[n] + B[n] zeta is
turned into a TCP pose (eqs. 5.25, 5.32): `predict_pose` here in torch, and the Warp
kernel `vkgrl_newton.kernels.kmp_horizon` for the batched env step.

Tables always have O = 6 (x, y, z, rx, ry, rz). In 4D mode the KMP is fitted on (x, y, z,
rz) only and embedded: rows and columns of rx, ry are zero, so roll and pitch stay at the
reference whatever zeta is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .._io import atomic_savez, load_npz, one_line
from ..rotations import quat_exp, quat_mul
from .gmr import GMM, gmr
from .kmp import _check_nonnegative, _check_positive
from .pose import AXES_4D

__all__ = ["KMPTables", "build_kmp_tables", "null_space_reach", "with_reach_floor", "with_seat_press", "EmpiricalReference", "REFERENCES", "demonstrations_on_grid", "kmp_eta_torch", "kmp_pose_torch", "control_grid", "reference_window", "tables_path_for"]

TABLES_FORMAT_VERSION = 1


def _steps_of(dt: float) -> int:
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    n_steps = int(round(1.0 / dt))
    if n_steps < 1 or abs(n_steps * dt - 1.0) > 1e-9:
        raise ValueError(f"dt must be 1/n for a whole number of steps n, got dt = {dt} (1/dt = {1.0 / dt})")
    return n_steps


def control_grid(dt: float) -> torch.Tensor:
    """Normalized times s_n = n dt, n = 0..1/dt (float64, inclusive of s = 1)."""
    n_steps = _steps_of(dt)
    return torch.arange(n_steps + 1, dtype=torch.float64) / n_steps


def reference_window(dt: float, horizon: int) -> torch.Tensor:
    """Reference inputs of every step's window, (n_steps + 1, horizon + 1): s_n + j dt clamped to 1."""
    if int(horizon) != horizon or horizon < 0:
        raise ValueError(f"horizon must be a whole number >= 0, got {horizon}")
    grid = control_grid(dt)
    offsets = torch.arange(int(horizon) + 1, dtype=torch.float64) * dt
    return torch.clamp(grid[:, None] + offsets[None, :], max=1.0)


@dataclass(frozen=True)
class KMPTables:
    """Per-step KGRL tables on the control grid.

    mean: m (S, 6); gain: B (S, 6, 6); S = n_steps + 1; float64 CPU tensors.
    dt, horizon, lam, beta, l: the KMP parameters they were built with; action_dim 4 or 6.
    gmm: the GMM the reference came from (kept so the prior can be re-derived and plotted).
    source_sha256: hash of the demonstration file they were fitted to ('' if none).
    fit_seed: the random seed of the GMM fit (-1 if unknown), part of the cache key.
    reference: "gmr" (the thesis: GMR of the GMM, eqs. 4.2-4.3) or "empirical" (the
    demonstrations' own per-step mean and covariance, `empirical_reference`).
    """

    mean: torch.Tensor
    gain: torch.Tensor
    dt: float
    horizon: int
    lam: float
    beta: float
    l: float
    action_dim: int
    gmm: GMM
    source_sha256: str = ""
    fit_seed: int = -1
    reference: str = "gmr"  # what (mu, Sigma) the KMP was fitted to: REFERENCES

    @property
    def n_steps(self) -> int:
        return self.mean.shape[0] - 1

    def predict_eta(self, step_index: torch.Tensor, zeta: torch.Tensor) -> torch.Tensor:
        """eta = m[n] + B[n] zeta, batched: step_index (E,) int, zeta (E, 6) -> (E, 6).

        Step indices past the table's end use its last entry (s = 1). Runs on zeta's device/dtype.
        A reference and offline tool: it copies the tables to that device on every call. The
        per-step path is the Warp kernel with `to_warp()` arrays made once.
        """
        mean = self.mean.to(zeta.device, zeta.dtype)
        gain = self.gain.to(zeta.device, zeta.dtype)
        return kmp_eta_torch(step_index, zeta, mean, gain)

    def predict_pose(self, step_index, zeta, target_pos_w, ref_quat_w):
        """Commanded TCP pose in world frame: (pos (E, 3), quat (E, 4) xyzw), eqs. 5.25 and 5.32.

        target_pos_w (E, 3): target frame position; ref_quat_w (E, 4): q_ref = q(pi, 0, psi_ref).
        The torch counterpart of the Warp kernel `kmp_horizon_pose`.
        """
        mean = self.mean.to(zeta.device, zeta.dtype)
        gain = self.gain.to(zeta.device, zeta.dtype)
        return kmp_pose_torch(step_index, zeta, mean, gain, target_pos_w, ref_quat_w)

    def to_warp(self, device=None):
        """The tables as float32 warp arrays for `kmp_horizon_pose`: (m (S,) vec6f, B (S,) mat66f)."""
        import warp as wp

        from ..kernels.kmp_horizon import mat66f, vec6f

        mean = wp.array(self.mean.to(torch.float32).numpy(), dtype=vec6f, device=device)
        gain = wp.array(self.gain.to(torch.float32).numpy(), dtype=mat66f, device=device)
        return mean, gain

    # -- persistence ---------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the tables to an npz file atomically (temporary file + rename)."""
        return atomic_savez(
            path,
            overwrite=True,
            format_version=np.int64(TABLES_FORMAT_VERSION),
            mean=self.mean.numpy(),
            gain=self.gain.numpy(),
            dt=np.float64(self.dt),
            horizon=np.int64(self.horizon),
            lam=np.float64(self.lam),
            beta=np.float64(self.beta),
            l=np.float64(self.l),
            action_dim=np.int64(self.action_dim),
            gmm_weights=self.gmm.weights.numpy(),
            gmm_means=self.gmm.means.numpy(),
            gmm_covariances=self.gmm.covariances.numpy(),
            source_sha256=np.str_(self.source_sha256),
            fit_seed=np.int64(self.fit_seed),
            reference=np.str_(self.reference),
        )

    @classmethod
    def load(cls, path) -> "KMPTables":
        """Read tables written by `save`; FileNotFoundError if missing, ValueError if damaged,
        incomplete, of another format version, or inconsistent (shapes, NaN, grid length)."""
        data = load_npz(path, "KMP tables", _TABLE_KEYS)
        try:
            version = _one(data, "format_version", "iu")
            if version != TABLES_FORMAT_VERSION:
                raise ValueError(f"tables format {version}, this code reads {TABLES_FORMAT_VERSION}; rebuild them")
            arrays = {}
            for name in ("mean", "gain", "gmm_weights", "gmm_means", "gmm_covariances"):
                if data[name].dtype.kind not in "iuf":  # text or complex numbers are no tables
                    raise ValueError(f"{name} is {data[name].dtype}, not real numbers")
                if not np.isfinite(data[name]).all():
                    raise ValueError(f"{name} contains NaN or inf")
                arrays[name] = torch.as_tensor(data[name], dtype=torch.float64)
            mean, gain = arrays["mean"], arrays["gain"]
            dt = _one(data, "dt", "iuf")
            if mean.ndim != 2 or mean.shape[1] != 6 or gain.shape != (mean.shape[0], 6, 6):
                raise ValueError(f"mean {tuple(mean.shape)} / gain {tuple(gain.shape)} are not (S, 6) / (S, 6, 6)")
            if mean.shape[0] != _steps_of(dt) + 1:
                raise ValueError(f"{mean.shape[0]} table rows do not match dt = {dt} ({_steps_of(dt) + 1} grid points)")
            horizon, action_dim = _one(data, "horizon", "iu"), _one(data, "action_dim", "iu")
            lam, beta, l = (_one(data, k, "iuf") for k in ("lam", "beta", "l"))
            _check_params(lam, beta, l, action_dim)
            if horizon < 0:
                raise ValueError(f"horizon must be >= 0, got {horizon}")
            reference = _one(data, "reference", "U") if "reference" in data else "gmr"  # older files: GMR
            if reference not in REFERENCES:
                raise ValueError(f"reference {reference!r}; allowed: {list(REFERENCES)}")
            return cls(
                mean=mean,
                gain=gain,
                dt=dt,
                horizon=horizon,
                lam=lam,
                beta=beta,
                l=l,
                action_dim=action_dim,
                gmm=GMM(weights=arrays["gmm_weights"], means=arrays["gmm_means"],
                        covariances=arrays["gmm_covariances"]),
                source_sha256=_one(data, "source_sha256", "U"),
                fit_seed=_one(data, "fit_seed", "iu"),
                reference=reference,
            )
        except (TypeError, ValueError, IndexError, OverflowError) as e:
            raise ValueError(one_line(f"{path}: invalid KMP tables file: {e}")) from None


def _one(data: dict, name: str, kinds: str):
    """The one value of a scalar entry of a tables file, of a dtype kind in `kinds` (i, u, f, U)."""
    a = data[name]
    if a.size != 1 or a.dtype.kind not in kinds:
        raise ValueError(f"{name} must be one {'string' if kinds == 'U' else 'number'}, got {a.dtype} {a.shape}")
    v = a.reshape(-1)[0]
    return str(v) if kinds == "U" else int(v) if kinds in ("iu",) else float(v)


_TABLE_KEYS = ("format_version", "mean", "gain", "dt", "horizon", "lam", "beta", "l", "action_dim",
               "gmm_weights", "gmm_means", "gmm_covariances", "source_sha256", "fit_seed")


def _check_params(lam, beta, l, action_dim):
    _check_positive("lam", lam)
    _check_nonnegative("beta", beta)
    _check_positive("l", l)
    if action_dim not in (4, 6):
        raise ValueError(f"action_dim must be 4 or 6, got {action_dim}")


def build_kmp_tables(
    gmm: GMM,
    dt: float,
    horizon: int,
    lam: float,
    beta: float,
    l: float,
    action_dim: int = 6,
    source_sha256: str = "",
    fit_seed: int = -1,
    reference: EmpiricalReference | None = None,
) -> KMPTables:
    """Precompute m[n] and B[n] for every step of the control grid, batched over steps.

    gmm: the fitted GMM over (s, eta) with O = 6 outputs. See the module docstring for the
    window and the 4D embedding.
    """
    _check_params(lam, beta, l, action_dim)
    if gmm.output_dim != 6:
        raise ValueError(f"gmm must model the 6D relative pose; it has {gmm.output_dim} outputs")
    windows = reference_window(dt, horizon)  # (S, W)
    n_grid, w = windows.shape
    mu, sigma = gmr(gmm, windows.reshape(-1)) if reference is None else reference(windows.reshape(-1))
    axes = list(AXES_4D) if action_dim == 4 else list(range(6))
    o = len(axes)
    mu = mu[:, axes].reshape(n_grid, w, o)
    sigma = sigma[:, axes][:, :, axes].reshape(n_grid, w, o, o)

    gamma = float(lam) + float(beta)
    eye = torch.eye(o, dtype=torch.float64)
    k = torch.exp(-float(l) * (windows[:, :, None] - windows[:, None, :]) ** 2)  # (S, W, W)
    # K + gamma Sigma as (S, W, O, W, O) -> (S, WO, WO), time-major like ns_kmp_predict
    big = k[:, :, None, :, None] * eye[None, None, :, None, :]
    big = big.clone()
    idx = torch.arange(w)
    big[:, idx, :, idx, :] += gamma * sigma.permute(1, 0, 2, 3)
    big = big.reshape(n_grid, w * o, w * o)
    chol, info = torch.linalg.cholesky_ex(big)
    if (info != 0).any():
        first = int(torch.nonzero(info)[0])
        raise ValueError(f"K + gamma*Sigma is not positive definite at step {first}; check the demonstrations")

    k_star = k[:, 0, :]  # k(s*, s_i) with s* = s_n = first window point, (S, W)
    k_hat = k[:, :, 0]  # k(s_i, s_hat) with s_hat = s*, (S, W)
    a_mu = torch.cholesky_solve(mu.reshape(n_grid, w * o, 1), chol).reshape(n_grid, w, o)
    k_hat_full = (k_hat[:, :, None, None] * eye).reshape(n_grid, w * o, o)
    a_k_hat = torch.cholesky_solve(k_hat_full, chol).reshape(n_grid, w, o, o)
    mean_o = torch.einsum("sw,swo->so", k_star, a_mu)
    gain_o = (float(beta) / gamma) * (eye - torch.einsum("sw,swij->sij", k_star, a_k_hat))  # k_hat* = k(s*,s*) = 1

    mean = torch.zeros(n_grid, 6, dtype=torch.float64)
    gain = torch.zeros(n_grid, 6, 6, dtype=torch.float64)
    mean[:, axes] = mean_o
    gain[:, torch.tensor(axes)[:, None], torch.tensor(axes)[None, :]] = gain_o
    return KMPTables(
        mean=mean,
        gain=gain,
        dt=float(dt),
        horizon=int(horizon),
        lam=float(lam),
        beta=float(beta),
        l=float(l),
        action_dim=int(action_dim),
        gmm=gmm,
        source_sha256=source_sha256,
        fit_seed=int(fit_seed),
        reference="gmr" if reference is None else "empirical",
    )


def kmp_eta_torch(step_index, zeta, mean, gain) -> torch.Tensor:
    """eta = m[n] + B[n] zeta with n clamped to the table; all tensors on one device.

    step_index (E,) int; zeta (E, 6); mean (S, 6); gain (S, 6, 6) -> (E, 6).
    """
    idx = torch.clamp(step_index.long(), 0, mean.shape[0] - 1)
    return mean[idx] + torch.einsum("eij,ej->ei", gain[idx], zeta)


def null_space_reach(gain: torch.Tensor, scale) -> torch.Tensor:
    """How far a saturated action moves each axis of eta: sum_j |B[n]_ij| w_j, (S, 6) (m, rad).

    gain (S, 6, 6); scale: the action weights w (6,) of zeta = w a (Table 5.4). The largest move of
    axis i over every action in [-1, 1]^D (a bound reached at a = sign(B[n]_i.))."""
    w = torch.as_tensor(scale, dtype=gain.dtype)
    return (gain.abs() * w[None, None, :]).sum(-1)


def with_reach_floor(tables: KMPTables, floor: float, scale, axes=(0, 1)) -> KMPTables:
    """The tables with a saturated action reaching at least `floor` (m) on `axes` at every step.

    A deviation from the thesis (option `--kgrl-reach-floor`): B[n] ~ beta Sigma[n], so where the
    demonstrations agree (the PegInsert descent, n >= 50) the null space moves x and y by ~1 mm and
    ~0.6 mm, less than the in-hand offset (+-3 mm) and the target's observation noise (1 mm sd) that
    make the prior miss; RL cannot correct what it cannot reach. Each axis i short of the floor gets
    d = (floor - reach_i[n]) / w_i added to B[n]_ii (with B[n]_ii's sign), so that reach_i[n] =
    max(reach_i[n], floor) and a = 0 still follows the prior exactly (m[n] is unchanged)."""
    if not (math.isfinite(floor) and floor >= 0):
        raise ValueError(f"reach floor must be a finite number >= 0 (m), got {floor}")
    if floor == 0:
        return tables
    w = torch.as_tensor(scale, dtype=tables.gain.dtype)
    gain = tables.gain.clone()
    reach = null_space_reach(gain, w)
    for i in axes:
        short = torch.clamp(floor - reach[:, i], min=0.0) / w[i]
        sign = torch.where(gain[:, i, i] < 0, -1.0, 1.0).to(gain.dtype)
        gain[:, i, i] += sign * short
    return dataclasses.replace(tables, gain=gain)


def with_seat_press(tables: KMPTables, press: float, ramp_steps: int = 10) -> KMPTables:
    """The tables with the prior's z mean lowered `press` (m) from its seat on: from the first step within 1 mm
    of its final z, ramped over `ramp_steps` steps. Gains unchanged, so the null space is the same.

    A deviation from the thesis (option `--kgrl-seat-press`): the demonstrations record the TCP's *measured*
    pose, so the prior's last z is the demonstrations' mean seated height and its command does not press
    (docs/results/ceiling_40: a part whose grasp sits higher than the mean ends 1.5-3.9 mm above its seat, held
    there). The scripted demonstrator itself commands 4-6 mm below the seat."""
    if not (math.isfinite(press) and press >= 0):
        raise ValueError(f"seat press must be a finite number >= 0 (m), got {press}")
    if press == 0:
        return tables
    mean = tables.mean.clone()
    z = mean[:, 2]
    near = torch.nonzero((z - z[-1]).abs() < 1e-3).flatten()
    n0 = int(near[0]) if near.numel() else z.shape[0] - 1
    ramp = ((torch.arange(z.shape[0], dtype=mean.dtype) - n0 + 1) / float(ramp_steps)).clamp(0.0, 1.0)
    mean[:, 2] = z - press * ramp
    return dataclasses.replace(tables, mean=mean)


def kmp_pose_torch(step_index, zeta, mean, gain, target_pos_w, ref_quat_w):
    """The computation of the Warp kernel `kmp_horizon_pose` in torch: (pos (E, 3), quat (E, 4) xyzw)."""
    eta = kmp_eta_torch(step_index, zeta, mean, gain)
    return target_pos_w + eta[:, :3], quat_mul(ref_quat_w, quat_exp(eta[:, 3:]))


def tables_path_for(demo_path, action_dim: int, reference: str = "gmr") -> Path:
    """Where the tables of a demonstration file live: beside it, `<stem>.kmp<D>d.npz` (GMR, the
    thesis's reference) or `<stem>.kmp<D>d_<reference>.npz`."""
    demo_path = Path(demo_path)
    suffix = "" if reference == "gmr" else f"_{reference}"
    return demo_path.with_name(f"{demo_path.stem}.kmp{int(action_dim)}d{suffix}.npz")


REFERENCES = ("gmr", "empirical")


def demonstrations_on_grid(demos, dt: float) -> np.ndarray:
    """Every demonstration's eta at the control grid's times s_n (each linearly interpolated in its
    own normalized time): (num_demos, n_steps + 1, 6) float64."""
    grid = control_grid(dt).numpy()
    return np.stack([np.stack([np.interp(grid, s, eta[:, k]) for k in range(6)], axis=1)
                     for s, eta in demos.split()])


class EmpiricalReference:
    """(mu, Sigma) at the control grid's times: the mean and covariance (ddof 1, plus `ridge` I)
    of the demonstrations at each grid step, a deviation from the thesis's GMR (eqs. 4.2-4.3),
    for demonstrations that share their time base (the scripted ones: one control grid).

    Why: a 7-component GMM over (s, eta) cannot follow PegInsert's descent (the prior sat 4 mm
    below the demonstrations' mean at n = 60 with an sd 2.4x theirs, docs/log/benchmarks.md); the
    demonstrations' own statistics are what GMR estimates, without the mixture's bias.
    """

    def __init__(self, demos, dt: float, ridge: float = 1e-10):
        on_grid = demonstrations_on_grid(demos, dt)
        if on_grid.shape[0] < 2:
            raise ValueError("the empirical reference needs >= 2 demonstrations (a covariance)")
        self.dt = float(dt)
        self.mu = on_grid.mean(axis=0)
        x = on_grid - self.mu[None]
        self.sigma = np.einsum("dsi,dsj->sij", x, x) / (on_grid.shape[0] - 1) + ridge * np.eye(6)

    def __call__(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.as_tensor(s, dtype=torch.float64)
        k = torch.round(s / self.dt).long()
        if (k.double() * self.dt - s).abs().max() > 1e-9:
            raise ValueError("EmpiricalReference is defined on the control grid only")
        return torch.as_tensor(self.mu[k.numpy()]), torch.as_tensor(self.sigma[k.numpy()])
