"""Kernel microbenchmarks: `python -m vkgrl_newton.tools.bench_kernels [--json PATH]`.

Times every Warp kernel in vkgrl_newton.kernels against its torch implementation of the same
computation, for batch sizes (number of environments) 1, 128 and 4096 on every available
device (cpu, and cuda when present). Each timing is the median of --repeats runs after
--warmup runs, with the device synchronized around each run; inputs are allocated once,
outside the timed region. Prints a table and writes JSON.

On the CPU, Warp runs kernels on one thread, so torch is pinned to one thread too by default
(--torch-threads 1): a like-for-like comparison, and immune to the thread oversubscription
that makes multi-threaded torch timings on a busy 2-core machine swing by 50x.

A kernel joins the benchmark by adding a `Case` to `CASES`: a name and a setup function
(batch, device) -> (warp_fn, torch_fn), both zero-argument callables doing one batched call;
torch_fn may be None for a case with only one implementation (its torch columns print "-").

The OSC cases: "osc" is the kernel alone on random Newton-shaped inputs; "osc_newton_pipeline" is
what an env pays per control step on a real Franka model (newton.eval_fk + eval_jacobian +
eval_mass_matrix + the kernel); "osc_newton_controller" is Newton's own
newton.controllers.ControllerOperationalSpace.step on the same model (it runs FK, J, M and its
control law itself); building their 4096-world model takes a few seconds.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import warp as wp

from ..assets_usd.dimensions import FACTORY_NULL_JOINTS, FACTORY_RESET_JOINTS
from .._io import atomic_write_text, output_path_error, strict_json
from ..cli_types import device_name
from ..runtime import cpu_model, device_error, parse_cli
from ..signals import run_cli
from ..kernels.kmp_horizon import kmp_horizon_pose, mat66f, vec6f
from ..kernels.osc import osc_torques, osc_torques_torch


@dataclass(frozen=True)
class Case:
    name: str
    setup: Callable[[int, str], tuple[Callable[[], None], Callable[[], object] | None]]


def _torch_device(device: str) -> str:
    """torch's name of a warp device: 'cuda:N' is the same in both, warp's 'cpu' is torch's 'cpu'."""
    return device if device.startswith("cuda") else "cpu"


def setup_kmp_horizon(batch: int, device: str):
    """KMP horizon: 151-step tables (PegInsert grid), random actions, step indices and targets."""
    from ..kmp.tables import kmp_pose_torch

    tdev = _torch_device(device)
    g = torch.Generator().manual_seed(0)
    n_steps = 151
    mean = (torch.rand(n_steps, 6, generator=g) - 0.5) * 0.1
    gain = (torch.rand(n_steps, 6, 6, generator=g) - 0.5) * 1e-3
    zeta = (torch.rand(batch, 6, generator=g) - 0.5) * 300.0
    step_index = torch.randint(0, n_steps, (batch,), generator=g, dtype=torch.int32)
    target = torch.rand(batch, 3, generator=g)
    ref_quat = torch.nn.functional.normalize(torch.rand(batch, 4, generator=g) - 0.5, dim=1)
    mean, gain, zeta, step_index, target, ref_quat = (
        t.to(tdev).contiguous() for t in (mean, gain, zeta, step_index, target, ref_quat)
    )
    # warp views of the same torch memory (no copies), as the env will use them
    args = [
        wp.from_torch(step_index, dtype=wp.int32),
        wp.from_torch(zeta, dtype=vec6f),
        wp.from_torch(mean, dtype=vec6f),
        wp.from_torch(gain, dtype=mat66f),
        wp.from_torch(target, dtype=wp.vec3),
        wp.from_torch(ref_quat, dtype=wp.quat),
        wp.zeros(batch, dtype=vec6f, device=device),
        wp.zeros(batch, dtype=wp.vec3, device=device),
        wp.zeros(batch, dtype=wp.quat, device=device),
    ]

    def warp_fn():
        kmp_horizon_pose(*args)

    def torch_fn():
        return kmp_pose_torch(step_index, zeta, mean, gain, target, ref_quat)

    return warp_fn, torch_fn


FACTORY_KP = (565.0, 565.0, 565.0, 28.0, 28.0, 28.0)  # FORGE nominal task stiffness


