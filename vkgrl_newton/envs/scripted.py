"""A scripted demonstrator with privileged state: approach above the hole, align, descend, insert.

It commands absolute TCP poses through `AssemblyEnv.step_pose` (the same entry point KGRL uses),
one per control step. Per world and per episode it draws its own approach height, speeds and
timing, so demonstrations vary naturally (the KMP learns a distribution, not one curve).

Phases (positions are of the held part's bottom, the quantity that must reach the hole):
1. align: move the part's bottom to `approach_height` above the fixed tip on the hole axis, at
   `approach_speed`, while turning the gripper yaw toward psi_ref;
2. descend: along the axis at `descend_speed`, toward `push_depth` below the hole bottom (the
   compliant controller turns the overshoot into a gentle push: 100 N/m x ~5 mm);
3. hold: keep pushing at that target until the episode ends.
The in-hand offset of the part (TCP minus part bottom) is measured from the simulator at every
step until the part comes within 1 mm of the fixed part's top, then frozen (servoing on a grasp
that shifts under contact forces would chase the contact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..kmp.pose import euler_xyz_from_quat, quat_from_euler_xyz

__all__ = ["ScriptedInserter", "ScriptedParams"]


@dataclass(frozen=True)
class ScriptedParams:
    approach_height: tuple[float, float] = (0.006, 0.012)  # m above the fixed tip, part bottom
    approach_speed: tuple[float, float] = (0.025, 0.04)  # m/s
    descend_speed: tuple[float, float] = (0.012, 0.02)  # m/s
    push_depth: tuple[float, float] = (0.004, 0.006)  # m below the hole bottom
    align_tolerance: float = 0.0008  # m, xy error of the part bottom before descending
    settle_speed: float = 0.003  # m/s, TCP speed below which the arm counts as stopped
    yaw_rate: float = math.radians(60.0)  # rad/s toward psi_ref
    start_delay_steps: tuple[int, int] = (0, 4)  # control steps of waiting at the start


class ScriptedInserter:
    """Batched over the env's worlds. Call `reset(env)` after each env reset, then `act(env)`."""

    def __init__(self, params: ScriptedParams | None = None, seed: int = 0):
        self.params = params or ScriptedParams()
        self.seed = seed
        self._gen = None

    def _u(self, n, lo_hi, device):
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(n, device=device, generator=self._gen)

    def reset(self, env) -> None:
        n, dev = env.num_envs, env.tdev
        if self._gen is None:
            self._gen = torch.Generator(device=dev).manual_seed(self.seed)
        p = self.params
        self.height = self._u(n, p.approach_height, dev)
        self.v_approach = self._u(n, p.approach_speed, dev)
        self.v_descend = self._u(n, p.descend_speed, dev)
        self.push = self._u(n, p.push_depth, dev)
        lo, hi = p.start_delay_steps
        self.delay = torch.randint(lo, hi + 1, (n,), device=dev, generator=self._gen)
        self.phase = torch.zeros(n, dtype=torch.long, device=dev)
        self.offset = torch.zeros(n, 3, device=dev)  # TCP - part bottom, world
        tcp_p, tcp_q = env._tcp_pose()
        self.cmd_pos = tcp_p.clone()
        _, _, self.yaw = euler_xyz_from_quat(tcp_q)
        self.yaw = self.yaw.clone()

    def act(self, env) -> tuple[torch.Tensor, torch.Tensor]:
        """The TCP pose command (world frame) for this control step."""
        p = self.params
        dt = env.scene.config.sim_dt * env.scene.config.decimation
        tcp_p, _ = env._tcp_pose()
        held_p, _ = env.held_pose()
        fixed = env.fixed_pos_w  # true hole bottom on the axis (privileged)
        tip_z = fixed[:, 2] + env.geometry.fixed_height
        waiting = env.episode_length_buf < self.delay

        align = self.phase == 0
        tip_z_now = fixed[:, 2] + env.geometry.fixed_height
        free = held_p[:, 2] > tip_z_now + 0.001  # not touching the fixed part yet: keep servoing
        self.offset[free] = (tcp_p - held_p)[free]
        goal = fixed.clone()
        goal[:, 2] = torch.where(align, tip_z + self.height, fixed[:, 2] - self.push)
        bottom_cmd = self.cmd_pos - self.offset
        err = goal - bottom_cmd
        speed = torch.where(align, self.v_approach, self.v_descend).unsqueeze(-1)
        step = err.norm(dim=-1, keepdim=True)
        move = err * torch.clamp(speed * dt / step.clamp_min(1e-9), max=1.0)
        move[waiting] = 0.0
        self.cmd_pos = self.cmd_pos + move

        # aligned over the hole (measured on the real part) -> descend
        xy_err = (held_p[:, :2] - fixed[:, :2]).norm(dim=-1)
        z_err = (held_p[:, 2] - (tip_z + self.height)).abs()
        # ... once the command has arrived and the arm has stopped (Factory's soft gains lag and
        # overshoot: passing through the tolerance on the way is not being aligned)
        arrived = (goal - (self.cmd_pos - self.offset)).norm(dim=-1) < 1e-5
        still = env.tcp_twist_w[:, :3].norm(dim=-1) < p.settle_speed
        ready = align & ~waiting & arrived & still & (xy_err < p.align_tolerance) & (z_err < 0.003)
        self.phase[ready] = 1

        # yaw toward psi_ref at a bounded rate
        d_yaw = torch.atan2(torch.sin(env.task.psi_ref - self.yaw), torch.cos(env.task.psi_ref - self.yaw))
        self.yaw = self.yaw + torch.clamp(d_yaw, -p.yaw_rate * dt, p.yaw_rate * dt) * (~waiting).float()
        quat = quat_from_euler_xyz(torch.full_like(self.yaw, math.pi), torch.zeros_like(self.yaw), self.yaw)
        return self.cmd_pos.clone(), quat
