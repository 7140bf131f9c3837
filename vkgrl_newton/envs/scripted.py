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

from ..kmp.pose import euler_xyz_from_quat, quat_conjugate, quat_from_euler_xyz, quat_rotate

__all__ = ["ScriptedInserter", "ScriptedParams"]


@dataclass(frozen=True)
class ScriptedParams:
    approach_height: tuple[float, float] = (0.006, 0.012)  # m above the fixed tip, part bottom
    approach_speed: tuple[float, float] = (0.02, 0.035)  # m/s
    descend_speed: tuple[float, float] = (0.008, 0.012)  # m/s (mean speed of a minimum-jerk segment)
    push_depth: tuple[float, float] = (0.004, 0.006)  # m below the hole bottom
    align_tolerance: float = 0.0008  # m, xy error of the part bottom before descending
    settle_speed: float = 0.003  # m/s, TCP speed below which the arm counts as stopped
    lateral_gain: float = 0.1  # per step, integral gain on the part's lateral error at rest
    max_bias: float = 0.003  # m, bound on the integral correction
    min_segment_s: float = 1.0  # s, shortest approach (the yaw turn shares its timing)
    rest_steps: int = 3  # consecutive aligned, still control steps before descending
    entry_height: float = 0.001  # m above the fixed tip: the second alignment check
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
        tcp_p, tcp_q = env._tcp_pose()
        held_p, _ = env.held_pose()
        # rigid grasp offset (TCP - part bottom) in the TCP frame, measured once after the grasp
        # settled; re-measuring it every step feeds the arm's own sway back into the command
        self.offset_tcp = quat_rotate(quat_conjugate(tcp_q), tcp_p - held_p)
        self.bias = torch.zeros(n, 3, device=dev)  # slow integral correction at rest above the hole
        self.seg_start = held_p.clone()  # minimum-jerk segment of the part bottom's reference
        self.seg_goal = held_p.clone()
        self.seg_t0 = torch.zeros(n, device=dev)
        self.seg_len = torch.ones(n, device=dev)
        self.started = torch.zeros(n, dtype=torch.bool, device=dev)
        _, _, yaw = euler_xyz_from_quat(tcp_q)
        self.yaw0, self.yaw = yaw.clone(), yaw.clone()
        self.rest_steps = torch.zeros(n, dtype=torch.long, device=dev)

    def _start_segment(self, mask, env, goal, speed, t):
        ref = self._reference(t)
        self.seg_start[mask] = ref[mask]
        self.seg_goal[mask] = goal[mask]
        self.seg_t0[mask] = t[mask]
        self.seg_len[mask] = ((goal - ref).norm(dim=-1) / speed).clamp_min(self.params.min_segment_s)[mask]

    def _reference(self, t):
        tau = ((t - self.seg_t0) / self.seg_len).clamp(0.0, 1.0).unsqueeze(-1)
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
        return self.seg_start + (self.seg_goal - self.seg_start) * s

    def act(self, env) -> tuple[torch.Tensor, torch.Tensor]:
        """The TCP pose command (world frame) for this control step."""
        p = self.params
        dt = env.scene.config.sim_dt * env.scene.config.decimation
        t = env.episode_length_buf.float() * dt
        tcp_p, tcp_q = env._tcp_pose()
        held_p, _ = env.held_pose()
        fixed = env.fixed_pos_w  # true hole bottom on the axis (privileged)
        tip_z = fixed[:, 2] + env.geometry.fixed_height
        waiting = env.episode_length_buf < self.delay

        above = fixed.clone()
        above[:, 2] = tip_z + self.height
        start = ~waiting & ~self.started
        if start.any():
            self._start_segment(start, env, above, self.v_approach, t)
            self.started |= start

        # descend once the reference has arrived above the hole, the real part is on the axis and
        # the arm has stopped (Factory's soft gains are underdamped on the arm's real inertia:
        # passing through the tolerance on the way is not being aligned)
        align = self.phase < 2
        arrived = self.started & (t >= self.seg_t0 + self.seg_len)
        xy_err = (held_p[:, :2] - fixed[:, :2]).norm(dim=-1)
        still = env.tcp_twist_w[:, :3].norm(dim=-1) < p.settle_speed
        at_rest = align & arrived & still
        self.bias[:, :2] += torch.where(at_rest.unsqueeze(-1), p.lateral_gain * (fixed - held_p)[:, :2],
                                        torch.zeros_like(held_p[:, :2]))
        self.bias.clamp_(-p.max_bias, p.max_bias)
        self.rest_steps = torch.where(at_rest & (xy_err < p.align_tolerance), self.rest_steps + 1, 0)
        ready = self.rest_steps >= p.rest_steps
        # phase 0 -> 1: descend to the entry point, 1 mm above the fixed tip;
        # phase 1 -> 2: aligned and still again there (the descent couples into a lateral drift
        # through the arm's inertia), then insert
        entry = fixed.clone()
        entry[:, 2] = tip_z + p.entry_height
        bottom = fixed.clone()
        bottom[:, 2] = fixed[:, 2] - self.push
        go_entry = ready & (self.phase == 0)
        go_insert = ready & (self.phase == 1)
        if go_entry.any():
            self._start_segment(go_entry, env, entry, self.v_descend, t)
            self.phase[go_entry] = 1
            self.rest_steps[go_entry] = 0
        if go_insert.any():
            self._start_segment(go_insert, env, bottom, self.v_descend, t)
            self.phase[go_insert] = 2

        offset_w = quat_rotate(tcp_q, self.offset_tcp)
        cmd_pos = self._reference(t) + offset_w + self.bias

        # yaw turns to psi_ref along the approach segment (same minimum-jerk timing)
        tau = ((t - self.seg_t0) / self.seg_len).clamp(0.0, 1.0)
        s_yaw = torch.where(self.phase == 0, tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2), torch.ones_like(tau))
        s_yaw = torch.where(self.started, s_yaw, torch.zeros_like(tau))
        d_yaw = torch.atan2(torch.sin(env.task.psi_ref - self.yaw0), torch.cos(env.task.psi_ref - self.yaw0))
        self.yaw = self.yaw0 + d_yaw * s_yaw
        quat = quat_from_euler_xyz(torch.full_like(self.yaw, math.pi), torch.zeros_like(self.yaw), self.yaw)
        return cmd_pos, quat