def setup_osc(batch: int, device: str):
    """OSC kernel alone: Newton-shaped random J (batch, 6*11, 9) and SPD H (batch, 9, 9), 12 bodies
    and a 16-coordinate / 15-DoF state per world (robot + free peg), null space and dead zone on."""
    tdev = _torch_device(device)
    g = torch.Generator().manual_seed(0)
    n_links, n_dofs, bodies_per_world, hand_link = 11, 9, 12, 8
    jac = torch.randn(batch, 6 * n_links, n_dofs, generator=g) * 0.5
    a = torch.randn(batch, n_dofs, n_dofs, generator=g) * 0.3
    mass = a @ a.transpose(1, 2) + 0.1 * torch.eye(n_dofs)
    n_bodies = batch * bodies_per_world
    body_q = torch.cat([torch.rand(n_bodies, 3, generator=g),
                        torch.nn.functional.normalize(torch.randn(n_bodies, 4, generator=g), dim=1)], dim=1)
    hand_body = (torch.arange(batch) * bodies_per_world + hand_link).to(torch.int32)
    kp = torch.tensor(FACTORY_KP).repeat(batch, 1)
    t = dict(
        jacobian=jac,
        mass_matrix=mass,
        robot_articulation=torch.arange(batch, dtype=torch.int32),
        body_q=body_q,
        body_qd=torch.randn(n_bodies, 6, generator=g) * 0.1,
        body_com=torch.rand(n_bodies, 3, generator=g) * 0.05,
        hand_body=hand_body,
        joint_q=torch.rand(batch, 16, generator=g) * 2 - 1,
        joint_qd=torch.randn(batch, 15, generator=g) * 0.1,
        target_pos_w=body_q[hand_body.long(), :3] + 0.01,
        target_quat_w=torch.nn.functional.normalize(torch.randn(batch, 4, generator=g), dim=1),
        kp=kp,
        kd=2.0 * kp.sqrt(),
        dead_zone=torch.full((batch, 6), 0.5),
        q_null=torch.tensor(FACTORY_NULL_JOINTS),
        torque_limit=torch.full((7,), 100.0),
    )
    t = {k: v.to(tdev).contiguous() for k, v in t.items()}
    joint_f = torch.zeros(batch, 15, device=tdev)
    scalars = dict(hand_link=hand_link, arm_dof_start=0, tcp_offset_hand=(0.0, 0.0, 0.112071), arm_q_start=0,
                   arm_qd_start=0, kp_null=10.0, kd_null=6.3246)
    wdt = dict(body_q=wp.transform, body_qd=wp.spatial_vector, body_com=wp.vec3, target_pos_w=wp.vec3,
               target_quat_w=wp.quat, kp=vec6f, kd=vec6f, dead_zone=vec6f, robot_articulation=wp.int32,
               hand_body=wp.int32)
    # warp views of the same torch memory (no copies), as the env will use them
    w = {k: wp.from_torch(v, dtype=wdt.get(k, wp.float32)) for k, v in t.items()}
    w_out = dict(tcp_pos_w=wp.zeros(batch, dtype=wp.vec3, device=device),
                 tcp_quat_w=wp.zeros(batch, dtype=wp.quat, device=device),
                 tcp_twist_w=wp.zeros(batch, dtype=wp.spatial_vector, device=device),
                 wrench_w=wp.zeros(batch, dtype=vec6f, device=device),
                 joint_f=wp.from_torch(joint_f))

    def warp_fn():
        osc_torques(**w, **scalars, **w_out)

    def torch_fn():
        return osc_torques_torch(**t, **scalars, joint_f=joint_f)

    return warp_fn, torch_fn


