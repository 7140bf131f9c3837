"""The vectorized assembly env: torch tensors in and out on the sim device, rsl-rl `VecEnv` interface.

One control step (1/15 s) = 8 physics steps of 1/120 s (thesis Table 5.1), each of `substeps`
solver substeps; the task-space impedance controller (kernels/osc.py) runs every substep on a
Jacobian and mass matrix from Newton, and the contact forces on the gripper group are reduced
(kernels/contact_forces.py) once per physics step.

Observation (thesis eq. 5.5): [s_t, tcp_pos - target_frame_pos (3), tcp_quat xyzw (4)], plus in
Forge the smoothed contact force (3, + N(0, 1 N) noise), plus an optional vision-latent slot
(`vision_latent_dim`, filled by `set_vision_latent`). Dimensions 8 / 11 (+16).

Actions, two entry points:
- `step(actions)`: a in [-1, 1]^D, D in {4, 6}, Factory's delta-pose mapping (Isaac Lab
  `factory_env.py`, `_pre_physics_step` / `_apply_action`): action EMA, then every physics step the TCP target is the current TCP pose moved by
  a * (0.02 m, 0.097 rad), kept within 5 cm of the target frame. 4D: (x, y, z, yaw), roll stays
  pi and pitch 0. 6D: all three rotations, with the tilt of the gripper axis from straight down
  bounded by `max_tilt` (default 30 degrees; this project's choice: the thesis gives no bound,
  Factory forces roll = pi and pitch = 0). NutThread (Factory's `unidirectional_rot`, applied in
  both families here): the yaw action maps to -(a + 1) / 2 in [-1, 0], clockwise only, so a zero
  action turns at half speed and -1 holds the yaw.
- `step_pose(tcp_pos_w, tcp_quat_w)`: an absolute TCP pose command (world frame), held for the
  control step; the KGRL path (KMP prior + null-space action) uses it (no yaw restriction: the
  prior turns the nut, the null-space action may turn either way).

Reward (thesis 5.2): Factory 4 per step in the success state (held part centred on its target
within 2.5 mm and seated within 1 mm, the nut within 0.75 mm and with the TCP yaw below 0,
Isaac Lab's `_get_curr_successes` and `TASK_GEOMETRY`); Forge adds -0.001 (|dp|/0.02 + sum |d angle|/0.097)
(eqs. 5.11-5.18, dp = tcp - command) and -max(0, |f_smooth| - 7.5 N) (eq. 5.19).

Forge family (`randomize_dynamics`, on by default for forge; Isaac Lab `forge_env.py`,
`forge_env_cfg.py`): Kp (565, 28) scaled per
component by [0.71, 1.41], Kd = 2 sqrt(Kp), action scales and EMA factor randomized, a force /
torque dead zone U(0, 1) x (5 N, 1 N m) drawn at reset and again every 2 s, held-part mass +-5 g
per reset. Not randomized here: friction (Isaac Lab's `FactoryEnv._set_default_dynamics_parameters` overwrites its
friction events) and the contact-penalty threshold (Forge draws U(5, 10) N; the thesis fixes 7.5 N).

Episodes last the task's length (150 steps = 10 s; NutThread 225 = 15 s) and end by time-out
only, all worlds together (Factory). A physics blow-up (NaN, runaway velocity, a part thrown
away) in one world resets that world alone (its grasp settled like any reset's, the other worlds
untouched by it) and is counted in `extras["log"]["/physics_resets"]`. A reset whose IK does not
converge is counted in `extras["log"]["/ik_failures"]` and `ik_failures_total` (`_reset_worlds`);
a substep whose contacts overflow the solver's buffers (SimConfig.nconmax / njmax) in
`extras["log"]["/contact_overflows"]` and `contact_overflows_total`, with a warning the first time
(counted per world and substep; the contact buffers are shared by all worlds, so their overflow
counts once for every world).

The physics of a control step runs in sim/physics.py's PhysicsStepper, by default as one captured
Warp graph (EnvConfig.graph; False: the eager launches, bitwise equal, the tests' reference).

`step` and `step_pose` return (obs, rewards, dones, extras), rsl-rl's contract: dones = time-out
or blow-up, observations already those after the auto-reset. extras: "time_outs" (E,) bool;
"physics_resets" (E,) bool, the worlds reset after a blow-up (their transition is not the
policy's doing; learners drop it); "final_observations", only on steps where some world ended,
the observations before the reset (time-outs bootstrap from them); "log"; "episode" (metrics
of the timed-out worlds' episodes, less any world that blew up on that last step).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import gymnasium as gym
import numpy as np
import torch
import warp as wp
from rsl_rl.env import VecEnv
from tensordict import TensorDict

import newton

from ..assets_usd.dimensions import BOLT_TIP_HEIGHT, GEAR_BASE_HEIGHT, GEAR_HEIGHT, GEAR_HUB_RADIUS, GEAR_MEDIUM_X
from ..assets_usd.dimensions import FIXED_ASSET_NOMINAL_POS as FIXED_ASSET_NOMINAL  # the authored fixed-asset position
from ..assets_usd.dimensions import HOLE_DEPTH, NUT_ACROSS_FLATS, PEG_DIAMETER, THREAD_PITCH
from ..kernels.contact_forces import contact_force_reset
from ..kernels.kmp_horizon import vec6f
from ..rotations import euler_xyz_from_quat, quat_conjugate, quat_exp, quat_from_euler_xyz, quat_log, quat_mul, quat_rotate
from ..runtime import torch_device
from ..sim.physics import ActionBuffers, ControllerBuffers, ForceBuffers, PhysicsStepper
from ..sim.scene import ARM_DOFS, FACTORY_NULL_JOINTS, FACTORY_RESET_JOINTS, Scene, SimConfig, build_scene
from ..tasks import ACTION_DIMS, CONTROL_DT, FAMILIES, TARGET_OBS_NOISE, get_task, observation_dim  # noqa: F401  (observation_dim: a name of this module too)

__all__ = ["EnvConfig", "AssemblyEnv", "FAMILIES", "ACTION_DIMS", "TASK_GEOMETRY"]

# Factory / Forge controller (Isaac Lab `factory_env_cfg.py`, `factory_control.py`, `forge_env_cfg.py`)
FACTORY_KP = (100.0, 100.0, 100.0, 30.0, 30.0, 30.0)
FORGE_KP = (565.0, 565.0, 565.0, 28.0, 28.0, 28.0)
RESET_KP = (300.0, 300.0, 300.0, 20.0, 20.0, 20.0)
POS_ACTION_SCALE = 0.02  # m per step at |a| = 1
ROT_ACTION_SCALE = 0.097  # rad per step at |a| = 1
POS_ACTION_BOUND = 0.05  # m, target kept within this box around the target frame
FACTORY_EMA = 0.2
# Forge dynamics randomization (`forge_env_cfg.py`, `forge_events.py`) beyond the gains: the force/torque dead zone is drawn
# again every 2 s (30 control steps), and the held part's mass moves by up to 5 g at each reset
FORGE_DEAD_ZONE = (5.0, 5.0, 5.0, 1.0, 1.0, 1.0)  # N, N m at U = 1
FORGE_DEAD_ZONE_PERIOD_STEPS = 30
FORGE_HELD_MASS_NOISE = 0.005  # kg
# Null-space posture gains. Factory uses 10 / 2 sqrt(10); Isaac Lab's Newton port of Factory
# disables the term, and so does this env by default: measured here, the null-space torque moved a
# zero-action TCP by 5.8 mm in 5 control steps (the target follows the current pose every physics
# step, so any leak of null-space torque into the task space accumulates), versus 0.0 mm without.
NULL_KP, NULL_KD = 0.0, 2.0 * math.sqrt(10.0)
TORQUE_LIMIT = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
FORCE_OBS_NOISE = 1.0  # N, Forge
CONTACT_PENALTY_THRESHOLD = 7.5  # N, eq. 5.19
SUCCESS_REWARD = 4.0
PRIVILEGED_OBS_DIM = 16  # AssemblyEnv.privileged_state's width: the `critic` group's beyond `policy`
# Physics steps of gripper closing at reset. Factory uses 30 (0.25 s); here the pads (Menagerie's
# geometry, self-centring) then keep centring a peg placed off-centre by the in-hand noise for up to
# another second: measured, the part moved up to 2.3 mm in the grasp during the first 15 control
# steps of an episode after a 30-step settle. 150 steps (1.25 s) start every episode settled.
GRIP_SETTLE_STEPS = 150
MAX_LIN_VEL, MAX_ANG_VEL = 20.0, 200.0  # beyond these a world counts as blown up
# reset IK (damped least squares): draws of the hand pose tried per world, and when it has converged
IK_ATTEMPTS = 4
IK_POS_TOLERANCE, IK_ROT_TOLERANCE = 1e-3, 1e-2  # m, rad


@dataclass(frozen=True)
class TaskGeometry:
    """Held/fixed part facts the env needs (Isaac Lab `factory_tasks_cfg.py`: assets, success thresholds).

    Frames: the held part's origin is on its axis (peg and nut: bottom face; gear: the base
    plate's bottom level, 5 mm under its teeth, Factory's "assembled coordinates"); the target
    base is where that origin is when assembled, `target_offset` in the fixed part's (yawed)
    frame; the fixed tip (observation and action frame) is (target_offset x, y, fixed_height).
    """

    fixed_height: float  # m, fixed tip above the fixed part's origin
    held_in_tcp: float  # m, held origin below the TCP along the gripper axis
    held_pos_noise: tuple[float, float, float]  # in-hand noise half-ranges, held frame
    success_z: float  # m, seated threshold (held origin above the target base)
    success_xy: float  # m, centring threshold
    finger_open: float  # m per finger at reset
    finger_grip_target: float  # m, drive target giving ~20 N squeeze at contact
    target_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, target base in the fixed frame
    held_bottom: float = 0.0  # m, the held part's lowest face above its origin
    # Factory's NutThread: success also needs the TCP yaw (XYZ Euler, wrapped to (-125, 235] deg)
    # below this (rad), i.e. the nut turned; None: no yaw condition
    success_tcp_yaw_max: float | None = None
    unidirectional_yaw: bool = False  # Factory's NutThread: the yaw action turns clockwise only


# Finger pads touch a round part of radius r at q = r - 0.883 mm (measured on the 7.986 mm peg:
# q = 3.11 mm); the drive target 10 mm further in squeezes with ke 2000 N/m * 10 mm = 20 N.
# Fingers open to Factory's held diameter / 2 * 1.25 (`factory_env.py`, `_full_reset`).
_PAD = 0.000883
# Apart from tasks.py's TaskSpec (the thesis's per-task tables, plain data importing nothing of the package): these
# are the env's grasp and success facts in its own frames, derived from the authored parts (assets_usd.dimensions)
# and this gripper's measured pads and drives, read through the env (env.geometry); its keys: the tasks it simulates.
TASK_GEOMETRY = {
    # the fingertips grip the peg's top 17.608 mm (Factory: peg length - fingerpad length, 0.032392);
    # Factory's success: seated within 0.04 of the fixed part's height (success_threshold, factory_tasks_cfg.py)
    "PegInsert": TaskGeometry(
        fixed_height=HOLE_DEPTH, held_in_tcp=0.032392, held_pos_noise=(0.003, 0.0, 0.003), success_z=0.04 * HOLE_DEPTH,
        success_xy=0.0025, finger_open=0.00499, finger_grip_target=PEG_DIAMETER / 2 - _PAD - 0.010),
    # the fingers hold the gear's hub (r 10 mm, z 25..45 mm): TCP 29 mm above the origin, so the
    # pads stay above the teeth (z <= 25 mm) over the +-3 mm in-hand noise; fingers open to Factory's
    # gear "diameter" 0.03; target base on the medium shaft, the fixed tip at its top
    "GearMesh": TaskGeometry(
        fixed_height=GEAR_BASE_HEIGHT + GEAR_HEIGHT, held_in_tcp=0.029, held_pos_noise=(0.003, 0.0, 0.003),
        success_z=0.05 * GEAR_HEIGHT, success_xy=0.0025, finger_open=0.03 / 2 * 1.25,
        finger_grip_target=GEAR_HUB_RADIUS - _PAD - 0.010, target_offset=(GEAR_MEDIUM_X, 0.0, 0.0),
        held_bottom=GEAR_BASE_HEIGHT),
    # the nut's bottom face level with the fingertips; the pads close on two flats;
    # target base 1.5 pitches under the bolt tip, success within 0.375 pitch of it
    "NutThread": TaskGeometry(
        fixed_height=BOLT_TIP_HEIGHT, held_in_tcp=0.0, held_pos_noise=(0.0, 0.003, 0.003),
        success_z=0.375 * THREAD_PITCH, success_xy=0.0025, finger_open=NUT_ACROSS_FLATS / 2 * 1.25,
        finger_grip_target=NUT_ACROSS_FLATS / 2 - _PAD - 0.010,
        target_offset=(0.0, 0.0, BOLT_TIP_HEIGHT - 1.5 * THREAD_PITCH), success_tcp_yaw_max=0.0,
        unidirectional_yaw=True),
}


@dataclass(frozen=True)
class EnvConfig:
    task: str = "PegInsert"
    family: str = "factory"  # "factory" | "forge"
    action_dim: int = 6  # 4 (xyz + yaw) | 6 (xyz + roll, pitch, yaw)
    num_envs: int = 16
    device: str | None = None
    seed: int = 0
    randomize_dynamics: bool | None = None  # Forge's dynamics randomization; None: on for forge
    vision_latent_dim: int = 0  # 0: no vision slot; 16 for the thesis's VAE latent
    max_tilt: float = math.radians(30.0)  # 6D only: bound on the gripper axis tilt from straight down
    # the `critic` observation group beside `policy` (rsl-rl's and Isaac Lab's convention): the policy's
    # observation plus privileged state no policy observes (`privileged_state`), for an asymmetric critic
    privileged_obs: bool = False
    # what an actor needs to find a hole it cannot see (issue 40; deviations from eq. 5.5, off in the thesis):
    # the TCP's linear and angular velocity (world; Factory's finite differences over the control step)
    # and, in Factory, the smoothed contact force with Forge's noise (the KGRL paper's actor reads the wrench)
    tcp_velocity_obs: bool = False
    force_obs: bool = False
    # the physics of a control step as one captured Warp graph (sim/physics.py); False: eager
    # launches, the reference the graph is tested against (bitwise equal)
    graph: bool = True
    sim: SimConfig = field(default_factory=SimConfig)

    def __post_init__(self):
        get_task(self.task)
        if self.task not in TASK_GEOMETRY:
            raise ValueError(f"task {self.task!r} is not simulated yet; available: {sorted(TASK_GEOMETRY)}")
        if self.family not in FAMILIES:
            raise ValueError(f"family must be one of {FAMILIES}, got {self.family!r}")
        if self.action_dim not in ACTION_DIMS:
            raise ValueError(f"action_dim must be one of {ACTION_DIMS}, got {self.action_dim!r}")
        if not isinstance(self.num_envs, int) or self.num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {self.num_envs!r}")
        if self.force_obs and self.family == "forge":
            raise ValueError("force_obs is Factory's: the Forge observation holds the force already")
        if self.vision_latent_dim < 0:
            raise ValueError(f"vision_latent_dim must be >= 0, got {self.vision_latent_dim!r}")
        if not 0.0 < self.max_tilt < math.pi / 2:
            raise ValueError(f"max_tilt must be in (0, pi/2) rad, got {self.max_tilt!r}")

    @property
    def dynamics_randomized(self) -> bool:
        return self.family == "forge" if self.randomize_dynamics is None else bool(self.randomize_dynamics)


def _vec(t: torch.Tensor, dtype):
    return wp.from_torch(t.contiguous(), dtype=dtype)


class AssemblyEnv(VecEnv):
    """Batched PegInsert, GearMesh and NutThread in Newton; see the module docstring."""

    def __init__(self, cfg: EnvConfig, scene: Scene | None = None):
        self.cfg = cfg
        self.task = get_task(cfg.task)
        self.geometry = TASK_GEOMETRY[cfg.task]
        sim_cfg = replace(cfg.sim, num_worlds=cfg.num_envs, device=cfg.device or cfg.sim.device)
        if scene is None:
            scene = build_scene(cfg.task, sim_cfg)
        elif scene.num_worlds != cfg.num_envs or scene.task != cfg.task:
            raise ValueError(
                f"scene has {scene.num_worlds} worlds of {scene.task!r}, config asks {cfg.num_envs} of {cfg.task!r}"
            )
        self.scene = scene
        self.model = scene.model
        self.device = scene.device
        self.tdev = torch_device(self.device)  # the torch device sharing the Warp device's memory (cuda:1 -> cuda:1)
        self.num_envs = cfg.num_envs
        self.num_actions = cfg.action_dim
        self.max_episode_length = self.task.episode_steps
        self.generator = torch.Generator(device=self.tdev).manual_seed(cfg.seed)
        self.substeps = scene.config.substeps
        self.substep_dt = scene.config.substep_dt

        E, tdev = self.num_envs, self.tdev

        # controller buffers (torch tensors with warp views of the same memory)
        z = lambda *shape: torch.zeros(*shape, dtype=torch.float32, device=tdev)  # noqa: E731
        self.tcp_pos_w, self.tcp_quat_w = z(E, 3), z(E, 4)
        self.tcp_twist_w, self.wrench_w = z(E, 6), z(E, 6)
        self.cmd_pos_w, self.cmd_quat_w = z(E, 3), z(E, 4)
        self.kp, self.kd, self.dead_zone = z(E, 6), z(E, 6), z(E, 6)
        self.q_null = torch.tensor(FACTORY_NULL_JOINTS, dtype=torch.float32, device=tdev)
        self.torque_limit = torch.tensor(TORQUE_LIMIT, dtype=torch.float32, device=tdev)
        self._wp = {
            "tcp_pos_w": _vec(self.tcp_pos_w, wp.vec3), "tcp_quat_w": _vec(self.tcp_quat_w, wp.quat),
            "tcp_twist_w": _vec(self.tcp_twist_w, wp.spatial_vector), "wrench_w": _vec(self.wrench_w, vec6f),
            "cmd_pos_w": _vec(self.cmd_pos_w, wp.vec3), "cmd_quat_w": _vec(self.cmd_quat_w, wp.quat),
            "kp": _vec(self.kp, vec6f), "kd": _vec(self.kd, vec6f), "dead_zone": _vec(self.dead_zone, vec6f),
            "q_null": _vec(self.q_null, wp.float32), "torque_limit": _vec(self.torque_limit, wp.float32),
        }
        # contact-force buffers
        self.interaction_force_w, self.force_smoothed_w = z(E, 3), z(E, 3)
        self.force_norm_sum, self.force_peak = z(E), z(E)
        self.force_count = torch.zeros(E, dtype=torch.int32, device=tdev)
        self._wp.update({
            "interaction_force_w": _vec(self.interaction_force_w, wp.vec3),
            "force_smoothed_w": _vec(self.force_smoothed_w, wp.vec3),
            "force_norm_sum": _vec(self.force_norm_sum, wp.float32), "force_peak": _vec(self.force_peak, wp.float32),
            "force_count": _vec(self.force_count, wp.int32),
        })

        # task / episode buffers
        self.origins = torch.tensor(scene.env_origins, dtype=torch.float32, device=tdev)
        self.fixed_pos_w, self.fixed_yaw = z(E, 3), z(E)  # fixed part origin (world) and yaw
        self.target_frame_pos_w = z(E, 3)  # fixed tip + observation noise: the frame of obs and actions
        self.fixed_tip_w = z(E, 3)  # fixed tip, no noise
        self.target_base_w = z(E, 3)  # where the held origin is when assembled
        self.ref_quat_w = quat_from_euler_xyz(torch.tensor(math.pi), torch.tensor(0.0),
                                              torch.tensor(self.task.psi_ref)).float().to(tdev).expand(E, 4).contiguous()
        self.actions_applied = z(E, cfg.action_dim)
        self.ema = torch.full((E,), FACTORY_EMA, device=tdev)
        self.pos_scale = torch.full((E, 3), POS_ACTION_SCALE, device=tdev)
        self.rot_scale = torch.full((E, 3), ROT_ACTION_SCALE, device=tdev)
        self.episode_length_buf = torch.zeros(E, dtype=torch.long, device=tdev)
        self.step_index = torch.zeros(E, dtype=torch.int32, device=tdev)  # int32 copy for Warp kernels
        self.success = torch.zeros(E, dtype=torch.bool, device=tdev)
        self.success_any = torch.zeros(E, dtype=torch.bool, device=tdev)
        # per-world outcome of the last finished episode, kept past the auto-reset (demo recording)
        self.last_episode_success_any = torch.zeros(E, dtype=torch.bool, device=tdev)
        self.first_success_step = torch.full((E,), -1, dtype=torch.long, device=tdev)
        self.episode_reward = z(E)
        self.vision_latent = z(E, cfg.vision_latent_dim)
        self.vision_source = None  # attach_vision
        self._state_version, self._latent_version = 0, -1  # the latent is refreshed when they differ
        self.physics_resets_total = 0
        self.ik_failures_total, self._ik_failures_step = 0, 0  # reset IK that did not converge (_reset_worlds)
        self.obs_dim = observation_dim(cfg.family, cfg.vision_latent_dim, cfg.tcp_velocity_obs, cfg.force_obs)
        # TCP velocity by finite differences (tcp_velocity_obs): the pose one control step ago
        self.tcp_linvel_w, self.tcp_angvel_w = z(E, 3), z(E, 3)
        self.prev_tcp_pos_w, self.prev_tcp_quat_w = z(E, 3), z(E, 4)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(self.obs_dim,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(cfg.action_dim,), dtype=np.float32)

        # per-world views of the flat model arrays
        self._views: dict[int, dict[str, torch.Tensor]] = {}
        self.shape_transform = wp.to_torch(self.model.shape_transform)  # (S, 7)
        self.socket_shapes = wp.to_torch(scene.socket_shapes).long()  # (E, Ns)
        self.socket_local = wp.to_torch(scene.socket_local)  # (Ns, 7)
        self.hand_idx = wp.to_torch(scene.hand_body).long()
        self.held_idx = wp.to_torch(scene.held_body).long()
        self.tcp_offset = torch.tensor(scene.tcp_offset_hand, dtype=torch.float32, device=tdev)
        self.arm_q0 = torch.tensor(FACTORY_RESET_JOINTS, dtype=torch.float32, device=tdev)
        self.joint_lower = wp.to_torch(self.model.joint_limit_lower).view(E, -1)[:, :ARM_DOFS]
        self.joint_upper = wp.to_torch(self.model.joint_limit_upper).view(E, -1)[:, :ARM_DOFS]

        # the physics of a control step (sim/physics.py), on the buffers above: eager, or one captured graph
        self.first_cmd_pos_w, self.first_cmd_quat_w = z(E, 3), z(E, 4)  # the first command of a SAC step
        wv = self._wp
        self.physics = PhysicsStepper(
            scene,
            ControllerBuffers(
                cmd_pos_w=wv["cmd_pos_w"], cmd_quat_w=wv["cmd_quat_w"], kp=wv["kp"], kd=wv["kd"],
                dead_zone=wv["dead_zone"], q_null=wv["q_null"], torque_limit=wv["torque_limit"], kp_null=NULL_KP,
                kd_null=NULL_KD, tcp_pos_w=wv["tcp_pos_w"], tcp_quat_w=wv["tcp_quat_w"],
                tcp_twist_w=wv["tcp_twist_w"], wrench_w=wv["wrench_w"]),
            ForceBuffers(
                interaction_force_w=wv["interaction_force_w"], force_smoothed_w=wv["force_smoothed_w"],
                force_norm_sum=wv["force_norm_sum"], force_peak=wv["force_peak"], force_count=wv["force_count"]),
            ActionBuffers(
                actions=wp.from_torch(self.actions_applied), pos_scale=_vec(self.pos_scale, wp.vec3),
                rot_scale=_vec(self.rot_scale, wp.vec3), target_frame_pos_w=_vec(self.target_frame_pos_w, wp.vec3),
                first_pos_w=_vec(self.first_cmd_pos_w, wp.vec3), first_quat_w=_vec(self.first_cmd_quat_w, wp.quat),
                pos_bound=POS_ACTION_BOUND, max_tilt=cfg.max_tilt, unidirectional_yaw=self.geometry.unidirectional_yaw),
            graph=cfg.graph,
        )
        # substeps per world whose contacts or constraint rows overflowed the solver's buffers
        # (SimConfig.nconmax / njmax): counted inside the graph, read with the step's one host read
        self.contact_overflow_substeps = wp.to_torch(self.physics.overflow_substeps)
        self.contact_overflows_total = 0

        # the held part's nominal mass and inertia (Forge randomizes the mass per reset)
        self.body_mass = wp.to_torch(self.model.body_mass)
        self.body_inv_mass = wp.to_torch(self.model.body_inv_mass)
        self.body_inertia = wp.to_torch(self.model.body_inertia)
        self.body_inv_inertia = wp.to_torch(self.model.body_inv_inertia)
        self.held_mass_nominal = self.body_mass[self.held_idx].clone()
        self.held_inertia_nominal = self.body_inertia[self.held_idx].clone()
        self.dead_zone_max = torch.tensor(FORGE_DEAD_ZONE, device=tdev)

        self._set_family_gains(torch.ones(E, dtype=torch.bool, device=tdev))
        self.reset()

    # the stepper swaps its two states every substep: these always name its current ones
    state_0 = property(lambda self: self.physics.state_0,
                       lambda self, s: setattr(self.physics, "state_0", s))
    state_1 = property(lambda self: self.physics.state_1,
                       lambda self, s: setattr(self.physics, "state_1", s))
    # the stepper's simulation objects, read through (never stale copies)
    solver = property(lambda self: self.physics.solver)
    pipeline = property(lambda self: self.physics.pipeline)
    contacts = property(lambda self: self.physics.contacts)
    control = property(lambda self: self.physics.control)
    jacobian = property(lambda self: self.physics.jacobian)
    # opt-in time split of eager physics (vkgrl_newton/tools/throughput.py): stage name -> seconds.
    # None (the default) costs nothing; a dict runs the steps eagerly, synchronized around each stage.
    profile = property(lambda self: self.physics.profile,
                       lambda self, p: setattr(self.physics, "profile", p))

    # ------------------------------------------------------------------------------------------
    # views and kinematics

    def _state_views(self, state) -> dict[str, torch.Tensor]:
        key = id(state)
        if key not in self._views:
            E = self.num_envs
            self._views[key] = {
                "joint_q": wp.to_torch(state.joint_q).view(E, -1),
                "joint_qd": wp.to_torch(state.joint_qd).view(E, -1),
                "body_q": wp.to_torch(state.body_q),
                "body_qd": wp.to_torch(state.body_qd),
                "joint_q_2d": state.joint_q.reshape((E, self.scene.coords_per_world)),
                "joint_qd_2d": state.joint_qd.reshape((E, self.scene.dofs_per_world)),
            }
        return self._views[key]

    def hand_pose(self, state=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Hand body position and orientation (world, xyzw), (E, 3) and (E, 4): the camera mount."""
        hand = self._state_views(state or self.state_0)["body_q"][self.hand_idx]
        return hand[:, :3], hand[:, 3:]

    def tcp_pose(self, state=None) -> tuple[torch.Tensor, torch.Tensor]:
        """TCP position and orientation (world) from the hand body pose."""
        pos, quat = self.hand_pose(state)
        return pos + quat_rotate(quat, self.tcp_offset.expand_as(pos)), quat

    def held_pose(self) -> tuple[torch.Tensor, torch.Tensor]:
        held = self._state_views(self.state_0)["body_q"][self.held_idx]
        return held[:, :3], held[:, 3:]

    # ------------------------------------------------------------------------------------------
    # gains and randomization

    def _set_family_gains(self, mask: torch.Tensor) -> None:
        n = int(mask.sum())
        if n == 0:
            return
        kp_nom = torch.tensor(FORGE_KP if self.cfg.family == "forge" else FACTORY_KP, device=self.tdev)
        kp = kp_nom.expand(n, 6).clone()
        if self.cfg.dynamics_randomized:
            # Forge (`forge_env.py`, `_reset_idx`): x (1 + U(0, noise)), inverted with p = 0.5
            kp = kp * self._forge_scale(n, 6, 0.41)
            self.pos_scale[mask] = POS_ACTION_SCALE * self._forge_scale(n, 1, 0.25).expand(n, 3)
            self.rot_scale[mask] = ROT_ACTION_SCALE * self._forge_scale(n, 1, 0.29).expand(n, 3)
            self.ema[mask] = 0.025 + 0.075 * torch.rand(n, device=self.tdev, generator=self.generator)
            self.dead_zone[mask] = torch.rand(n, 1, device=self.tdev, generator=self.generator) * self.dead_zone_max
        else:
            self.pos_scale[mask] = POS_ACTION_SCALE
            self.rot_scale[mask] = ROT_ACTION_SCALE
            self.ema[mask] = FACTORY_EMA
            self.dead_zone[mask] = 0.0
        self.kp[mask] = kp
        self.kd[mask] = 2.0 * torch.sqrt(kp)

    def _randomize_held_mass(self, mask: torch.Tensor) -> None:
        """Forge: held-part mass = nominal + U(-5, 5) g, inertia scaled with it, told to the solver."""
        idx = self.held_idx[mask]
        nominal = self.held_mass_nominal[mask]
        mass = nominal + self._uniform(idx.shape[0], -FORGE_HELD_MASS_NOISE, FORGE_HELD_MASS_NOISE)
        inertia = self.held_inertia_nominal[mask] * (mass / nominal)[:, None, None]
        self.body_mass[idx] = mass
        self.body_inv_mass[idx] = 1.0 / mass
        self.body_inertia[idx] = inertia
        self.body_inv_inertia[idx] = torch.linalg.inv(inertia)
        self.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)

    def _forge_scale(self, n: int, k: int, noise: float) -> torch.Tensor:
        s = 1.0 + noise * torch.rand(n, k, device=self.tdev, generator=self.generator)
        flip = torch.rand(n, k, device=self.tdev, generator=self.generator) < 0.5
        return torch.where(flip, 1.0 / s, s)

    def _uniform(self, n: int, lo, hi) -> torch.Tensor:
        lo = torch.as_tensor(lo, dtype=torch.float32, device=self.tdev)
        hi = torch.as_tensor(hi, dtype=torch.float32, device=self.tdev)
        return lo + (hi - lo) * torch.rand(n, *lo.shape, device=self.tdev, generator=self.generator)

    # ------------------------------------------------------------------------------------------
    # reset

    def reset(self) -> TensorDict:
        """Reset every world (Factory resets all worlds together) and return the observations."""
        self._reset_worlds(torch.ones(self.num_envs, dtype=torch.bool, device=self.tdev))
        return self.get_observations()

    def _place_fixed_part(self, mask: torch.Tensor) -> None:
        n = int(mask.sum())
        task = self.task
        pos = torch.tensor(FIXED_ASSET_NOMINAL, device=self.tdev) + self._uniform(
            n, [-a for a in task.target_pos_noise], list(task.target_pos_noise))
        yaw = self._uniform(n, task.target_yaw_range[0], task.target_yaw_range[1])
        self.fixed_pos_w[mask] = self.origins[mask] + pos
        self.fixed_yaw[mask] = yaw
        # static socket shapes: world pose = (fixed pos, yaw) * local pose
        q_yaw = quat_from_euler_xyz(torch.zeros_like(yaw), torch.zeros_like(yaw), yaw)  # (n, 4)
        local = self.socket_local  # (Ns, 7)
        ns = local.shape[0]
        p = self.fixed_pos_w[mask][:, None, :] + quat_rotate(q_yaw[:, None, :].expand(n, ns, 4),
                                                             local[None, :, :3].expand(n, ns, 3))
        q = quat_mul(q_yaw[:, None, :].expand(n, ns, 4), local[None, :, 3:].expand(n, ns, 4))
        self.shape_transform[self.socket_shapes[mask].reshape(-1)] = torch.cat((p, q), -1).reshape(-1, 7)
        geo = self.geometry
        ox, oy, oz = geo.target_offset
        local = torch.tensor(((ox, oy, oz), (ox, oy, geo.fixed_height)), device=self.tdev)  # base, tip
        world = quat_rotate(q_yaw[:, None, :].expand(n, 2, 4), local[None].expand(n, 2, 3))
        self.target_base_w[mask] = self.fixed_pos_w[mask] + world[:, 0]
        tip = self.fixed_pos_w[mask] + world[:, 1]
        self.fixed_tip_w[mask] = tip
        noise = TARGET_OBS_NOISE * torch.randn(n, 3, device=self.tdev, generator=self.generator)
        self.target_frame_pos_w[mask] = tip + noise

    def _solve_ik(self, mask: torch.Tensor, pos_w: torch.Tensor, quat_w: torch.Tensor, iters: int = 40):
        """Damped least squares (Factory's `set_pos_inverse_kinematics`, lambda 0.1) on the masked worlds' arm joints.

        Kinematic only (no physics): eval_fk + eval_jacobian on the model, joints written in place.
        Returns the final position and rotation errors (n,).
        """
        s = self.state_0
        v = self._state_views(s)
        sc = self.scene
        idx = mask.nonzero().squeeze(1)
        art = wp.to_torch(sc.robot_articulation).long()[idx]
        jac_t = wp.to_torch(self.jacobian)
        lam2 = 0.1**2
        for _ in range(iters):
            newton.eval_fk(self.model, s.joint_q, s.joint_qd, s)
            newton.eval_jacobian(self.model, s, self.jacobian, mask=sc.robot_articulation_mask)
            p, q = self.tcp_pose(s)
            p, q = p[idx], q[idx]
            e_p = pos_w - p
            e_r = _orientation_error(quat_w, q)
            err = torch.cat((e_p, e_r), -1)
            j = jac_t[art, 6 * sc.hand_link: 6 * sc.hand_link + 6, :ARM_DOFS]  # (n, 6, 7) hand COM rows
            com_w = self._hand_com_w(s)[idx]
            j = _point_jacobian(j, p - com_w)
            jjt = j @ j.transpose(1, 2) + lam2 * torch.eye(6, device=self.tdev)
            dq = (j.transpose(1, 2) @ torch.linalg.solve(jjt, err.unsqueeze(-1))).squeeze(-1)
            qa = v["joint_q"][idx, :ARM_DOFS] + dq
            v["joint_q"][idx, :ARM_DOFS] = torch.clamp(qa, self.joint_lower[idx], self.joint_upper[idx])
        newton.eval_fk(self.model, s.joint_q, s.joint_qd, s)
        p, q = self.tcp_pose(s)
        return (pos_w - p[idx]).norm(dim=-1), _orientation_error(quat_w, q[idx]).norm(dim=-1)

    def _hand_com_w(self, state) -> torch.Tensor:
        body_q = self._state_views(state)["body_q"]
        hand = body_q[self.hand_idx]
        com = wp.to_torch(self.model.body_com)[self.hand_idx]
        return hand[:, :3] + quat_rotate(hand[:, 3:], com)

    def _reset_worlds(self, mask: torch.Tensor) -> None:
        """Factory's reset of the masked worlds (Isaac Lab `factory_env.py`, `randomize_initial_state`).

        Fixed part placed and the target frame drawn; hand above the fixed tip by IK (up to 4
        draws; a world whose IK has not converged after the 4th keeps the last iterate, a hand
        pose that may be off the drawn one by more than 1 mm / 0.01 rad: it is counted in
        `ik_failures_total` and in the step's `log["/ik_failures"]`, and its episode runs from
        there); fingers open, held part placed in the hand, then the grasp settles
        (`_settle_grasp`) whichever worlds reset: the others are not advanced by it.
        """
        n = int(mask.sum())
        if n == 0:
            return
        self._state_version += 1  # the state is written directly below
        E = self.num_envs
        v = self._state_views(self.state_0)
        task, geo = self.task, self.geometry
        self._place_fixed_part(mask)
        self._set_family_gains(mask)
        if self.cfg.dynamics_randomized:
            self._randomize_held_mass(mask)

        # hand target above the fixed tip (Factory's `hand_init_pos`), IK with retries from the reset posture
        tip = self.fixed_tip_w[mask]
        todo = torch.ones(n, dtype=torch.bool, device=self.tdev)
        hand_pos = torch.zeros(n, 3, device=self.tdev)
        hand_quat = torch.zeros(n, 4, device=self.tdev)
        midx = mask.nonzero().squeeze(1)
        for attempt in range(IK_ATTEMPTS):
            k = int(todo.sum())
            noise = self._uniform(k, [-a for a in task.ee_pos_noise], list(task.ee_pos_noise))
            hand_pos[todo] = tip[todo] + torch.tensor((0.0, 0.0, task.hand_init_height), device=self.tdev) + noise
            yaw = self._uniform(k, task.ee_yaw_range[0], task.ee_yaw_range[1])
            hand_quat[todo] = quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw)
            sub = torch.zeros(E, dtype=torch.bool, device=self.tdev)
            sub[midx[todo]] = True
            v["joint_q"][sub, :ARM_DOFS] = self.arm_q0
            e_p, e_r = self._solve_ik(sub, hand_pos[todo], hand_quat[todo])
            ok = (e_p < IK_POS_TOLERANCE) & (e_r < IK_ROT_TOLERANCE)
            still = todo.clone()
            still[todo] = ~ok
            todo = still
            if not todo.any():
                break
        failed = int(todo.sum())
        self.ik_failures_total += failed
        self._ik_failures_step += failed

        # MuJoCo-Warp warm-starts each solve from the last accelerations: a world that blew up
        # keeps NaN there and would blow up again on every step, so clear it for reset worlds
        mjw_data = getattr(self.solver, "mjw_data", None)
        for name in ("qacc_warmstart", "qacc"):
            arr = getattr(mjw_data, name, None) if mjw_data is not None else None
            if arr is not None and arr.shape[0] == E:
                wp.to_torch(arr)[mask] = 0.0

        # fingers open, held part in the hand
        v["joint_q"][mask, ARM_DOFS:ARM_DOFS + 2] = geo.finger_open
        v["joint_qd"][mask] = 0.0
        self._place_held_part(mask)
        newton.eval_fk(self.model, self.state_0.joint_q, self.state_0.joint_qd, self.state_0)
        self.state_1.assign(self.state_0)

        # controller holds the current TCP pose while the fingers close; episode buffers
        tcp_p, tcp_q = self.tcp_pose()
        self.cmd_pos_w[mask] = tcp_p[mask]
        self.cmd_quat_w[mask] = tcp_q[mask]
        self.actions_applied[mask] = 0.0
        self.control_finger_targets(mask, geo.finger_grip_target)
        self._settle_grasp(mask)
        contact_force_reset(
            reset_mask=wp.from_torch(mask), force_smoothed_w=self._wp["force_smoothed_w"],
            force_norm_sum=self._wp["force_norm_sum"], force_sample_count=self._wp["force_count"],
            force_peak=self._wp["force_peak"],
        )
        self.episode_length_buf[mask] = 0
        self.step_index[mask] = 0
        tcp_p, tcp_q = self.tcp_pose()  # (after the grasp settled) an episode starts at rest
        self.prev_tcp_pos_w[mask], self.prev_tcp_quat_w[mask] = tcp_p[mask], tcp_q[mask]
        self.tcp_linvel_w[mask], self.tcp_angvel_w[mask] = 0.0, 0.0
        self.success[mask] = False
        self.first_success_step[mask] = -1
        self.episode_reward[mask] = 0.0
        self.success_any[mask] = False

    def _settle_grasp(self, mask: torch.Tensor) -> None:
        """Close the gripper on the held part for GRIP_SETTLE_STEPS physics steps under Factory's
        reset gains, the controller holding the pose; then the command is the settled TCP pose.

        Physics steps all worlds at once, so when only some reset (a blow-up) the others are put
        back afterwards exactly as they were (`_physics_rows`): to them the settle never happened.
        """
        keep = ~mask
        kept = None
        if bool(keep.any()):
            kept = {name: rows[keep] for name, rows in self._physics_rows().items()}  # boolean indexing copies
        saved = self.kp.clone(), self.kd.clone()
        kp = torch.tensor(RESET_KP, device=self.tdev)
        self.kp[:] = kp
        self.kd[:] = 2.0 * torch.sqrt(kp)
        self.kd[:, 3:] /= 10.0  # Factory's rot_deriv_scale during reset
        self.physics.settle(GRIP_SETTLE_STEPS)
        self.kp[:], self.kd[:] = saved
        if kept is not None:
            for name, rows in self._physics_rows().items():
                rows[keep] = kept[name]
        tcp_p, tcp_q = self.tcp_pose()
        self.cmd_pos_w[mask] = tcp_p[mask]
        self.cmd_quat_w[mask] = tcp_q[mask]

    def _physics_rows(self) -> dict[str, torch.Tensor]:
        """Every per-world array a physics step reads and writes, as torch views (E, ...) of the
        live buffers: the state it steps from, the solver's warm start, the controller's outputs.
        (What a step derives afresh, e.g. contacts and Jacobians, is not listed.)"""
        E = self.num_envs
        s = self.state_0
        rows = {
            "joint_q": wp.to_torch(s.joint_q).view(E, -1), "joint_qd": wp.to_torch(s.joint_qd).view(E, -1),
            "body_q": wp.to_torch(s.body_q).view(E, -1), "body_qd": wp.to_torch(s.body_qd).view(E, -1),
            "body_f": wp.to_torch(s.body_f).view(E, -1), "joint_f": wp.to_torch(self.control.joint_f).view(E, -1),
            "tcp_pos_w": self.tcp_pos_w, "tcp_quat_w": self.tcp_quat_w, "tcp_twist_w": self.tcp_twist_w,
            "wrench_w": self.wrench_w,
        }
        mjw_data = getattr(self.solver, "mjw_data", None)
        for name in ("qacc_warmstart", "qacc", "qvel", "qpos", "time", "act"):
            arr = getattr(mjw_data, name, None) if mjw_data is not None else None
            if arr is not None and arr.shape[0] == E and arr.size:
                rows[f"mjw_{name}"] = wp.to_torch(arr).view(E, -1)
        return rows

    def control_finger_targets(self, mask: torch.Tensor, target: float) -> None:
        tq = wp.to_torch(self.control.joint_target_q).view(self.num_envs, -1)
        tq[mask, ARM_DOFS:ARM_DOFS + 2] = target

    def _place_held_part(self, mask: torch.Tensor) -> None:
        """Held part in the gripper (Factory's `_full_reset`): TCP flipped about its y, offset, in-hand noise."""
        newton.eval_fk(self.model, self.state_0.joint_q, self.state_0.joint_qd, self.state_0)
        tcp_p, tcp_q = self.tcp_pose()
        tcp_p, tcp_q = tcp_p[mask], tcp_q[mask]
        n = tcp_p.shape[0]
        flip = torch.tensor((0.0, 1.0, 0.0, 0.0), device=self.tdev).expand(n, 4)  # 180 deg about y
        held_q = quat_mul(tcp_q, flip)
        noise = self._uniform(n, [-a for a in self.geometry.held_pos_noise], list(self.geometry.held_pos_noise))
        offset = torch.tensor((0.0, 0.0, -self.geometry.held_in_tcp), device=self.tdev) + noise
        held_p = tcp_p + quat_rotate(held_q, offset)
        v = self._state_views(self.state_0)
        hq, hqd = self.scene.held_q_start, self.scene.held_qd_start
        v["joint_q"][mask, hq:hq + 3] = held_p  # a free joint's coordinates are its world pose
        v["joint_q"][mask, hq + 3:hq + 7] = held_q
        v["joint_qd"][mask, hqd:hqd + 6] = 0.0

    # ------------------------------------------------------------------------------------------
    # step

    def get_observations(self) -> TensorDict:
        tcp_p, tcp_q = self.tcp_pose()
        s = (self.episode_length_buf.float() / self.max_episode_length).unsqueeze(-1)
        parts = [s, tcp_p - self.target_frame_pos_w, tcp_q]
        if self.cfg.family == "forge" or self.cfg.force_obs:
            noise = FORCE_OBS_NOISE * torch.randn(self.num_envs, 3, device=self.tdev, generator=self.generator)
            parts.append(self.force_smoothed_w + noise)
        if self.cfg.tcp_velocity_obs:
            parts += [self.tcp_linvel_w, self.tcp_angvel_w]
        if self.cfg.vision_latent_dim:
            parts.append(self.current_vision_latent())
        policy = torch.cat(parts, -1)
        if not self.cfg.privileged_obs:
            return TensorDict({"policy": policy}, batch_size=[self.num_envs])
        return TensorDict({"policy": policy, "critic": torch.cat([policy, self.privileged_state()], -1)},
                          batch_size=[self.num_envs])

    def privileged_state(self) -> torch.Tensor:
        """(E, PRIVILEGED_OBS_DIM): what decides an episode and no policy observes, for an asymmetric
        critic: the held part's position relative to its assembled pose (3, world; xy is the lateral
        error the success test reads), the TCP relative to the noiseless target tip (3, world: the
        policy sees it through the 1 mm observation noise), the held part's pose in the TCP frame
        (3 + 4: the in-hand offset and tilt, drawn at reset and changed by slips) and the smoothed
        contact force without Forge's observation noise (3, world)."""
        tcp_p, tcp_q = self.tcp_pose()
        held_p, held_q = self.held_pose()
        inv = quat_conjugate(tcp_q)
        return torch.cat([held_p - self.target_base_w, tcp_p - self.fixed_tip_w, quat_rotate(inv, held_p - tcp_p),
                          quat_mul(inv, held_q), self.force_smoothed_w], -1)

    def attach_vision(self, source) -> None:
        """Fill the vision slot from `source(env) -> (E, vision_latent_dim)` (e.g. the task camera
        through a frozen encoder, `envs.camera_latent.CameraLatent`). It is called lazily, when an
        observation is read after the state changed, so the latent always shows the state the
        rest of the observation shows: after each step, after resets, and in the final
        observations of ended episodes. None detaches."""
        if source is not None and not self.cfg.vision_latent_dim:
            raise ValueError("attach_vision needs EnvConfig.vision_latent_dim > 0 (the slot to fill)")
        self.vision_source = source
        self._latent_version = -1

    def current_vision_latent(self) -> torch.Tensor:
        """(E, vision_latent_dim) the vision slot for the state now: the attached source is called only when the
        state changed since it was last read (the camera and the encoder run once a step however often it is read)."""
        if self.vision_source is not None and self._latent_version != self._state_version:
            self.physics._tick(None)  # profiled (throughput's split): the camera and encoder as "vision"
            self.set_vision_latent(self.vision_source(self))
            self.physics._tick("vision")
            self._latent_version = self._state_version
        return self.vision_latent

    def set_vision_latent(self, z: torch.Tensor) -> None:
        if z.shape != self.vision_latent.shape:
            raise ValueError(f"vision latent must have shape {tuple(self.vision_latent.shape)}, got {tuple(z.shape)}")
        self.vision_latent.copy_(z)

    def _check_actions(self, actions: torch.Tensor, width: int, name: str) -> torch.Tensor:
        if not isinstance(actions, torch.Tensor) or actions.shape != (self.num_envs, width):
            shape = tuple(actions.shape) if hasattr(actions, "shape") else type(actions).__name__
            raise ValueError(f"{name} must be a tensor of shape ({self.num_envs}, {width}), got {shape}")
        actions = actions.to(self.tdev, torch.float32)
        if not torch.isfinite(actions).all():
            raise ValueError(f"{name} contain NaN or inf")
        return actions

    def _bound_command(self, pos: torch.Tensor, quat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep a pose command within 5 cm of the target frame, gripper down (4D) or tilt-bounded (6D):
        the bounds the SAC path's kernel applies (kernels/delta_command.py), for `step_pose`."""
        pos = self.target_frame_pos_w + torch.clamp(pos - self.target_frame_pos_w, -POS_ACTION_BOUND, POS_ACTION_BOUND)
        roll, pitch, yaw = euler_xyz_from_quat(quat)
        if self.cfg.action_dim == 4:
            quat = quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw)
        else:
            quat = _bound_tilt(quat, self.cfg.max_tilt)
        return pos, quat

    def step(self, actions: torch.Tensor):
        """SAC path: actions in [-1, 1]^D, Factory's delta-pose mapping (module docstring): the
        smoothed action moves the command from the current TCP pose every physics step, inside
        the control step's graph (kernels/delta_command.py)."""
        actions = torch.clamp(self._check_actions(actions, self.cfg.action_dim, "actions"), -1.0, 1.0)
        ema = self.ema.unsqueeze(-1)
        self.actions_applied.copy_(ema * actions + (1.0 - ema) * self.actions_applied)  # in place: the kernel reads it
        self.physics.control_step(delta_actions=True)
        self._state_version += 1
        return self._finish_step(self.first_cmd_pos_w, self.first_cmd_quat_w)

    def step_pose(self, tcp_pos_w: torch.Tensor, tcp_quat_w: torch.Tensor):
        """KGRL path: an absolute TCP pose command (world frame), held for the control step."""
        pos = self._check_actions(tcp_pos_w, 3, "tcp_pos_w")
        quat = self._check_actions(tcp_quat_w, 4, "tcp_quat_w")
        quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        pos, quat = self._bound_command(pos, quat)
        self.cmd_pos_w.copy_(pos)
        self.cmd_quat_w.copy_(quat)
        self.physics.control_step(delta_actions=False)
        self._state_version += 1
        return self._finish_step(pos, quat)

    def actions_for_command(self, tcp_pos_w: torch.Tensor, tcp_quat_w: torch.Tensor) -> torch.Tensor:
        """The inverse of `step`'s mapping: (E, D) actions in [-1, 1] under which the next `step`'s first
        physics step commands this TCP pose (world frame), where the smoothing reaches it in one step;
        clipped where it does not (more than |a| = 1 of the smoothed action, per component: a clipped 6D
        rotation also turns about another axis; or an EMA step too far). Not inverted, as the kernel
        applies them after: the 5 cm box around the target frame, the 6D tilt cone, 4D's roll = pi and
        pitch = 0 (the 4D command keeps the pose's yaw alone).

        The smoothed action wanted: (pos - p_tcp) / pos_scale; the yaw difference / rot_scale_z (4D:
        exp(r) q_tcp adds r_z to the Euler yaw), the world-frame rotation vector log(q q_tcp^-1) /
        rot_scale (6D), -2 r_z / rot_scale_z - 1 (unidirectional yaw); clipped to [-1, 1], then
        a = (wanted - (1 - ema) applied) / ema. For a demonstrator commanding poses through the SAC
        action space (envs.evaluation.ScriptedDeltaPolicy); privileged (reads the smoothing state)."""
        pos = self._check_actions(tcp_pos_w, 3, "tcp_pos_w")
        quat = self._check_actions(tcp_quat_w, 4, "tcp_quat_w")
        quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        tcp_p, tcp_q = self.tcp_pose()
        D = self.cfg.action_dim
        wanted = torch.empty(self.num_envs, D, device=self.tdev)
        wanted[:, :3] = (pos - tcp_p) / self.pos_scale
        if D == 4:
            r_z = _wrap(euler_xyz_from_quat(quat)[2] - euler_xyz_from_quat(tcp_q)[2])
            wanted[:, 3] = r_z / self.rot_scale[:, 2]
        else:
            r = quat_log(quat_mul(quat, quat_conjugate(tcp_q)))
            r_z = r[:, 2]
            wanted[:, 3:] = r / self.rot_scale
        if self.geometry.unidirectional_yaw:  # the kernel's r_z = -(a + 1) / 2 rot_scale_z
            wanted[:, D - 1] = -2.0 * r_z / self.rot_scale[:, 2] - 1.0
        ema = self.ema.unsqueeze(-1)
        return ((wanted.clamp(-1.0, 1.0) - (1.0 - ema) * self.actions_applied) / ema).clamp(-1.0, 1.0)

    def _finish_step(self, cmd_pos: torch.Tensor, cmd_quat: torch.Tensor):
        self.episode_length_buf += 1
        self.step_index.copy_(self.episode_length_buf.to(torch.int32))
        if self.cfg.dynamics_randomized:  # Forge: a new dead zone every 2 s (torch.where: no host sync)
            redraw = (self.episode_length_buf % FORGE_DEAD_ZONE_PERIOD_STEPS == 0).unsqueeze(-1)
            fresh = torch.rand(self.num_envs, 1, device=self.tdev, generator=self.generator) * self.dead_zone_max
            self.dead_zone.copy_(torch.where(redraw, fresh, self.dead_zone))
        held_p, _ = self.held_pose()
        tcp_p, tcp_q = self.tcp_pose()  # once per step: the nut's success test and Forge's penalty read it
        if self.cfg.tcp_velocity_obs:  # Factory's ee_linvel_fd / ee_angvel_fd over the control step
            self.tcp_linvel_w.copy_((tcp_p - self.prev_tcp_pos_w) / CONTROL_DT)
            self.tcp_angvel_w.copy_(quat_log(quat_mul(tcp_q, quat_conjugate(self.prev_tcp_quat_w))) / CONTROL_DT)
            self.prev_tcp_pos_w.copy_(tcp_p)
            self.prev_tcp_quat_w.copy_(tcp_q)
        d = held_p - self.target_base_w
        success = (d[:, :2].norm(dim=-1) < self.geometry.success_xy) & (d[:, 2] < self.geometry.success_z)
        if self.geometry.success_tcp_yaw_max is not None:
            _, _, tcp_yaw = euler_xyz_from_quat(tcp_q)
            tcp_yaw = torch.remainder(tcp_yaw, 2 * math.pi)  # Factory's Euler yaw is in [0, 2 pi), then wrap_yaw:
            tcp_yaw = torch.where(tcp_yaw > math.radians(235.0), tcp_yaw - 2 * math.pi, tcp_yaw)  # (-125, 235] deg
            success = success & (tcp_yaw < self.geometry.success_tcp_yaw_max)
        # in place, as every state tensor here: a step under torch.inference_mode (rsl-rl's runner)
        # must not leave inference tensors behind that a later reset outside it cannot write
        self.success.copy_(success)
        newly = success & (self.first_success_step < 0)
        self.first_success_step.copy_(torch.where(newly, self.episode_length_buf, self.first_success_step))
        self.success_any |= success

        reward = SUCCESS_REWARD * success.float()
        log: dict[str, float | torch.Tensor] = {}
        if self.cfg.family == "forge":
            e_pos = (tcp_p - cmd_pos).norm(dim=-1) / POS_ACTION_SCALE
            r1, p1, y1 = euler_xyz_from_quat(tcp_q)
            r2, p2, y2 = euler_xyz_from_quat(cmd_quat)
            e_rot = _wrap(y1 - y2).abs()
            if self.cfg.action_dim == 6:
                e_rot = e_rot + _wrap(r1 - r2).abs() + _wrap(p1 - p2).abs()
            action_penalty = -0.001 * (e_pos + e_rot / ROT_ACTION_SCALE)
            contact_penalty = -torch.clamp(self.force_smoothed_w.norm(dim=-1) - CONTACT_PENALTY_THRESHOLD, min=0.0)
            reward = reward + action_penalty + contact_penalty
            log["/reward/action_penalty"] = action_penalty.mean()  # tensors: no host sync per step
            log["/reward/contact_penalty"] = contact_penalty.mean()
        self.episode_reward += reward

        # blow-ups: those worlds end here and are reset with the timed-out ones
        blown = self._blown_up(held_p, tcp_p)
        time_out = self.episode_length_buf >= self.max_episode_length
        n_blown, n_time_out, n_overflow = torch.stack(  # the step's one host read
            (blown.sum(), time_out.sum(), self.contact_overflow_substeps.sum())).tolist()
        new_overflows = n_overflow - self.contact_overflows_total
        if new_overflows:
            self._warn_overflow(new_overflows)
        self.contact_overflows_total = n_overflow
        log["/contact_overflows"] = float(new_overflows)
        extras: dict = {"time_outs": time_out.clone(), "log": log, "physics_resets": blown}
        if n_blown or n_time_out:
            # the observation each world ended its episode in, before the auto-reset replaces it:
            # off-policy learners bootstrap time-outs from it (rows of blown-up worlds are garbage)
            extras["final_observations"] = self.get_observations()
        if n_blown:
            self.physics_resets_total += n_blown
            reward = torch.where(blown, torch.zeros_like(reward), reward)
        log["/physics_resets"] = float(n_blown)
        log["/success"] = success.float().mean()
        if n_time_out:
            # the finished episodes' metrics, before the reset; a world that blew up on its last
            # step has no meaningful episode (num_episodes counts the others)
            extras["episode"] = self.episode_metrics(time_out & ~blown if n_blown else time_out)
            self.last_episode_success_any.copy_(self.success_any)
            for k, val in extras["episode"].items():
                if k != "env_ids":
                    log[f"/episode/{k}"] = val
        self._ik_failures_step = 0
        if n_blown or n_time_out:
            self._reset_worlds(time_out | blown)
        log["/ik_failures"] = float(self._ik_failures_step)
        dones = time_out | blown
        return self.get_observations(), reward, dones, extras

    def _warn_overflow(self, n: int) -> None:
        """Say (once per env) that contacts were dropped: the results are then not those of the model."""
        if getattr(self, "_overflow_warned", False):
            return
        self._overflow_warned = True
        from ..sim.scene import contact_limits

        bits = int(np.bitwise_or.reduce(wp.to_torch(self.physics.overflow_bits).cpu().numpy()))
        nconmax, njmax = contact_limits(self.cfg.task, self.scene.config)
        warnings.warn(
            f"{self.cfg.task}: contacts or constraint rows overflowed their buffers in {n} world-substeps "
            f"(SolverMuJoCo.OverflowBits mask {bits:#x}); raise SimConfig.nconmax (now {nconmax}) / njmax "
            f"(now {njmax}). Counted in extras['log']['/contact_overflows'] and contact_overflows_total.",
            RuntimeWarning, stacklevel=3)

    def episode_metrics(self, mask: torch.Tensor) -> dict:
        """Thesis metrics of the finished episodes of the masked worlds (means over those worlds)."""
        if not bool(mask.any()):
            nan = float("nan")
            return {"success_rate": nan, "success_rate_any": nan, "mean_contact_force": nan, "peak_contact_force": nan,
                    "mean_peak_contact_force": nan, "time_to_first_success_s": nan, "episode_reward": nan,
                    "num_episodes": 0, "world_success": [nan] * self.num_envs,
                    "world_contact_force": [nan] * self.num_envs}
        count = self.force_count[mask].clamp_min(1).float()
        nan_e = torch.full((self.num_envs,), float("nan"), device=self.tdev)
        # per world, NaN where the world's episode does not count: paired comparisons (two policies
        # on the same evaluation episodes, results/paired.py) match episodes world by world
        world_force = self.force_norm_sum / self.force_count.clamp_min(1).float()
        fs = self.first_success_step[mask]
        reached = fs >= 0
        ttfs = (fs[reached].float() * self.task.episode_length_s / self.max_episode_length)
        return {
            "success_rate": float(self.success[mask].float().mean()),
            "success_rate_any": float(self.success_any[mask].float().mean()),
            "mean_contact_force": float((self.force_norm_sum[mask] / count).mean()),
            "peak_contact_force": float(self.force_peak[mask].max()),
            "mean_peak_contact_force": float(self.force_peak[mask].mean()),
            "time_to_first_success_s": float(ttfs.mean()) if reached.any() else float("nan"),
            "episode_reward": float(self.episode_reward[mask].mean()),
            "num_episodes": int(mask.sum()),
            "world_success": torch.where(mask, self.success.float(), nan_e).tolist(),
            "world_contact_force": torch.where(mask, world_force, nan_e).tolist(),
        }

    def _blown_up(self, held_p: torch.Tensor, tcp_p: torch.Tensor) -> torch.Tensor:
        v = self._state_views(self.state_0)
        bq = v["body_q"].view(self.num_envs, -1, 7)
        bqd = v["body_qd"].view(self.num_envs, -1, 6)
        bad = ~torch.isfinite(bq).all(-1).all(-1) | ~torch.isfinite(bqd).all(-1).all(-1)
        bad |= bqd[..., :3].norm(dim=-1).amax(-1) > MAX_LIN_VEL
        bad |= bqd[..., 3:].norm(dim=-1).amax(-1) > MAX_ANG_VEL
        bad |= (held_p - tcp_p).norm(dim=-1) > 0.5  # the part was thrown out of the hand
        return bad


