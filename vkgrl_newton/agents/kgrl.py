"""The KGRL action path (thesis eqs. 4.36, 5.20, 5.25, 5.32) and the task's KMP prior.

A policy action a in [-1, 1]^D becomes the scaled null-space input zeta = w * a (w_pos on x, y, z;
w_rot on the rotations, thesis Table 5.4; in 4D zeta = (x, y, z, 0, 0, yaw)), the per-step KMP
tables give eta = m[n] + B[n] zeta at the env's control step n, and eta becomes an absolute TCP
pose command relative to the observed target frame and q_ref: the Warp kernel
`kernels/kmp_horizon.py` does the last two steps for all worlds at once. The env's `step_pose`
then holds that command for the control step. zeta = 0 follows the prior alone.

The prior (`load_or_make_prior`) is fitted to scripted demonstrations recorded in the simulator
(envs/demonstrations.py), cached per task under `cache_dir` and reused; 4D and 6D tables come
from the same 6D demonstrations.
"""

from __future__ import annotations

from pathlib import Path

import torch
import warp as wp

from ..kernels.kmp_horizon import kmp_horizon_pose, vec6f
from ..kmp.demos import DemoSet
from ..kmp.prior import KMP_BETA, KMP_L, KMP_LAMBDA, load_or_fit_prior
from ..cache import file_sha256
from ..kmp.tables import KMPTables, with_reach_floor

__all__ = ["KGRLActionPath", "load_or_make_prior", "demos_path_for", "prior_record"]