def franka_builder(tcp_offset: float = 0.1034):
    """One Franka Panda (link0 fixed to the world, 7 revolute arm joints about local z, a fixed hand,
    two prismatic fingers) from Franka's modified-DH body tree and the Gaz et al. (RA-L 2019) inertias,
    with a site "tool_site" tcp_offset along the hand's z. 11 links, 9 DoF; arm joints labelled
    joint1..joint7."""
    import newton

    def quat(w, x, y, z):  # the table's wxyz -> warp's xyzw
        return wp.quat(x, y, z, w)

    def inertia(ixx, iyy, izz, ixy, ixz, iyz):
        return wp.mat33(ixx, ixy, ixz, ixy, iyy, iyz, ixz, iyz, izz)

    s = math.sqrt(0.5)  # the table's 0.70711, exact
    # (parent offset, parent rotation wxyz, mass, com, inertia ixx iyy izz ixy ixz iyz)
    links = [
        ((0, 0, 0), (1, 0, 0, 0), 0.629769, (-0.041018, -0.00014, 0.049974), (0.00315, 0.00388, 0.004285, 8.2904e-7, 0.00015, 8.2299e-6)),
        ((0, 0, 0.333), (1, 0, 0, 0), 4.970684, (0.003875, 0.002081, -0.04762), (0.70337, 0.70661, 0.009117, -0.000139, 0.006772, 0.019169)),
        ((0, 0, 0), (s, -s, 0, 0), 0.646926, (-0.003141, -0.02872, 0.003495), (0.007962, 0.02811, 0.025995, -0.003925, 0.010254, 0.000704)),
        ((0, -0.316, 0), (s, s, 0, 0), 3.228604, (0.027518, 0.039252, -0.066502), (0.037242, 0.036155, 0.01083, -0.004761, -0.011396, -0.012805)),
        ((0.0825, 0, 0), (s, s, 0, 0), 3.587895, (-0.05317, 0.104419, 0.027454), (0.025853, 0.019552, 0.028323, 0.007796, -0.001332, 0.008641)),
        ((-0.0825, 0.384, 0), (s, -s, 0, 0), 1.225946, (-0.011953, 0.041065, -0.038437), (0.035549, 0.029474, 0.008627, -0.002117, -0.004037, 0.000229)),
        ((0, 0, 0), (s, s, 0, 0), 1.666555, (0.060149, -0.014117, -0.010517), (0.001964, 0.004354, 0.005433, 0.000109, -0.001158, 0.000341)),
        ((0.088, 0, 0), (s, s, 0, 0), 0.735522, (0.010517, -0.004252, 0.061597), (0.012516, 0.010027, 0.004815, -0.000428, -0.001196, -0.000741)),
    ]
    armature = (0.3, 0.3, 0.3, 0.3, 0.11, 0.11, 0.11)  # Isaac Lab's Newton Factory port
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    joints, parent = [], -1
    for i, (pos, rot, mass, com, inert) in enumerate(links):
        body = b.add_link(mass=mass, com=com, inertia=inertia(*inert), label="link0" if i == 0 else f"link{i}")
        xform = wp.transform(pos, quat(*rot))
        if i == 0:
            joints.append(b.add_joint_fixed(parent, body, parent_xform=xform, label="base_joint"))
        else:
            joints.append(b.add_joint_revolute(parent, body, parent_xform=xform, axis=newton.Axis.Z,
                                               armature=armature[i - 1], label=f"joint{i}"))
        parent = body
    hand = b.add_link(mass=0.73, com=(-0.01, 0.0, 0.03), inertia=inertia(0.001, 0.0025, 0.0017, 0, 0, 0), label="hand")
    joints.append(b.add_joint_fixed(parent, hand, parent_xform=wp.transform((0, 0, 0.107), quat(math.cos(math.pi / 8), 0, 0, -math.sin(math.pi / 8))),
                                    label="hand_joint"))
    for k, rot in enumerate(((1, 0, 0, 0), (0, 0, 0, 1))):
        finger = b.add_link(mass=0.015, inertia=inertia(2.375e-6, 2.375e-6, 7.5e-7, 0, 0, 0), label=f"finger{k + 1}")
        joints.append(b.add_joint_prismatic(hand, finger, parent_xform=wp.transform((0, 0, 0.0584), quat(*rot)),
                                            axis=newton.Axis.Y, limit_lower=0.0, limit_upper=0.04, armature=0.15,
                                            label=f"finger_joint{k + 1}"))
    b.add_articulation(joints, label="franka")
    b.add_site(hand, xform=wp.transform((0.0, 0.0, tcp_offset), wp.quat_identity()), label="tool_site")
    return b