# ---------------------------------------------------------------------------------------------
# small torch helpers


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


def _orientation_error(q_target: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Rotation vector of q_target * q^-1 (world frame), the shortest way (Factory 5.4)."""
    return quat_log(quat_mul(q_target, quat_conjugate(q)))


def _point_jacobian(j_com: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Jacobian of a point at offset r (world) from the body COM: v = v_com + w x r."""
    j_lin, j_ang = j_com[:, :3], j_com[:, 3:]
    # w x r = -r x w = -[r]x j_ang qd
    rx = torch.zeros(r.shape[0], 3, 3, device=r.device, dtype=r.dtype)
    rx[:, 0, 1], rx[:, 0, 2] = -r[:, 2], r[:, 1]
    rx[:, 1, 0], rx[:, 1, 2] = r[:, 2], -r[:, 0]
    rx[:, 2, 0], rx[:, 2, 1] = -r[:, 1], r[:, 0]
    return torch.cat((j_lin - rx @ j_ang, j_ang), 1)


def _bound_tilt(quat: torch.Tensor, max_tilt: float) -> torch.Tensor:
    """Limit the angle between the gripper axis (local +z) and straight down (world -z)."""
    down = torch.tensor((0.0, 0.0, -1.0), device=quat.device, dtype=quat.dtype).expand(quat.shape[0], 3)
    z = quat_rotate(quat, torch.tensor((0.0, 0.0, 1.0), device=quat.device, dtype=quat.dtype).expand(quat.shape[0], 3))
    cos_tilt = (z * down).sum(-1).clamp(-1.0, 1.0)
    tilt = torch.acos(cos_tilt)
    over = tilt > max_tilt  # torch.where below, not an early return: no host read
    # rotate back about axis (z x down) by (tilt - max_tilt)
    axis = torch.cross(z, down, dim=-1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    corr = quat_exp(axis * (tilt - max_tilt).unsqueeze(-1))
    return torch.where(over.unsqueeze(-1), quat_mul(corr, quat), quat)
