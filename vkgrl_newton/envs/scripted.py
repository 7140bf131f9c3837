"""A scripted demonstrator with privileged state: approach above the hole, align, descend, insert.

It commands absolute TCP poses through `AssemblyEnv.step_pose` (the same entry point KGRL uses),
one per control step. Per world and per episode it draws its own approach height, timing and
speeds, so demonstrations vary naturally (the KMP learns a distribution, not one curve).

Phases (positions are of the held part's bottom, the quantity that must reach the hole):
0. approach: a minimum-jerk move of the part's bottom to `approach_height` above the fixed tip on
   the hole axis, while the gripper yaw turns toward psi_ref (GearMesh: toward the meshing yaw
   nearest psi_ref; NutThread: held, the turn comes once the nut is on the thread, `_yaw`);
1. align: hold until the part is on the axis (`align_tolerance`) and the arm is still, or for at
   most `align_timeout_s`;
2. descend to the entry point `entry_height` above the fixed tip;
3. align again there (the descent couples into a lateral lag, see below);
4. insert: a minimum-jerk descent to `push_depth` below the hole bottom (the compliant controller
   turns the overshoot into a gentle push: 250 N/m x ~5 mm). If the part is still on top of the
   fixed part `retry_after_s` after the reference went below the tip, lift to `retry_height` and
   go back to phase 1.
While the part is above the fixed tip and the arm is still, a slow integral correction removes the
part's lateral error. Above the hole the part bottom is placed with the hand's measured
orientation (a tilted wrist would otherwise put it ~1 mm off the axis); once it is 1 mm inside,
the walls hold it on the axis: the correction decays, the lateral spring softens to 20 N/m and the
TCP is steered back above the axis, so a tilted part straightens instead of wedging.

The demonstrator's own impedance. Every command is chosen so that the env's OSC applies the
demonstrator's wrench F* = K (ref - x) - D v (K 300 N/m, D 77 N s/m, rotation 30 / 10.95), whatever
the family's gains and dead zone (`_invert_controller`); inserting, K along z is 250 N/m.

Why (measured in this env): with Factory's gains (Kp 100 N/m, Kd 20) the TCP behaves like a
~5 kg mass on that spring, damping ratio ~0.3, period ~1.5 s, and without inertia decoupling a
vertical move drags the TCP 1-2 mm sideways; the chamfer catches ~0.8 mm, so open-loop moves
miss the hole about half the time. The extra damping, the stillness gates, the slow integral
correction and the retry make it reliable. Feeding the swaying pose back faster (proportional or
fast integral gains at 15 Hz) sustained a 1-2 mm limit cycle. Forge's force dead zone (up to 5 N
and 1 N m, swallowing the damping too) lets an arm commanded like in Factory coast at a few mm/s
inside a band of up to ~12 mm and never settle (Forge success 0.0-0.03 before the inversion).
In Forge 4D the wrist still floats within its torque dead zone (roll and pitch are not
commandable) and tilts the peg up to ~3 degrees: before the measured-orientation placement and the
soft in-hole spring, that missed the chamfer or wedged the peg in 4 of 32 episodes (0.875).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..assets_usd.dimensions import GEAR_TEETH
from ..rotations import (euler_xyz_from_quat, quat_conjugate, quat_exp, quat_from_euler_xyz, quat_log, quat_mul,
                         quat_rotate)

__all__ = ["ScriptedInserter", "ScriptedParams", "DEMONSTRATOR_VERSION"]

# Bumped whenever the demonstrator's behaviour changes (its phases, parameters or random draws):
# the cached demonstrations and image sets are keyed by it, so a changed demonstrator never
# reuses what the old one recorded.
DEMONSTRATOR_VERSION = 1

GEAR_TEETH_MEDIUM = GEAR_TEETH["medium"]  # the held gear's teeth: its yaw symmetry

APPROACH, ALIGN, DESCEND, ALIGN_ENTRY, INSERT = range(5)


@dataclass(frozen=True)
class ScriptedParams:
    approach_height: tuple[float, float] = (0.004, 0.010)  # m above the fixed tip, part bottom
    approach_time_s: tuple[float, float] = (1.2, 1.6)  # s, minimum-jerk approach (yaw shares it)
    descend_speed: tuple[float, float] = (0.008, 0.012)  # m/s, mean speed down to the entry point
    insert_speed: tuple[float, float] = (0.010, 0.015)  # m/s, mean speed of the insertion
    push_depth: tuple[float, float] = (0.004, 0.006)  # m below the hole bottom
    entry_height: float = 0.002  # m above the fixed tip
    align_tolerance: float = 0.0004  # m, lateral error of the part bottom counted as aligned
    settle_speed: float = 0.002  # m/s, TCP speed below which the arm counts as still
    align_timeout_s: float = 1.0  # s in an align phase before going on anyway
    # N/m, the demonstrator's TCP stiffness: 3x Factory's Kp, so that the ~0.2-1 N the arm's own
    # dynamics leave uncompensated (null-space posture, the wrist floating in Forge's torque dead
    # zone) hold the part ~1 mm off the axis instead of ~2-3 mm; Forge 4D 61/64 vs 28/32 at 100
    stiffness: float = 300.0
    damping: float = 77.0  # N s/m, critical for the ~5 kg the TCP behaves like (Factory's Kd 20: zeta ~0.3)
    insert_stiffness_z: float = 250.0  # N/m along z while inserting: pushes a slightly tilted peg
    # (Forge 4D: the wrist floats within its torque dead zone, ~3 degrees) past the wall friction
    rot_stiffness: float = 30.0  # N m/rad (Factory's)
    rot_damping: float = 10.95  # N m s/rad (Factory's)
    lateral_gain: float = 0.03  # per control step, integral gain on the part's lateral error
    correction_speed_gate: float = 0.004  # m/s, TCP speed below which the correction integrates
    max_bias: float = 0.004  # m, bound on the integral correction
    # once the part is 1 mm into the hole: a soft lateral spring (N/m on x, y) and the integral
    # correction released (factor per control step), so a tilted part can straighten in the hole
    inside_lateral_stiffness: float = 20.0
    bias_release: float = 0.8
    tilt_feedforward: bool = True  # place the part bottom with the hand's measured orientation
    retry_after_s: float = 0.6  # s the part may rest on the fixed tip before a retry
    retry_height: float = 0.003  # m above the fixed tip
    start_delay_steps: tuple[int, int] = (0, 4)  # control steps of waiting at the start
    turn_time_s: tuple[float, float] = (3.0, 4.0)  # NutThread: s of the screwing turn to psi_ref


class ScriptedInserter:
    """Batched over the env's worlds. Call `reset(env)` after each env reset (`reset(env, mask)` after a
    reset of some worlds), then `act(env)`."""

    def __init__(self, params: ScriptedParams | None = None, seed: int = 0):
        self.params = params or ScriptedParams()
        self.seed = seed
        self._gen = None

    def _u(self, n, lo_hi, device):
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(n, device=device, generator=self._gen)

    def reset(self, env, mask: torch.Tensor | None = None) -> None:
        """A new episode in every world, or in the worlds of `mask` (E,) bool alone: the others keep their
        episode's state (the draws are made for all worlds either way, so the random stream is the same)."""
        old = dict(vars(self)) if mask is not None and self._gen is not None else None
        self._reset_all(env)
        if old is not None:
            for name, value in vars(self).items():
                if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == env.num_envs:
                    setattr(self, name, torch.where(mask.view(-1, *([1] * (value.ndim - 1))), value, old[name]))

    def _reset_all(self, env) -> None:
        n, dev = env.num_envs, env.tdev
        if self._gen is None:
            self._gen = torch.Generator(device=dev).manual_seed(self.seed)
        p = self.params
        self.height = self._u(n, p.approach_height, dev)
        self.t_approach = self._u(n, p.approach_time_s, dev)
        self.v_descend = self._u(n, p.descend_speed, dev)
        self.v_insert = self._u(n, p.insert_speed, dev)
        self.push = self._u(n, p.push_depth, dev)
        lo, hi = p.start_delay_steps
        self.delay = torch.randint(lo, hi + 1, (n,), device=dev, generator=self._gen)
        self.phase = torch.full((n,), APPROACH, dtype=torch.long, device=dev)
        self.retries = torch.zeros(n, dtype=torch.long, device=dev)
        tcp_p, tcp_q = env.tcp_pose()
        held_p, _ = env.held_pose()
        # rigid grasp offset (TCP - part bottom) in the TCP frame, measured once: the env's reset
        # lets the grasp settle, and the part does not slip measurably in the 20 N grip
        self.offset_tcp = quat_rotate(quat_conjugate(tcp_q), tcp_p - held_p)
        self.bias = torch.zeros(n, 3, device=dev)
        self.seg_start = held_p.clone()  # minimum-jerk segment of the part bottom's reference
        self.seg_goal = held_p.clone()
        self.seg_t0 = torch.zeros(n, device=dev)
        self.seg_len = torch.ones(n, device=dev)
        self.phase_t0 = torch.zeros(n, device=dev)
        self.started = torch.zeros(n, dtype=torch.bool, device=dev)
        self.inside = torch.zeros(n, dtype=torch.bool, device=dev)
        _, _, yaw = euler_xyz_from_quat(tcp_q)
        self.yaw0 = yaw.clone()
        _, _, held_yaw = euler_xyz_from_quat(env.held_pose()[1])
        d = held_yaw - yaw
        self.held_yaw_offset = torch.atan2(torch.sin(d), torch.cos(d))
        # drawn for NutThread only: an extra draw would shift the other tasks' random streams (their
        # recorded demonstrations and image sets stay reproducible per seed)
        self.t_turn = (self._u(n, p.turn_time_s, dev) if env.cfg.task == "NutThread"
                       else torch.full((n,), p.turn_time_s[0], device=dev))
        self.turn_t0 = torch.full((n,), -1.0, device=dev)

    def _start_segment(self, mask, goal, duration, t):
        # torch.where, not boolean indexing: no device-to-host sync per control step on CUDA
        m = mask.unsqueeze(-1)
        self.seg_start = torch.where(m, self._reference(t), self.seg_start)
        self.seg_goal = torch.where(m, goal, self.seg_goal)
        self.seg_t0 = torch.where(mask, t, self.seg_t0)
        self.seg_len = torch.where(mask, duration.clamp_min(0.2), self.seg_len)

    def _progress(self, t):
        tau = ((t - self.seg_t0) / self.seg_len).clamp(0.0, 1.0)
        return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)  # minimum jerk

    def _reference(self, t):
        return self.seg_start + (self.seg_goal - self.seg_start) * self._progress(t).unsqueeze(-1)

    def _enter(self, mask, phase, t, goal=None, speed=None):
        """Switch the masked worlds to `phase`; with a goal, start a segment toward it."""
        if goal is not None:
            dist = (goal - self._reference(t)).norm(dim=-1)
            self._start_segment(mask, goal, dist / speed, t)
        self.phase = torch.where(mask, torch.full_like(self.phase, phase), self.phase)
        self.phase_t0 = torch.where(mask, t, self.phase_t0)

    def act(self, env) -> tuple[torch.Tensor, torch.Tensor]:
        """The TCP pose command (world frame) for this control step."""
        p = self.params
        dt = env.scene.config.sim_dt * env.scene.config.decimation
        t = env.episode_length_buf.float() * dt
        held_p, _ = env.held_pose()
        fixed = env.target_base_w  # where the held origin goes: the hole bottom, gear seat, nut target (privileged)
        tip_z = env.fixed_tip_w[:, 2] - env.geometry.held_bottom  # held origin with its bottom at the fixed tip

        def on_axis(height):
            goal = fixed.clone()
            goal[:, 2] = tip_z + height
            return goal

        start = ~self.started & (env.episode_length_buf >= self.delay)
        self._start_segment(start, on_axis(self.height), self.t_approach, t)
        self.started |= start
        arrived = t >= self.seg_t0 + self.seg_len
        lateral = (fixed - held_p)[:, :2]
        ready = arrived & (
            ((lateral.norm(dim=-1) < p.align_tolerance) & (env.tcp_twist_w[:, :3].norm(dim=-1) < p.settle_speed))
            | (t - self.phase_t0 >= p.align_timeout_s)
        )
        # transitions, each from the phase the world was in at the start of this step
        phase = self.phase.clone()
        self._enter(self.started & (phase == APPROACH) & arrived, ALIGN, t)
        self._enter((phase == ALIGN) & ready, DESCEND, t, on_axis(torch.full_like(tip_z, p.entry_height)),
                    self.v_descend)
        self._enter((phase == DESCEND) & arrived, ALIGN_ENTRY, t)
        bottom = fixed.clone()
        bottom[:, 2] = fixed[:, 2] - self.push
        self._enter((phase == ALIGN_ENTRY) & ready, INSERT, t, bottom, self.v_insert)
        # a part still resting on the fixed tip after the reference went below it: lift and retry
        below_at = self.seg_t0 + self.seg_len * 0.5
        stuck = (phase == INSERT) & (held_p[:, 2] > tip_z - 0.0005) & (t > below_at + p.retry_after_s)
        self.retries += stuck.long()
        self.seg_start = torch.where(stuck.unsqueeze(-1), held_p, self.seg_start)
        self.seg_goal = torch.where(stuck.unsqueeze(-1), held_p, self.seg_goal)
        self._enter(stuck, ALIGN, t, on_axis(torch.full_like(tip_z, p.retry_height)), self.v_descend)

        # lateral correction while the part is above the fixed tip
        correcting = (self.phase >= ALIGN) & (held_p[:, 2] > tip_z)
        still = env.tcp_twist_w[:, :3].norm(dim=-1) < p.correction_speed_gate
        self.bias[:, :2] += p.lateral_gain * lateral * (correcting & still).unsqueeze(-1)
        self.bias.clamp_(-p.max_bias, p.max_bias)
        # in the hole the walls hold the part bottom on the axis; a correction that put a tilted
        # part's bottom on the axis would now hold the TCP off it and keep the part tilted
        inside = (self.phase == INSERT) & (held_p[:, 2] < tip_z - 0.001)
        self.inside = inside
        self.bias *= torch.where(inside, p.bias_release, 1.0).unsqueeze(-1)

        yaw = self._yaw(env, t, held_p, tip_z)
        quat = quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw)
        # the grasp offset turned by the hand's measured orientation: a wrist tilted inside Forge's
        # torque dead zone (roll and pitch not commandable in 4D) would otherwise put the part bottom
        # ~1 mm off the axis; in the hole, by the commanded one, so the TCP goes back above the axis
        offset_q = torch.where(self.inside.unsqueeze(-1), quat, env.tcp_pose()[1]) if p.tilt_feedforward else quat
        cmd_pos = self._reference(t) + quat_rotate(offset_q, self.offset_tcp) + self.bias
        return self._invert_controller(env, cmd_pos, quat)

    def _yaw(self, env, t, held_p, tip_z):
        """The gripper yaw this step.

        PegInsert: to psi_ref along the approach segment (same minimum-jerk timing). GearMesh: to
        the yaw nearest psi_ref at which the held gear's teeth face the fixed gears' gaps (its
        yaw relative to the base a multiple of the tooth pitch; the in-hand yaw offset is
        measured at reset). NutThread: held during the approach; once the nut is on the thread
        (its bottom 1 mm under the bolt tip), a minimum-jerk turn to psi_ref over `turn_time_s`,
        clockwise, which screws it in.
        """
        task = env.cfg.task
        if task == "NutThread":
            on_thread = (self.phase == INSERT) & (held_p[:, 2] < tip_z - 0.001) & (self.turn_t0 < 0)
            self.turn_t0 = torch.where(on_thread, t, self.turn_t0)
            tau = torch.where(self.turn_t0 >= 0, ((t - self.turn_t0) / self.t_turn).clamp(0.0, 1.0),
                              torch.zeros_like(t))
            s_yaw = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
            return self.yaw0 + (env.task.psi_ref - self.yaw0) * s_yaw  # no wrap: the turn is clockwise
        goal = torch.full_like(self.yaw0, env.task.psi_ref)
        if task == "GearMesh":
            pitch = 2 * math.pi / GEAR_TEETH_MEDIUM
            # gear yaw = tcp yaw + held_yaw_offset; mesh when gear yaw - base yaw = k * pitch
            free = goal + self.held_yaw_offset - env.fixed_yaw
            goal = env.fixed_yaw + torch.round(free / pitch) * pitch - self.held_yaw_offset
        s_yaw = torch.where(self.phase == APPROACH, self._progress(t), torch.ones_like(t))
        s_yaw = torch.where(self.started, s_yaw, torch.zeros_like(t))
        d_yaw = torch.atan2(torch.sin(goal - self.yaw0), torch.cos(goal - self.yaw0))
        return self.yaw0 + d_yaw * s_yaw

    def _invert_controller(self, env, pos, quat):
        """The pose command under which the env's OSC applies the demonstrator's own impedance.

        Per world-frame wrench component the env applies F = dz(Kp (cmd - x) - Kd v), with Forge's
        dead zone dz(f) = f - d sign(f) for |f| > d, else 0 (d up to 5 N / 1 N m: up to ~12 mm or
        ~3 degrees of error that produce no force, and no damping either). With
        cmd = x + (F* + Kd v + sign(F*) d) / Kp the applied force is F* at the start of the control
        step (the command jumps when F* changes sign; the force does not). F* = K (ref - x) - D v
        with the demonstrator's own gains; it reads the env's Kp, Kd, d (privileged). In Factory
        (d = 0) this is cmd = ref - (D - Kd) / Kp v, i.e. damping added through the command.
        """
        p = self.params
        tcp_p, tcp_q = env.tcp_pose()
        twist = env.tcp_twist_w
        stiffness = torch.full_like(pos, p.stiffness)
        stiffness[:, 2] = torch.where(self.phase == INSERT, p.insert_stiffness_z, p.stiffness)
        stiffness[:, :2] = torch.where(self.inside.unsqueeze(-1), p.inside_lateral_stiffness, stiffness[:, :2])
        force = stiffness * (pos - tcp_p) - p.damping * twist[:, :3]
        torque = p.rot_stiffness * quat_log(quat_mul(quat, quat_conjugate(tcp_q))) - p.rot_damping * twist[:, 3:]
        wrench = torch.cat((force, torque), dim=-1)
        g = (wrench + env.kd * twist + torch.sign(wrench) * env.dead_zone) / env.kp
        go = self.started.unsqueeze(-1)
        cmd_pos = torch.where(go, tcp_p + g[:, :3], pos)
        cmd_quat = torch.where(go, quat_mul(quat_exp(g[:, 3:]), tcp_q), quat)
        return cmd_pos, cmd_quat