def franka_model(world_count: int, device: str, seed: int = 0):
    """(model, state) of world_count Franka worlds at the Factory reset pose plus noise, random joint
    velocities, forward kinematics evaluated."""
    import newton

    scene = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    scene.replicate(franka_builder(), world_count)
    model = scene.finalize(device=device)
    rng = torch.Generator().manual_seed(seed)
    q = torch.tensor(FACTORY_RESET_JOINTS + (0.04, 0.04)).repeat(world_count, 1)
    q[:, :7] += 0.1 * torch.randn(world_count, 7, generator=rng)
    qd = 0.2 * torch.randn(world_count, 9, generator=rng)
    state = model.state()
    state.joint_q.assign(q.reshape(-1).numpy())
    state.joint_qd.assign(qd.reshape(-1).numpy())
    newton.eval_fk(model, state.joint_q, state.joint_qd, state)
    return model, state


def setup_osc_newton_pipeline(batch: int, device: str):
    """Per-step OSC cost on a Newton Franka model: eval_fk + eval_jacobian + eval_mass_matrix + kernel."""
    import newton

    model, state = franka_model(batch, device)
    jac = wp.zeros((model.articulation_count, 6 * model.max_joints_per_articulation, model.max_dofs_per_articulation),
                   dtype=wp.float32, device=device)
    mass = wp.zeros((model.articulation_count, model.max_dofs_per_articulation, model.max_dofs_per_articulation),
                    dtype=wp.float32, device=device)
    joint_s = wp.zeros(model.joint_dof_count, dtype=wp.spatial_vector, device=device)
    body_i_s = wp.zeros(model.body_count, dtype=wp.spatial_matrix, device=device)
    hand_body = wp.array(np.arange(batch, dtype=np.int32) * 11 + 8, dtype=wp.int32, device=device)
    control = model.control()
    jq = state.joint_q.reshape((batch, 9))
    jqd = state.joint_qd.reshape((batch, 9))
    jf = control.joint_f.reshape((batch, 9))
    tcp_pos = state.body_q.numpy()[hand_body.numpy(), :3] + np.array([0.0, 0.0, -0.11])
    kp = np.tile(np.array(FACTORY_KP, np.float32), (batch, 1))
    args = dict(
        jacobian=jac, mass_matrix=mass, robot_articulation=wp.array(np.arange(batch, dtype=np.int32), device=device),
        hand_link=8, arm_dof_start=0, body_q=state.body_q, body_qd=state.body_qd, body_com=model.body_com,
        hand_body=hand_body, tcp_offset_hand=(0.0, 0.0, 0.1034), joint_q=jq, joint_qd=jqd, arm_q_start=0,
        arm_qd_start=0, target_pos_w=wp.array(tcp_pos, dtype=wp.vec3, device=device),
        target_quat_w=wp.array(np.tile([1.0, 0.0, 0.0, 0.0], (batch, 1)), dtype=wp.quat, device=device),
        kp=wp.array(kp, dtype=vec6f, device=device), kd=wp.array(2 * np.sqrt(kp), dtype=vec6f, device=device),
        dead_zone=wp.zeros(batch, dtype=vec6f, device=device),
        q_null=wp.array(np.array(FACTORY_NULL_JOINTS, np.float32), device=device), kp_null=10.0, kd_null=6.3246,
        torque_limit=wp.array(np.full(7, 100.0, np.float32), device=device),
        tcp_pos_w=wp.zeros(batch, dtype=wp.vec3, device=device), tcp_quat_w=wp.zeros(batch, dtype=wp.quat, device=device),
        tcp_twist_w=wp.zeros(batch, dtype=wp.spatial_vector, device=device),
        wrench_w=wp.zeros(batch, dtype=vec6f, device=device), joint_f=jf,
    )

    def warp_fn():
        newton.eval_fk(model, state.joint_q, state.joint_qd, state)
        newton.eval_jacobian(model, state, jac, joint_S_s=joint_s)
        newton.eval_mass_matrix(model, state, mass, J=jac, body_I_s=body_i_s)
        osc_torques(**args)

    return warp_fn, None


