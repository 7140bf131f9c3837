"""The task parts alone, without the robot: the checks that the contact geometry does its job.

    python -m vkgrl_newton.tools.parts --task NutThread     # advance per turn under push + torque
    python -m vkgrl_newton.tools.parts --task GearMesh      # blocked when misaligned, slides when aligned
    python -m vkgrl_newton.tools.parts --task NutThread --geometry mesh   # the same with the part meshes

The task stage is loaded on its own (fixed asset static at its authored pose, held asset a free
body) with the contact settings of the full scene (`scene.apply_contact_settings`) and stepped
with the scene's solver and substeps. A light drive acts on the held part's COM through
`State.body_f` (world frame): a constant axial force, and a yaw torque tau = kd (w_des - w_z), a
velocity servo (kd * substep_dt / I_zz must stay well under 1: the nut's I_zz is 3.3e-6 kg m^2).

Success criteria (what the tests assert):
- NutThread: started engaged on the thread and turned clockwise (screwing in), the nut descends
  one pitch (2 mm) per turn to within 10 %, and it does not descend without turning;
- GearMesh: the medium gear, pushed down above its shaft, slides onto the base plate when its
  teeth face the neighbours' gaps (yaw 0) and rests on the neighbours' teeth, 20 mm higher, when
  turned by half a tooth pitch.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

import newton

from ..cli_types import add_device_option
from ..assets_usd import TASK_USD
from ..assets_usd.dimensions import (FIXED_ASSET_NOMINAL_POS, GEAR_MEDIUM_X, GEAR_TEETH, THREAD_BOLT_RADIUS,
                                     THREAD_BOLT_TOP, THREAD_CAPSULE_RADIUS, THREAD_NUT_BOTTOM, THREAD_NUT_RADIUS,
                                     THREAD_PITCH)
from ..rotations import euler_xyz_from_quat
from ..runtime import parse_cli
from ..sim.scene import GEOMETRIES, SimConfig, add_part_meshes, apply_contact_settings, make_solver_for, stage_root

__all__ = ["PartsSim", "build_parts", "DriveResult", "run_drive"]


@dataclass
class PartsSim:
    task: str
    config: SimConfig
    model: newton.Model
    held_body: int  # in world 0
    bodies_per_world: int
    num_worlds: int


def build_parts(task: str, num_worlds: int | None = None, config: SimConfig | None = None) -> PartsSim:
    """The task stage alone, `num_worlds` copies (default: the config's, else 1), with the
    scene's contact settings."""
    if config is None:
        config = SimConfig(num_worlds=1 if num_worlds is None else num_worlds, device="cpu")
    elif num_worlds is not None and num_worlds != config.num_worlds:
        raise ValueError(f"num_worlds={num_worlds} disagrees with config.num_worlds={config.num_worlds}")
    num_worlds = config.num_worlds
    template = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    template.add_usd(str(TASK_USD[task]))
    if config.geometry == "mesh":
        device = str(config.device or "cpu")
        add_part_meshes(template, task, sdf_device=device if device.startswith("cuda") else None)
    for s in range(len(template.shape_label)):
        apply_contact_settings(template, s, config)
    root = f"/{stage_root(task)}/"
    held = [i for i, lbl in enumerate(template.body_label) if lbl.startswith(root)]
    if len(held) != 1:
        raise ValueError(f"{task}: expected one held body in the stage, found {len(held)}")
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.replicate(template, num_worlds, spacing=(0.0, 0.0, 0.0))
    model = builder.finalize(device=config.device or "cpu")
    return PartsSim(task, config, model, held[0], template.body_count, num_worlds)


@dataclass
class DriveResult:
    time: np.ndarray  # (T,) s
    pos: np.ndarray  # (T, E, 3) held origin relative to the fixed asset's frame, m
    yaw: np.ndarray  # (T, E) unwrapped held yaw, rad
    tilt: np.ndarray  # (T, E) angle of the held z axis from vertical, rad
    contacts: np.ndarray  # (T,) rigid contact count (all worlds)


def _yaw_tilt(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw (XYZ Euler, rotations.euler_xyz_from_quat) and the tilt of the body z axis from vertical, xyzw quats."""
    _, _, yaw = euler_xyz_from_quat(torch.from_numpy(np.ascontiguousarray(q, dtype=np.float64)))
    x, y = q[..., 0], q[..., 1]
    zz = 1 - 2 * (x * x + y * y)  # z component of the rotated z axis
    return yaw.numpy(), np.arccos(np.clip(zz, -1.0, 1.0))


def run_drive(sim: PartsSim, start_pos, start_yaw, duration: float, force_z: float, omega_des: float = 0.0,
              torque_kd: float = 0.0, torque_max: float = 0.01) -> DriveResult:
    """Place the held part (origin at `start_pos` in the fixed frame, yaw `start_yaw`; per world or
    shared), then step `duration` s pushing with `force_z` N along world z and the yaw servo."""
    model, cfg = sim.model, sim.config
    nw = sim.num_worlds
    start_pos = np.broadcast_to(np.asarray(start_pos, dtype=np.float64), (nw, 3))
    start_yaw = np.broadcast_to(np.asarray(start_yaw, dtype=np.float64), (nw,))
    solver, pipeline = make_solver_for(model, sim.task, cfg, nw)  # the scene's solver and collision settings
    s0, s1, control = model.state(), model.state(), model.control()
    contacts = pipeline.contacts()

    held = np.array([w * sim.bodies_per_world + sim.held_body for w in range(nw)])
    origin = np.array(FIXED_ASSET_NOMINAL_POS)
    body_q = s0.body_q.numpy()
    for w, b in enumerate(held):
        body_q[b, :3] = origin + start_pos[w]
        body_q[b, 3:] = (0.0, 0.0, math.sin(start_yaw[w] / 2), math.cos(start_yaw[w] / 2))
    # free joints: joint_q mirrors body_q for a root body
    joint_q = s0.joint_q.numpy()
    q_per_world = model.joint_coord_count // nw
    for w, b in enumerate(held):
        joint_q[w * q_per_world: w * q_per_world + 7] = body_q[b]
    s0.joint_q.assign(joint_q)
    s0.joint_qd.zero_()
    newton.eval_fk(model, s0.joint_q, s0.joint_qd, s0)

    dt = cfg.sim_dt / cfg.substeps
    frames = int(round(duration / cfg.sim_dt))
    t_log, pos_log, q_log, n_log = [], [], [], []
    held_t = torch.as_tensor(held, device=wp.device_to_torch(model.device))
    for f in range(frames):
        for _ in range(cfg.substeps):
            # the drive on the device (torch views of the state, no host round trip per substep)
            wz = wp.to_torch(s0.body_qd)[held_t, 5]
            wrench = wp.to_torch(s0.body_f)
            wrench.zero_()
            wrench[held_t, 2] = force_z
            wrench[held_t, 5] = torch.clamp(torque_kd * (omega_des - wz), -torque_max, torque_max)
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        bq = s0.body_q.numpy()[held]
        t_log.append((f + 1) * cfg.sim_dt)
        pos_log.append(bq[:, :3] - origin)
        q_log.append(bq[:, 3:])
        n_log.append(int(contacts.rigid_contact_count.numpy()[0]))
    q = np.array(q_log)
    yaw, tilt = _yaw_tilt(q)
    return DriveResult(np.array(t_log), np.array(pos_log), np.unwrap(yaw, axis=0), tilt, np.array(n_log))


def advance_per_turn(result: DriveResult, world: int = 0, skip: float = 0.2) -> float:
    """Slope of z against yaw turns (m per turn, positive when screwing in clockwise descends)
    over the part of the run after the first `skip` fraction."""
    n = len(result.time)
    k0 = int(skip * n)
    turns = -result.yaw[k0:, world] / (2 * math.pi)  # clockwise turns
    z = result.pos[k0:, world, 2]
    slope = np.polyfit(turns, z, 1)[0]
    return float(-slope)


def nut_rest_height(yaw: float) -> float:
    """Height of the nut's origin (bottom face) in the bolt frame where its bottom thread turn rests
    on the bolt's top turn, for a nut yaw `yaw` relative to the bolt (the authored helices: both
    start on their frame's +x; the nut's ridge sits above the bolt's by the axial offset at which
    the two capsules touch, given their radial offset)."""
    radial = THREAD_NUT_RADIUS - THREAD_BOLT_RADIUS
    axial = math.sqrt((2 * THREAD_CAPSULE_RADIUS) ** 2 - radial**2)
    frac = (yaw / (2 * math.pi)) % 1.0
    return THREAD_BOLT_TOP - THREAD_NUT_BOTTOM - THREAD_PITCH + THREAD_PITCH * frac + axial


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", choices=("NutThread", "GearMesh"), required=True)
    ap.add_argument("--geometry", choices=GEOMETRIES, default="primitives",
                    help="the parts' collision geometry (mesh: SDFs on CUDA, Newton's triangle BVH path on a CPU)")
    add_device_option(ap, default="cpu")
    args = parse_cli(ap, argv, device=True)
    config = lambda nw: SimConfig(num_worlds=nw, device=args.device, geometry=args.geometry)  # noqa: E731
    if args.task == "NutThread":
        sim = build_parts("NutThread", config=config(1))
        # engaged on the bolt's top turn; the mesh bolt's top turn is the thread's runout: one lower
        z0 = nut_rest_height(math.pi / 2) - (THREAD_PITCH if args.geometry == "mesh" else 0.0)
        r = run_drive(sim, (0.0, 0.0, z0), math.pi / 2, 1.0, force_z=-0.5, omega_des=-2 * math.pi, torque_kd=1e-3)
        turned = (math.pi / 2 - r.yaw[-1, 0]) / (2 * math.pi)
        print(f"clockwise turns {turned:.2f}, dz {1e3 * (r.pos[-1, 0, 2] - r.pos[0, 0, 2]):.2f} mm, "
              f"advance {1e3 * advance_per_turn(r):.3f} mm/turn, max tilt {math.degrees(r.tilt.max()):.2f} deg, "
              f"contacts {r.contacts.mean():.0f}")
    else:
        sim = build_parts("GearMesh", config=config(2))
        pitch = 2 * math.pi / GEAR_TEETH["medium"]
        r = run_drive(sim, (GEAR_MEDIUM_X, 0.0, 0.03), [0.0, pitch / 2], 0.5, force_z=-1.0)
        for w, name in enumerate(("aligned", "misaligned")):
            print(f"{name}: z {1e3 * r.pos[0, w, 2]:.1f} -> {1e3 * r.pos[-1, w, 2]:.2f} mm, "
                  f"xy offset {1e3 * np.hypot(r.pos[-1, w, 0] - GEAR_MEDIUM_X, r.pos[-1, w, 1]):.2f} mm, "
                  f"max tilt {math.degrees(r.tilt[:, w].max()):.2f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
