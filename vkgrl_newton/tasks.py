"""One table of per-task facts for PegInsert, GearMesh and NutThread, from the thesis unless noted.

Each TaskSpec holds the episode length (Table 5.1), the KMP inference parameters (Table 5.4),
the initial-state randomization (Table 5.2) and the hand's start height (Isaac Lab Factory).
The other per-task facts live where they are used: part dimensions in
vkgrl_newton.assets_usd.dimensions, the env's part geometry and success test in
vkgrl_newton.envs.assembly_env.TASK_GEOMETRY, the task camera (Table 5.6) in
vkgrl_newton.sim.camera.TASK_CAMERAS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["TaskSpec", "TASKS", "get_task", "CONTROL_DT", "SIM_DT", "DECIMATION"]

SIM_DT = 1.0 / 120.0  # Table 5.1
DECIMATION = 8  # Table 5.1
CONTROL_DT = SIM_DT * DECIMATION  # 1/15 s, eq. 5.1


@dataclass(frozen=True)
class TaskSpec:
    name: str
    episode_length_s: float  # Table 5.1
    # KMP inference parameters, Table 5.4
    kmp_dt: float
    kmp_horizon: int
    w_pos: float
    w_rot: float
    psi_ref: float  # reference yaw of q_ref = q(pi, 0, psi_ref), radians, eq. 5.28
    # Initial-state randomization, Table 5.2: half-ranges (m) and yaw range (rad)
    ee_pos_noise: tuple[float, float, float]
    ee_yaw_range: tuple[float, float]
    target_pos_noise: tuple[float, float, float]
    target_yaw_range: tuple[float, float]
    # Isaac Lab Factory (`hand_init_pos` z, factory_tasks_cfg.py): hand start height above the
    # fixed asset's tip, m
    hand_init_height: float

    @property
    def episode_steps(self) -> int:
        """Control steps per episode (150 for 10 s at 15 Hz)."""
        return int(round(self.episode_length_s / CONTROL_DT))

    @property
    def kmp_steps(self) -> int:
        """Steps of the KMP control grid, 1 / kmp_dt (equals episode_steps for every thesis task)."""
        return int(round(1.0 / self.kmp_dt))


_deg = math.radians

# The experiment's other axes (thesis ch. 5-6): environment families and action spaces. The methods are
# the run layer's table (run/methods.py: learner, action path and observation parts of each).
FAMILIES = ("factory", "forge")
ACTION_DIMS = (4, 6)
# The parts' collision geometry (sim/scene.py): the primitives everywhere; tooth / thread meshes
# (SDFs on CUDA) for the tasks whose primitives are approximations.
GEOMETRIES = ("primitives", "mesh")
SOLVERS = ("mujoco", "steel")
TARGET_OBS_NOISE = 0.001  # m, per axis, per episode: the observed target frame's noise (eq. 5.23 / Factory)
VISION_LATENT_DIM = 16  # d_z of the thesis's VAE (5.6): the vision methods' latent slot  # sim.scene.SimConfig.solver (here: the CLIs list them before importing the sim)
MESH_TASKS = ("GearMesh", "NutThread")


def geometry_error(task: str, geometry: str) -> str | None:
    """Why `geometry` does not exist for `task` (a message naming the allowed values), or None."""
    if geometry not in GEOMETRIES:
        return f"geometry must be one of {GEOMETRIES}, got {geometry!r}"
    if geometry == "mesh" and task not in MESH_TASKS:
        return f"geometry 'mesh' exists for {sorted(MESH_TASKS)}, not {task} (its primitives are exact)"
    return None


def observation_dim(family: str, vision_latent_dim: int = 0, tcp_velocity: bool = False, force: bool = False) -> int:
    """Thesis eq. 5.5: s_t (1), TCP position in the target frame (3), TCP quaternion (4), Forge's
    smoothed force (3), the vision latent; with the deviations of issue 40 the force in Factory too
    (`force`, 3) and the TCP's linear and angular velocity (`tcp_velocity`, 6)."""
    return 8 + (3 if family == "forge" or force else 0) + (6 if tcp_velocity else 0) + vision_latent_dim

TASKS: dict[str, TaskSpec] = {
    "PegInsert": TaskSpec(
        name="PegInsert",
        episode_length_s=10.0,
        kmp_dt=1.0 / 150.0,
        kmp_horizon=15,
        w_pos=150.0,
        w_rot=15.0,
        psi_ref=0.0,
        ee_pos_noise=(0.02, 0.02, 0.01),
        ee_yaw_range=(_deg(-45.0), _deg(45.0)),
        target_pos_noise=(0.05, 0.05, 0.05),
        target_yaw_range=(_deg(0.0), _deg(360.0)),
        hand_init_height=0.047,
    ),
    "GearMesh": TaskSpec(
        name="GearMesh",
        episode_length_s=10.0,
        kmp_dt=1.0 / 150.0,
        kmp_horizon=15,
        w_pos=250.0,
        w_rot=25.0,
        psi_ref=0.0,
        ee_pos_noise=(0.02, 0.02, 0.01),
        ee_yaw_range=(_deg(-45.0), _deg(45.0)),
        target_pos_noise=(0.05, 0.05, 0.05),
        target_yaw_range=(_deg(0.0), _deg(15.0)),
        hand_init_height=0.035,
    ),
    "NutThread": TaskSpec(
        name="NutThread",
        episode_length_s=15.0,
        kmp_dt=1.0 / 225.0,
        kmp_horizon=25,
        w_pos=200.0,
        w_rot=10.0,
        psi_ref=_deg(-40.0),
        ee_pos_noise=(0.02, 0.02, 0.01),
        ee_yaw_range=(_deg(90.0), _deg(120.0)),
        target_pos_noise=(0.05, 0.05, 0.05),
        target_yaw_range=(_deg(120.0), _deg(150.0)),
        hand_init_height=0.015,
    ),
}


def get_task(name: str) -> TaskSpec:
    """The TaskSpec of a task name; ValueError naming the allowed names otherwise."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"task must be one of {sorted(TASKS)}, got {name!r}") from None