def setup_osc_newton_controller(batch: int, device: str):
    """newton.controllers.ControllerOperationalSpace.step on the same Franka model: inertia decoupling
    (Lambda, which also makes its null space dynamically consistent), null-space posture, no gravity
    compensation. Its task gains are accelerations (1/s^2), so the values differ from Factory's."""
    from newton.controllers import ControllerOperationalSpace

    model, state = franka_model(batch, device)
    osc = ControllerOperationalSpace(
        model, joints=[f"joint{i}" for i in range(1, 8)], tool_sites="tool_site",
        motion_stiffness=400.0, motion_damping=40.0, use_gravity_compensation=False,
        use_null_space_control=True, null_space_stiffness=10.0, null_space_damping=6.3246)
    control = model.control()
    inp, out = osc.input(), osc.output()
    out.joint_f = control.joint_f[osc.qd_start]
    inp.joint_q, inp.joint_qd = state.joint_q, state.joint_qd
    hand = state.body_q.numpy()[np.arange(batch) * 11 + 8]
    pose = np.concatenate([hand[:, :3] + np.array([0.0, 0.0, -0.11]), np.tile([1.0, 0.0, 0.0, 0.0], (batch, 1))], axis=1)
    inp.desired_tool_pose_operational.assign(pose.astype(np.float32))
    inp.joint_q_des_null.assign(np.tile(np.array(FACTORY_NULL_JOINTS, np.float32), batch))

    def warp_fn():
        osc.step(inputs=inp, outputs=out, dt=1.0 / 120.0)

    return warp_fn, None


CASES = [
    Case("kmp_horizon", setup_kmp_horizon),
    Case("osc", setup_osc),
    Case("osc_newton_pipeline", setup_osc_newton_pipeline),
    Case("osc_newton_controller", setup_osc_newton_controller),
]


def setup_contact_forces(batch: int, device: str):
    """Contact forces: reduce + EMA/statistics update. Per world 60 shapes (the first 6 in the gripper group)
    and 200 contact rows, of which 150 are live; random within-world shape pairs and forces."""
    from ..kernels.contact_forces import contact_force_reduce, contact_force_update, contact_forces_torch

    tdev = _torch_device(device)
    g = torch.Generator().manual_seed(0)
    shapes_per_world, rows_per_world, live_per_world = 60, 200, 150
    num_shapes, num_rows = shapes_per_world * batch, rows_per_world * batch
    shape_world = torch.arange(batch, dtype=torch.int32).repeat_interleave(shapes_per_world)
    shape_group = (torch.arange(num_shapes) % shapes_per_world < 6).to(torch.int32)
    row_world = torch.randint(0, batch, (num_rows,), generator=g)
    shape0 = (row_world * shapes_per_world + torch.randint(0, shapes_per_world, (num_rows,), generator=g)).int()
    shape1 = (row_world * shapes_per_world + torch.randint(0, shapes_per_world, (num_rows,), generator=g)).int()
    contact_f = torch.randn(num_rows, 6, generator=g)
    count = torch.tensor([live_per_world * batch], dtype=torch.int32)
    smoothed, norm_sum = torch.zeros(batch, 3), torch.zeros(batch)
    sample_count, peak = torch.zeros(batch, dtype=torch.int32), torch.zeros(batch)
    tensors = [t.to(tdev).contiguous() for t in (count, shape0, shape1, contact_f, shape_group, shape_world,
                                                 smoothed, norm_sum, sample_count, peak)]
    count, shape0, shape1, contact_f, shape_group, shape_world, smoothed, norm_sum, sample_count, peak = tensors
    t_stats = [t.clone() for t in (smoothed, norm_sum, sample_count, peak)]
    # warp views of the same torch memory (no copies), as the env will use them
    reduce_args = dict(
        contact_count=wp.from_torch(count, dtype=wp.int32),
        contact_shape0=wp.from_torch(shape0, dtype=wp.int32),
        contact_shape1=wp.from_torch(shape1, dtype=wp.int32),
        contact_f=wp.from_torch(contact_f, dtype=wp.spatial_vector),
        shape_group=wp.from_torch(shape_group, dtype=wp.int32),
        shape_world=wp.from_torch(shape_world, dtype=wp.int32),
        interaction_force_w=wp.zeros(batch, dtype=wp.vec3, device=device),
    )
    update_args = dict(
        interaction_force_w=reduce_args["interaction_force_w"],
        force_smoothed_w=wp.from_torch(smoothed, dtype=wp.vec3),
        force_norm_sum=wp.from_torch(norm_sum, dtype=wp.float32),
        force_sample_count=wp.from_torch(sample_count, dtype=wp.int32),
        force_peak=wp.from_torch(peak, dtype=wp.float32),
    )

    def warp_fn():
        contact_force_reduce(**reduce_args)
        contact_force_update(**update_args)

    def torch_fn():
        return contact_forces_torch(count, shape0, shape1, contact_f, shape_group, shape_world, *t_stats)

    return warp_fn, torch_fn


