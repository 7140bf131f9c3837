"""The KGRL action path (thesis eqs. 4.36, 5.20, 5.25, 5.32): policy actions -> TCP pose commands.

A policy action a in [-1, 1]^D becomes the scaled null-space input zeta = w * a (w_pos on x, y, z;
w_rot on the rotations, thesis Table 5.4; in 4D zeta = (x, y, z, 0, 0, yaw)), the per-step KMP
tables give eta = m[n] + B[n] zeta at the env's control step n, and eta becomes an absolute TCP
pose command relative to the observed target frame and q_ref: the Warp kernel
`kernels/kmp_horizon.py` does the last two steps for all worlds at once. The env's `step_pose`
then holds that command for the control step. zeta = 0 follows the prior alone.

With `time_steps` k > 0 (the thesis's future work, Chapter 7: KMP inference time as an action) the
policy acts in D + 1 dimensions: the last, a_t, moves the query along the prior, which advances by
1 + round(k a_t) control steps per step (clamped to the tables) instead of by 1, so that a policy can
hold the prior's phase, go back to lift a blocked part and try again, or hurry. a_t = 0 advances it
by exactly 1: the query is the control step and a = 0 is still the prior. The query's phase
(query / n_steps, as the time input) is an input the policy needs: `query_phase()`, appended by
`envs.evaluation.kgrl_observation`.

It lives beside the env it drives; the prior's tables come from `prepare.prior.load_or_make_prior`.
"""

from __future__ import annotations

import torch
import warp as wp

from ..kernels.kmp_horizon import kmp_horizon_pose, vec6f
from ..kmp.tables import KMPTables, with_reach_floor, with_seat_press

__all__ = ["KGRLActionPath"]