class KGRLActionPath:
    """Maps policy actions to absolute TCP pose commands through the KMP tables, batched over worlds."""

    def __init__(self, tables: KMPTables, env, reach_floor: float = 0.0, reach_floor_z: float = 0.0):
        spec = env.task
        if tables.action_dim != env.num_actions:
            raise ValueError(f"KMP tables are {tables.action_dim}D, the env acts in {env.num_actions}D")
        if tables.n_steps != env.max_episode_length:
            raise ValueError(f"KMP tables cover {tables.n_steps} steps, an episode has {env.max_episode_length}: "
                             f"tables of another task or KMP dt")
        self.env = env
        self.action_dim = env.num_actions
        E, tdev = env.num_envs, env.tdev
        # zeta = scale * a, with a embedded in the 6D (x, y, z, rx, ry, rz) layout of the tables
        self.axes = [0, 1, 2, 5] if self.action_dim == 4 else [0, 1, 2, 3, 4, 5]
        scale = [spec.w_pos] * 3 + [spec.w_rot] * (self.action_dim - 3)
        # reach_floor (m, x and y) and reach_floor_z (m, z); 0: the thesis. kmp.tables.with_reach_floor, a
        # deviation: late in PegInsert the null space moves z ~2 mm while the prior presses a blocked peg
        # ~20 mm into the hole's face, so a policy cannot lighten the press that keeps it from sliding
        self.reach_floor, self.reach_floor_z = float(reach_floor), float(reach_floor_z)
        w6 = [spec.w_pos] * 3 + [spec.w_rot] * 3
        self.tables = with_reach_floor(with_reach_floor(tables, self.reach_floor, w6), self.reach_floor_z, w6, axes=(2,))
        tables = self.tables
        self.scale = torch.tensor(scale, dtype=torch.float32, device=tdev)
        self.zeta = torch.zeros(E, 6, dtype=torch.float32, device=tdev)
        self.eta = torch.zeros(E, 6, dtype=torch.float32, device=tdev)
        self.tcp_pos_cmd_w = torch.zeros(E, 3, dtype=torch.float32, device=tdev)
        self.tcp_quat_cmd_w = torch.zeros(E, 4, dtype=torch.float32, device=tdev)
        self._mean_wp, self._gain_wp = tables.to_warp(env.device)
        self._wp = {  # warp views of the torch buffers (same memory), made once
            "zeta": wp.from_torch(self.zeta, dtype=vec6f),
            "eta": wp.from_torch(self.eta, dtype=vec6f),
            "pos": wp.from_torch(self.tcp_pos_cmd_w, dtype=wp.vec3),
            "quat": wp.from_torch(self.tcp_quat_cmd_w, dtype=wp.quat),
            "step_index": wp.from_torch(env.step_index, dtype=wp.int32),
            "target_pos_w": wp.from_torch(env.target_frame_pos_w, dtype=wp.vec3),
            "ref_quat_w": wp.from_torch(env.ref_quat_w, dtype=wp.quat),
        }

    def pose(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Commanded TCP pose (pos (E, 3), quat (E, 4) xyzw, world frame) for actions (E, D) in [-1, 1]."""
        if actions.shape != (self.env.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.env.num_envs}, {self.action_dim}), got {tuple(actions.shape)}")
        self.zeta[:, self.axes] = actions.clamp(-1.0, 1.0).to(self.zeta) * self.scale
        w = self._wp
        kmp_horizon_pose(w["step_index"], w["zeta"], self._mean_wp, self._gain_wp, w["target_pos_w"], w["ref_quat_w"],
                         w["eta"], w["pos"], w["quat"])
        return self.tcp_pos_cmd_w, self.tcp_quat_cmd_w

    def step(self, actions: torch.Tensor):
        """One env control step on the KGRL path; returns what `env.step` returns."""
        return self.env.step_pose(*self.pose(actions))


def demos_path_for(cache_dir, task: str, num_demos: int, seed: int, geometry: str = "primitives",
                   device: str | None = None) -> Path:
    """Where the scripted demonstrations are cached, keyed by the demonstrator's version (a changed
    demonstrator records anew). The mesh variant's apart, per contact path (SDF on CUDA, the
    triangle BVH and a coarser thread grid on a CPU: not the same physics)."""
    from ..envs.scripted import DEMONSTRATOR_VERSION

    suffix = ""
    if geometry != "primitives":
        from ..runtime import default_device

        suffix = f"_{geometry}_{'sdf' if str(device or default_device()).startswith('cuda') else 'bvh'}"
    return (Path(cache_dir) / task
            / f"demos_scripted_v{DEMONSTRATOR_VERSION}_factory_n{num_demos}_seed{seed}{suffix}.npz")


def load_or_make_prior(task: str, action_dim: int, cache_dir, demos: str | Path | None = None, num_demos: int = 16,
                       num_envs: int = 16, device: str | None = None, seed: int = 0,
                       geometry: str = "primitives", lam: float = KMP_LAMBDA, beta: float = KMP_BETA,
                       l: float = KMP_L, reference: str = "gmr", log=print) -> tuple[KMPTables, Path]:
    """The task's KMP tables, with the demonstrations they come from recorded first if missing.

    demos: a demonstration npz of your own; None records `num_demos` scripted ones in the
    Factory env (6D, `num_envs` worlds, the parts' collision `geometry`: sim.scene.GEOMETRIES)
    into `cache_dir/<task>/` once and reuses them. The tables (KMP parameters lam, beta, l) are
    cached beside the demonstrations (kmp.prior.load_or_fit_prior: keyed by content). Both are
    made under the demonstration file's cache lock (`vkgrl_newton.cache`): runs started together
    record and fit once. reference: the KMP's reference distribution, "gmr" (the thesis) or
    "empirical" (kmp.tables.EmpiricalReference). Returns (tables, demonstration path).
    """
    from ..cache import entry_lock

    if demos is None:
        path = demos_path_for(cache_dir, task, num_demos, seed, geometry, device)
    else:
        path = Path(demos)
        if not path.exists():
            raise FileNotFoundError(f"demonstrations {path} not found")
        demo_task = DemoSet.load(path).task
        if demo_task != task:
            raise ValueError(f"demonstrations {path} are of task {demo_task!r}, not {task!r}")
    with entry_lock(path, log=log, what=f"the {task} demonstrations"):
        if demos is None and not path.exists():
            _record_scripted(task, path, num_demos, num_envs, device, seed, geometry, log)
        tables, tables_path, rebuilt = load_or_fit_prior(path, action_dim=action_dim, lam=lam, beta=beta, l=l,
                                                         seed=seed, reference=reference)
    log(f"KMP prior {'fitted' if rebuilt else 'loaded'}: {tables_path}")
    return tables, path


def prior_record(tables: KMPTables, demos_path, reach_floor_mm: float = 0.0, reach_floor_z_mm: float = 0.0) -> dict:
    """What a KGRL run records of its prior (checkpoint meta "prior"): the demonstration file and its
    sha256, the KMP parameters and the number of demonstrations (`cache.check_unchanged` checks the file),
    and the action path's reach floors (mm, x-y and z) where there are."""
    record = {"demos": str(demos_path), "demos_sha256": file_sha256(demos_path), "lam": float(tables.lam),
              "beta": float(tables.beta), "l": float(tables.l),
              "num_demos": int(len(DemoSet.load(demos_path).demo_lengths))}
    if tables.reference != "gmr":  # absent for the thesis's GMR, so older runs' records still match
        record["reference"] = tables.reference
    if reach_floor_mm > 0:  # likewise absent for the thesis's null space
        record["reach_floor_mm"] = float(reach_floor_mm)
    if reach_floor_z_mm > 0:
        record["reach_floor_z_mm"] = float(reach_floor_z_mm)
    return record


def _record_scripted(task, path, num_demos, num_envs, device, seed, geometry, log) -> None:
    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..envs.demonstrations import record_demonstrations
    from ..sim.scene import SimConfig

    log(f"recording {num_demos} scripted {task} demonstrations into {path} (once; cached)")
    env = AssemblyEnv(EnvConfig(task=task, family="factory", action_dim=6, num_envs=num_envs, device=device,
                                seed=seed, sim=SimConfig(geometry=geometry)))
    demo_set, episodes = record_demonstrations(env, num_demos, seed=seed,
                                               max_episodes=max(4, 3 * num_demos // num_envs + 2))
    if demo_set is None or len(demo_set.demo_lengths) < num_demos:
        got = 0 if demo_set is None else len(demo_set.demo_lengths)
        raise RuntimeError(f"the scripted demonstrator seated the part in only {got} of {episodes * num_envs} "
                           f"episodes, {num_demos} needed; see docs/benchmarks.md for its success rate")
    path.parent.mkdir(parents=True, exist_ok=True)
    demo_set.save(path)