CASES.append(Case("contact_forces", setup_contact_forces))


def _time(fn, device: str, warmup: int, repeats: int) -> float:
    sync = (lambda: wp.synchronize_device(device)) if device.startswith("cuda") else (lambda: None)
    tsync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    tsync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        tsync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _machine() -> dict:
    info = dict(cpu=cpu_model(), cores=os.cpu_count(), python=platform.python_version(), torch=torch.__version__,
                torch_threads=torch.get_num_threads(), warp=wp.config.version)
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, nargs="+", default=[1, 128, 4096], help="numbers of environments")
    p.add_argument("--devices", nargs="+", default=None, type=device_name, help="warp devices (default: cpu and cuda:0 if present)")
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--json", default=None,
                   help="where to write the results, a new file (never overwritten; default "
                        "runs/bench/kernels_<date-time>.json, a new file per run)")
    p.add_argument("--only", nargs="+", default=None, help=f"case names, from {[c.name for c in CASES]}")
    p.add_argument("--torch-threads", type=int, default=1, help="torch CPU threads (0: torch's default)")
    args = parse_cli(p, argv)
    for device in args.devices or ():
        if (why := device_error(device, "--devices")) is not None:
            p.error(why)
    if args.torch_threads < 0:
        p.error(f"--torch-threads {args.torch_threads}: must be >= 0 (0: torch's default)")
    if min(args.batch) < 1 or args.warmup < 0 or args.repeats < 1:
        p.error(f"--batch {args.batch} / --warmup {args.warmup} / --repeats {args.repeats}: batches and repeats "
                "must be >= 1, warmup >= 0")
    if args.only is not None and set(args.only) - {c.name for c in CASES}:
        p.error(f"--only {sorted(set(args.only) - {c.name for c in CASES})}: unknown; cases are {[c.name for c in CASES]}")
    out = Path(args.json or f"runs/bench/kernels_{time.strftime('%Y%m%d-%H%M%S')}.json")
    if why := output_path_error(out, "--json"):  # checked before the benchmark runs, not after
        p.error(why)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)

    devices = args.devices or (["cpu"] + (["cuda:0"] if wp.is_cuda_available() else []))
    cases = [c for c in CASES if args.only is None or c.name in args.only]
    rows = []
    name_w = max([14] + [len(c.name) for c in cases])
    header = (f"{'kernel':<{name_w}} {'device':<8} {'batch':>6} {'warp us':>10} {'torch us':>10} {'torch/warp':>10} "
              f"{'Menv/s warp':>12}")
    print(header)
    print("-" * len(header))
    for case in cases:
        for device in devices:
            for batch in args.batch:
                with wp.ScopedDevice(device):
                    warp_fn, torch_fn = case.setup(batch, device)
                    t_warp = _time(warp_fn, device, args.warmup, args.repeats)
                    t_torch = None
                    if torch_fn is not None:
                        with torch.no_grad():
                            t_torch = _time(torch_fn, device, args.warmup, args.repeats)
                row = dict(kernel=case.name, device=device, batch=batch, warp_s=t_warp, torch_s=t_torch)
                rows.append(row)
                torch_us = "-" if t_torch is None else f"{t_torch * 1e6:.1f}"
                ratio = "-" if t_torch is None else f"{t_torch / t_warp:.2f}"
                print(f"{case.name:<{name_w}} {device:<8} {batch:>6} {t_warp * 1e6:>10.1f} {torch_us:>10} "
                      f"{ratio:>10} {batch / t_warp / 1e6:>12.3f}")
    result = dict(machine=_machine(), warmup=args.warmup, repeats=args.repeats, rows=rows,
                  date=time.strftime("%Y-%m-%d %H:%M:%S"))
    atomic_write_text(out, strict_json(result, indent=2))  # FileExistsError rather than overwrite
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main, "bench_kernels", "nothing was written"))