class KGRLActionPath:
    """Maps policy actions to absolute TCP pose commands through the KMP tables, batched over worlds."""

    def __init__(self, tables: KMPTables, env, reach_floor: float = 0.0, reach_floor_z: float = 0.0,
                 time_steps: int = 0, seat_press: float = 0.0):
        spec = env.task
        if tables.action_dim != env.num_actions:
            raise ValueError(f"KMP tables are {tables.action_dim}D, the env acts in {env.num_actions}D")
        if tables.n_steps != env.max_episode_length:
            raise ValueError(f"KMP tables cover {tables.n_steps} steps, an episode has {env.max_episode_length}: "
                             f"tables of another task or KMP dt")
        if not (isinstance(time_steps, int) and 0 <= time_steps <= tables.n_steps):
            raise ValueError(f"time_steps={time_steps!r}: control steps per unit time action, an int in "
                             f"[0, {tables.n_steps}]")
        self.env = env
        self.base, self.residual_scale = None, 1.0  # set_base: the controller a = 0 stands for (None: the prior)
        self.env_action_dim = env.num_actions
        self.time_steps = time_steps
        self.action_dim = env.num_actions + (1 if time_steps else 0)  # the policy's: + a_t with the time action
        E, tdev = env.num_envs, env.tdev
        # zeta = scale * a, with a embedded in the 6D (x, y, z, rx, ry, rz) layout of the tables
        self.axes = [0, 1, 2, 5] if self.env_action_dim == 4 else [0, 1, 2, 3, 4, 5]
        scale = [spec.w_pos] * 3 + [spec.w_rot] * (self.env_action_dim - 3)
        # reach_floor (m, x and y) and reach_floor_z (m, z); 0: the thesis. kmp.tables.with_reach_floor, a
        # deviation: late in PegInsert the null space moves z ~2 mm while the prior presses a blocked peg
        # ~20 mm into the hole's face, so a policy cannot lighten the press that keeps it from sliding
        self.reach_floor, self.reach_floor_z = float(reach_floor), float(reach_floor_z)
        w6 = [spec.w_pos] * 3 + [spec.w_rot] * 3
        self.tables = with_reach_floor(with_reach_floor(tables, self.reach_floor, w6), self.reach_floor_z, w6, axes=(2,))
        # seat_press (m): the prior's z lowered that much from its seat on (kmp.tables.with_seat_press); 0: the thesis
        self.seat_press = float(seat_press)
        self.tables = with_seat_press(self.tables, self.seat_press)
        tables = self.tables
        self.scale = torch.tensor(scale, dtype=torch.float32, device=tdev)
        self.zeta = torch.zeros(E, 6, dtype=torch.float32, device=tdev)
        self.eta = torch.zeros(E, 6, dtype=torch.float32, device=tdev)
        self.tcp_pos_cmd_w = torch.zeros(E, 3, dtype=torch.float32, device=tdev)
        self.tcp_quat_cmd_w = torch.zeros(E, 4, dtype=torch.float32, device=tdev)
        # the tables' row each world reads: the control step, or with the time action its own query
        self.query_index = env.step_index.clone()
        self.final_query_index = self.query_index.clone()  # where each world's last step left its query
        self._mean_wp, self._gain_wp = tables.to_warp(env.device)
        self._wp = {  # warp views of the torch buffers (same memory), made once
            "zeta": wp.from_torch(self.zeta, dtype=vec6f),
            "eta": wp.from_torch(self.eta, dtype=vec6f),
            "pos": wp.from_torch(self.tcp_pos_cmd_w, dtype=wp.vec3),
            "quat": wp.from_torch(self.tcp_quat_cmd_w, dtype=wp.quat),
            "step_index": wp.from_torch(env.step_index if not time_steps else self.query_index, dtype=wp.int32),
            "target_pos_w": wp.from_torch(env.target_frame_pos_w, dtype=wp.vec3),
            "ref_quat_w": wp.from_torch(env.ref_quat_w, dtype=wp.quat),
        }

    def pose(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Commanded TCP pose (pos (E, 3), quat (E, 4) xyzw, world frame) for actions (E, D) in [-1, 1]."""
        if actions.shape != (self.env.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.env.num_envs}, {self.action_dim}), got {tuple(actions.shape)}")
        self.zeta[:, self.axes] = actions[:, :self.env_action_dim].clamp(-1.0, 1.0).to(self.zeta) * self.scale
        if self.time_steps:  # a world at its episode's first step starts the prior from its beginning
            self.query_index.masked_fill_(self.env.step_index == 0, 0)
        w = self._wp
        kmp_horizon_pose(w["step_index"], w["zeta"], self._mean_wp, self._gain_wp, w["target_pos_w"], w["ref_quat_w"],
                         w["eta"], w["pos"], w["quat"])
        return self.tcp_pos_cmd_w, self.tcp_quat_cmd_w

    def set_base(self, base, residual_scale: float = 1.0) -> None:
        """A controller under the policy's actions (--kgrl-base; envs.evaluation.base_controller), or None: the
        prior. Each `step` adds the policy's actions to the base's `actions(env, inputs)` (a residual, as ResiP;
        clipped to [-1, 1]), so that a = 0 is the base controller. The base keeps per-world state from step to step
        (it restarts where an episode starts): `step` calls it exactly once a control step; `pose` never does.
        residual_scale in (0, 1]: the policy's actions are scaled by it before they are added (ResiP's residual
        scale: a bounded correction, and exploration noise that much smaller around the base)."""
        if not (0.0 < residual_scale <= 1.0):
            raise ValueError(f"residual_scale={residual_scale!r}; allowed: (0, 1]")
        self.base, self.residual_scale = base, float(residual_scale)

    def with_base(self, actions: torch.Tensor) -> torch.Tensor:
        """The actions `step` commands: the policy's (times residual_scale) plus the base's on the env's axes (the time action's a_t
        stays the policy's), for the state now; the policy's as they are without a base."""
        if self.base is None:
            return actions
        if actions.shape != (self.env.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.env.num_envs}, {self.action_dim}), got {tuple(actions.shape)}")
        env = self.env
        # the base reads what a policy observes: the TCP relative to the observed target frame (policy_observation's
        # columns 1:4; column 0, time, it takes from the env's step counter)
        inputs = torch.cat([torch.zeros_like(env.target_frame_pos_w[:, :1]),
                            env.tcp_pose()[0] - env.target_frame_pos_w], -1)
        out = actions.to(torch.float32).clone()
        D = self.env_action_dim
        out[:, :D] = (self.residual_scale * out[:, :D] + self.base.actions(env, inputs).to(out)).clamp(-1.0, 1.0)
        return out

    def step(self, actions: torch.Tensor):
        """One env control step on the KGRL path; returns what `env.step` returns."""
        actions = self.with_base(actions)
        out = self.env.step_pose(*self.pose(actions))
        if self.time_steps:
            a_t = actions[:, -1].clamp(-1.0, 1.0)
            moved = self.query_index + 1 + torch.round(self.time_steps * a_t).to(torch.int32)
            self.final_query_index.copy_(moved.clamp(0, self.tables.n_steps))  # rows 0..n_steps
            # a world the env has just reset (a new episode) starts the prior again
            self.query_index.copy_(self.final_query_index).masked_fill_(self.env.step_index == 0, 0)
        return out

    def query_phase(self, final: bool = False) -> torch.Tensor | None:
        """(E, 1) the query's phase in [0, 1] with the time action (None without): where each world is
        along the prior now, or with `final`, where its last step left it (before a reset: the state a
        time-out bootstraps from)."""
        if not self.time_steps:
            return None
        q = self.final_query_index if final else torch.where(self.env.step_index == 0, 0, self.query_index)
        return (q.to(torch.float32) / self.tables.n_steps).unsqueeze(-1)  # as the time input: step / episode length
