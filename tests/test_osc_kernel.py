"""The Warp task-space impedance (OSC) kernel and its torch twin against a float64 numpy reference.

The reference is written here from the formulas (Isaac Lab Factory `compute_dof_torque`, TCP shifted from
the hand COM), independently of the kernel's helpers: quaternion algebra and rotation vectors by scipy's
Rotation, wrapping and the null-space projector spelled out with numpy and literal matrix inverses.
"""

import numpy as np
from quat_ref import random_quats
import pytest
import torch
from scipy.spatial.transform import Rotation

TASK_REG = 1.0e-6  # relative diagonal regularization of J M^-1 J^T, as documented in kernels/osc.py
HAND_LINK = 8  # Newton Franka: link0, link1..7, hand, two fingers -> 11 links, 9 DoF
N_LINKS, N_DOFS = 11, 9
COORDS_PER_WORLD, DOFS_PER_WORLD = 16, 15  # robot (9) + free-jointed peg (7 coords, 6 DoF)
SENTINEL = 12345.0


# ------------------------------------------------------------------ float64 reference


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def reference(inp, kp_null, kd_null, reg=TASK_REG):
    """float64 torques and intermediate quantities per env, from the (float32-rounded) inputs."""
    d = {k: (np.asarray(v, dtype=np.float64) if isinstance(v, np.ndarray) else v) for k, v in inp.items()}
    c0, L = d["arm_dof_start"], d["hand_link"]
    out = dict(tau=[], tau_task=[], tau_null=[], u=[], wrench=[], pos=[], quat=[], twist=[], J=[], M=[])
    for e in range(len(d["robot_articulation"])):
        a, hb = int(d["robot_articulation"][e]), int(d["hand_body"][e])
        p_hand, q_hand = d["body_q"][hb, :3], d["body_q"][hb, 3:]
        R = Rotation.from_quat(q_hand).as_matrix()
        p_tcp = p_hand + R @ d["tcp_offset_hand"]
        r = p_tcp - (p_hand + R @ d["body_com"][hb])
        v_com, w = d["body_qd"][hb, :3], d["body_qd"][hb, 3:]
        v_tcp = v_com + np.cross(w, r)
        Jh = d["jacobian"][a, 6 * L:6 * L + 6, c0:c0 + 7]
        J = np.vstack([Jh[:3] - skew(r) @ Jh[3:], Jh[3:]])
        M = d["mass_matrix"][a, c0:c0 + 7, c0:c0 + 7]
        q_star = d["target_quat_w"][e]
        if q_star @ q_hand < 0:
            q_star = -q_star
        # e_r = axis * angle of q* q^-1, angle in [0, pi] (scipy's rotation vector is the shortest one)
        e_r = (Rotation.from_quat(q_star) * Rotation.from_quat(q_hand).inv()).as_rotvec()
        err = np.concatenate([d["target_pos_w"][e] - p_tcp, e_r])
        F = d["kp"][e] * err - d["kd"][e] * np.concatenate([v_tcp, w])
        dz = d["dead_zone"][e]
        F = np.where(np.abs(F) < dz, 0.0, F - np.sign(F) * dz)
        tau_task = J.T @ F
        dq = d["q_null"] - d["joint_q"][e, d["arm_q_start"]:d["arm_q_start"] + 7]
        dq = (dq + np.pi) % (2 * np.pi) - np.pi
        u = M @ (kp_null * dq - kd_null * d["joint_qd"][e, d["arm_qd_start"]:d["arm_qd_start"] + 7])
        Minv = np.linalg.inv(M)
        A = J @ Minv @ J.T
        Lam = np.linalg.inv(A + reg * np.diag(np.diag(A)))
        tau_null = (np.eye(7) - J.T @ Lam @ J @ Minv) @ u
        tau = np.clip(tau_task + tau_null, -d["torque_limit"], d["torque_limit"])
        for k, v in dict(tau=tau, tau_task=tau_task, tau_null=tau_null, u=u, wrench=F, pos=p_tcp, quat=q_hand,
                         twist=np.concatenate([v_tcp, w]), J=J, M=M).items():
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}


# ------------------------------------------------------------------ random inputs


def random_case(num_envs=8, seed=0, arm_dof_start=0, arm_q_start=0, arm_qd_start=0, dead_zone=False,
                torque_limit=100.0, num_articulations=None):
    """Newton-shaped inputs: each env's robot in a shuffled articulation, hand bodies scattered among
    12 bodies per world, well-conditioned SPD mass matrices and full-rank hand Jacobians."""
    rng = np.random.default_rng(seed)
    n_art = num_articulations or num_envs + 2
    n_dofs = N_DOFS + arm_dof_start
    bodies_per_world = 12
    n_bodies = bodies_per_world * num_envs
    jac = rng.normal(size=(n_art, 6 * N_LINKS, n_dofs))
    mass = np.zeros((n_art, n_dofs, n_dofs))
    for a in range(n_art):
        # hand block: singular values in [0.3, 1.2], lever arms ~0.5 m, like a Franka in its workspace
        u, _, vt = np.linalg.svd(rng.normal(size=(6, 7)), full_matrices=False)
        hand_block = u @ np.diag(rng.uniform(0.3, 1.2, 6)) @ vt
        jac[a, 6 * HAND_LINK:6 * HAND_LINK + 6, arm_dof_start:arm_dof_start + 7] = hand_block
        qm, _ = np.linalg.qr(rng.normal(size=(n_dofs, n_dofs)))
        mass[a] = qm @ np.diag(rng.uniform(0.05, 2.0, n_dofs)) @ qm.T
    body_q = np.concatenate([rng.uniform(-1, 1, (n_bodies, 3)), random_quats(rng, n_bodies)], axis=1)
    hand_body = np.array([w * bodies_per_world + rng.integers(bodies_per_world) for w in range(num_envs)])
    hand_pos = body_q[hand_body, :3]
    target_quat = random_quats(rng, num_envs)
    # half the targets near the hand orientation (small angles), half anywhere (angles up to pi)
    near = body_q[hand_body[: num_envs // 2], 3:] + 0.05 * rng.normal(size=(num_envs // 2, 4))
    target_quat[: num_envs // 2] = near / np.linalg.norm(near, axis=1, keepdims=True)
    kp = np.concatenate([rng.uniform(100, 600, (num_envs, 3)), rng.uniform(20, 40, (num_envs, 3))], axis=1)
    case = dict(
        jacobian=jac,
        mass_matrix=mass,
        robot_articulation=rng.permutation(n_art)[:num_envs].astype(np.int32),
        hand_link=HAND_LINK,
        arm_dof_start=arm_dof_start,
        body_q=body_q,
        body_qd=rng.normal(scale=0.3, size=(n_bodies, 6)),
        body_com=rng.uniform(-0.05, 0.05, (n_bodies, 3)),
        hand_body=hand_body.astype(np.int32),
        tcp_offset_hand=np.array([0.0, 0.0, 0.112071]),
        # q - q_null spans several turns, so the wrap to [-pi, pi] matters
        joint_q=rng.uniform(-8, 8, (num_envs, COORDS_PER_WORLD)),
        joint_qd=rng.normal(size=(num_envs, DOFS_PER_WORLD)),
        arm_q_start=arm_q_start,
        arm_qd_start=arm_qd_start,
        target_pos_w=hand_pos + rng.uniform(-0.05, 0.05, (num_envs, 3)),
        target_quat_w=target_quat,
        kp=kp,
        kd=2.0 * np.sqrt(kp),
        dead_zone=(rng.uniform(0, 5, (num_envs, 6)) if dead_zone else np.zeros((num_envs, 6))),
        q_null=np.array([-1.3003, -0.4015, 1.1791, -2.1493, 0.4001, 1.9425, 0.4754]),
        torque_limit=np.full(7, torque_limit) if np.isscalar(torque_limit) else np.asarray(torque_limit, float),
    )
    # inputs as the kernel sees them: float32-rounded (the reference then computes in float64)
    for k, v in case.items():
        if isinstance(v, np.ndarray) and v.dtype.kind == "f":
            case[k] = v.astype(np.float32)
    # wrap points (q_null - q = +-pi + 2 pi k) are a discontinuity: keep float32 rounding away from them
    dq = case["q_null"] - case["joint_q"][:, arm_q_start:arm_q_start + 7]
    assert np.abs(np.abs((dq.astype(np.float64) + np.pi) % (2 * np.pi) - np.pi) - np.pi).min() > 1e-3
    return case


def run_kernel(wp, case, kp_null, kd_null, joint_f_fill=SENTINEL):
    from vkgrl_newton.kernels.kmp_horizon import vec6f
    from vkgrl_newton.kernels.osc import osc_torques

    e = len(case["robot_articulation"])
    joint_f = wp.array(np.full((e, DOFS_PER_WORLD), joint_f_fill, np.float32), dtype=wp.float32)
    out = dict(tcp_pos_w=wp.zeros(e, dtype=wp.vec3), tcp_quat_w=wp.zeros(e, dtype=wp.quat),
               tcp_twist_w=wp.zeros(e, dtype=wp.spatial_vector), wrench_w=wp.zeros(e, dtype=vec6f))
    arr = lambda k, dtype: wp.array(np.ascontiguousarray(case[k]), dtype=dtype)
    osc_torques(
        jacobian=arr("jacobian", wp.float32),
        mass_matrix=arr("mass_matrix", wp.float32),
        robot_articulation=arr("robot_articulation", wp.int32),
        hand_link=case["hand_link"],
        arm_dof_start=case["arm_dof_start"],
        body_q=arr("body_q", wp.transform),
        body_qd=arr("body_qd", wp.spatial_vector),
        body_com=arr("body_com", wp.vec3),
        hand_body=arr("hand_body", wp.int32),
        tcp_offset_hand=tuple(float(x) for x in case["tcp_offset_hand"]),
        joint_q=arr("joint_q", wp.float32),
        joint_qd=arr("joint_qd", wp.float32),
        arm_q_start=case["arm_q_start"],
        arm_qd_start=case["arm_qd_start"],
        target_pos_w=arr("target_pos_w", wp.vec3),
        target_quat_w=arr("target_quat_w", wp.quat),
        kp=arr("kp", vec6f),
        kd=arr("kd", vec6f),
        dead_zone=arr("dead_zone", vec6f),
        q_null=arr("q_null", wp.float32),
        kp_null=kp_null,
        kd_null=kd_null,
        torque_limit=arr("torque_limit", wp.float32),
        joint_f=joint_f,
        **out,
    )
    res = {k: v.numpy() for k, v in out.items()}
    res["joint_f"] = joint_f.numpy()
    s = case["arm_qd_start"]
    res["tau"] = res["joint_f"][:, s:s + 7]
    return res


def run_torch(case, kp_null, kd_null, dtype=torch.float64):
    from vkgrl_newton.kernels.osc import osc_torques_torch

    t = {k: (torch.as_tensor(v, dtype=dtype) if v.dtype.kind == "f" else torch.as_tensor(v))
         if isinstance(v, np.ndarray) else v for k, v in case.items()}
    joint_f = torch.full((len(case["robot_articulation"]), DOFS_PER_WORLD), SENTINEL, dtype=dtype)
    pos, quat, twist, wrench, tau = osc_torques_torch(**t, kp_null=kp_null, kd_null=kd_null, joint_f=joint_f)
    return dict(tcp_pos_w=pos.numpy(), tcp_quat_w=quat.numpy(), tcp_twist_w=twist.numpy(), wrench_w=wrench.numpy(),
                tau=tau.numpy(), joint_f=joint_f.numpy())


def assert_close(got, want, rel, what):
    """Per env: max |got - want| <= rel * max(|want|, 1) (torques are O(1..100) N m)."""
    err = np.abs(got - want).max(axis=-1)
    scale = np.maximum(np.abs(want).max(axis=-1), 1.0)
    assert (err <= rel * scale).all(), f"{what}: worst relative error {(err / scale).max():.3g}"


NULL_ON = (10.0, 6.3246)  # Factory kp_null, kd_null
CASES = {
    "null_space": dict(kwargs=dict(), null=NULL_ON),
    "no_null_space": dict(kwargs=dict(), null=(0.0, 0.0)),
    "dead_zone_and_offsets": dict(kwargs=dict(dead_zone=True, arm_dof_start=1, arm_q_start=2, arm_qd_start=1, seed=3),
                                  null=NULL_ON),
    "clamped": dict(kwargs=dict(torque_limit=[87, 87, 1.0, 87, 12, 0.5, 12], seed=5), null=NULL_ON),
}


# ------------------------------------------------------------------ tests


@pytest.mark.parametrize("name", list(CASES))
def test_kernel_and_torch_match_float64_reference(wp_cpu, name):
    spec = CASES[name]
    case = random_case(**spec["kwargs"])
    ref = reference(case, *spec["null"])
    got = run_kernel(wp_cpu, case, *spec["null"])
    for impl in (got, run_torch(case, *spec["null"], dtype=torch.float32)):
        assert_close(impl["tcp_pos_w"], ref["pos"], 1e-6, "tcp position")
        assert np.abs(impl["tcp_quat_w"] - ref["quat"]).max() < 1e-6
        assert_close(impl["tcp_twist_w"], ref["twist"], 1e-5, "tcp twist")
        assert_close(impl["wrench_w"], ref["wrench"], 1e-4, "wrench")
        assert_close(impl["tau"], ref["tau"], 1e-4, "torque")
    # the float64 torch twin agrees with the reference to float64 precision (given exactly unit
    # quaternions: the reference inverts and rotates by the normalized quaternion, the kernel by the raw one)
    case64 = {k: (v.astype(np.float64) if isinstance(v, np.ndarray) and v.dtype.kind == "f" else v)
              for k, v in case.items()}
    case64["body_q"][:, 3:] /= np.linalg.norm(case64["body_q"][:, 3:], axis=1, keepdims=True)
    ref64 = reference(case64, *spec["null"])
    t64 = run_torch(case64, *spec["null"], dtype=torch.float64)
    assert_close(t64["tau"], ref64["tau"], 1e-10, "float64 torch torque")
    assert_close(t64["wrench_w"], ref64["wrench"], 1e-10, "float64 torch wrench")
    if name == "clamped":
        lim = case["torque_limit"]
        assert (np.abs(ref["tau_task"] + ref["tau_null"]) > lim).sum() >= 4, "the case must exercise the clamp"
        assert np.all(np.abs(got["tau"]) <= lim)
    if name == "dead_zone_and_offsets":
        assert (ref["wrench"] == 0.0).sum() >= 4, "the case must have components inside the dead zone"


def test_regularization_is_negligible_away_from_singularities():
    """The eps = 1e-6 diagonal regularization moves the torque by about eps * cond(J M^-1 J^T) (~40 for
    these inputs, ~200 for a Franka): well inside the float32 tolerance of the other tests."""
    case = random_case(seed=7)
    reg = reference(case, *NULL_ON)
    exact = reference(case, *NULL_ON, reg=0.0)
    assert_close(reg["tau"], exact["tau"], 1e-4, "regularized vs exact")


def test_target_quaternion_sign_does_not_matter(wp_cpu):
    case = random_case(seed=11)
    flipped = dict(case, target_quat_w=-case["target_quat_w"])
    a, b = run_kernel(wp_cpu, case, *NULL_ON), run_kernel(wp_cpu, flipped, *NULL_ON)
    np.testing.assert_array_equal(a["joint_f"], b["joint_f"])
    np.testing.assert_array_equal(a["wrench_w"], b["wrench_w"])


def test_null_space_off_is_exactly_task_torque(wp_cpu):
    """kp_null = kd_null = 0: the posture inputs (q, qd, q_null, M) have no effect, to the last bit."""
    case = random_case(seed=13)
    other = dict(case, joint_q=case["joint_q"] + 1.0, joint_qd=-case["joint_qd"], q_null=case["q_null"] * 0.5,
                 mass_matrix=case["mass_matrix"] * 3.0)
    a, b = run_kernel(wp_cpu, case, 0.0, 0.0), run_kernel(wp_cpu, other, 0.0, 0.0)
    np.testing.assert_array_equal(a["joint_f"], b["joint_f"])
    ref = reference(case, 0.0, 0.0)
    assert np.abs(ref["tau_null"]).max() == 0.0
    assert_close(a["tau"], np.clip(ref["tau_task"], -case["torque_limit"], case["torque_limit"]), 1e-4, "task torque")


def test_null_space_torque_is_dynamically_consistent():
    """J M^-1 tau_null = 0 up to the eps regularization: the posture task causes no TCP acceleration.
    Measured against J M^-1 u, the TCP acceleration of the unprojected posture torque u = M u0."""
    case = random_case(seed=17)
    ref = reference(case, *NULL_ON)
    for e in range(len(ref["tau"])):
        J, M = ref["J"][e], ref["M"][e]
        leak = J @ np.linalg.solve(M, ref["tau_null"][e])
        unprojected = J @ np.linalg.solve(M, ref["u"][e])
        assert np.abs(unprojected).max() > 1.0  # a real posture command, not a trivial zero
        assert np.abs(leak).max() <= 1e-5 * np.abs(unprojected).max(), e


def zero_error_case(wp, seed):
    """Targets = the kernel's own TCP pose, hand at rest: the task wrench is (nearly) zero."""
    case = random_case(seed=seed, torque_limit=[87, 87, 87, 87, 12, 12, 2.0])
    case["body_qd"] = np.zeros_like(case["body_qd"])
    first = run_kernel(wp, case, 0.0, 0.0)
    case["target_pos_w"] = first["tcp_pos_w"]
    case["target_quat_w"] = first["tcp_quat_w"]
    return case


def test_zero_error_env_gives_clamped_null_torque_only(wp_cpu):
    case = zero_error_case(wp_cpu, seed=19)
    got = run_kernel(wp_cpu, case, *NULL_ON)
    ref = reference(case, *NULL_ON)
    assert np.abs(got["wrench_w"][:, :3]).max() == 0.0  # the same float32 TCP position
    assert np.abs(got["wrench_w"][:, 3:]).max() < 1e-4  # q q^-1 is identity up to float32 rounding
    assert np.abs(ref["tau_task"]).max() < 1e-4
    lim = case["torque_limit"]
    assert_close(got["tau"], np.clip(ref["tau_null"], -lim, lim), 1e-4, "null torque")
    assert (np.abs(ref["tau_null"]) > lim).any(), "the clamp should be active somewhere"
    # dynamic consistency of the kernel's own (float32, unclamped) null torque
    unclamped = dict(case, torque_limit=np.full(7, 1e9, np.float32))
    tau_null = run_kernel(wp_cpu, unclamped, *NULL_ON)["tau"].astype(np.float64)
    for e in range(len(tau_null)):
        J, M = ref["J"][e], ref["M"][e]
        leak = J @ np.linalg.solve(M, tau_null[e])
        unprojected = J @ np.linalg.solve(M, ref["u"][e])
        assert np.abs(leak).max() <= 1e-3 * np.abs(unprojected).max(), e


def test_only_arm_columns_of_joint_f_are_written(wp_cpu):
    case = random_case(seed=23, arm_qd_start=3)
    got = run_kernel(wp_cpu, case, *NULL_ON)
    cols = np.zeros(DOFS_PER_WORLD, bool)
    cols[3:10] = True
    assert np.all(got["joint_f"][:, ~cols] == SENTINEL)
    assert np.all(got["joint_f"][:, cols] != SENTINEL)
    ref = reference(case, *NULL_ON)
    assert_close(got["joint_f"][:, cols], ref["tau"], 1e-4, "torque")


def test_small_rotation_errors_are_smooth(wp_cpu):
    """Orientation errors from 0 to 1e-2 rad (both sides of the series threshold) match the reference."""
    num_envs = 32
    case = random_case(num_envs=num_envs, seed=29)
    rng = np.random.default_rng(0)
    angles = np.concatenate([[0.0], np.logspace(-8, -2, num_envs - 1)])
    axes = rng.normal(size=(num_envs, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    dq = np.concatenate([axes * np.sin(angles / 2)[:, None], np.cos(angles / 2)[:, None]], axis=1)
    q_hand = case["body_q"][case["hand_body"], 3:].astype(np.float64)
    case["target_quat_w"] = (Rotation.from_quat(dq) * Rotation.from_quat(q_hand)).as_quat().astype(np.float32)
    case["kp"][:, :3] = 0.0  # rotation only
    case["kd"][:] = 0.0
    got = run_kernel(wp_cpu, case, 0.0, 0.0)
    ref = reference(case, 0.0, 0.0)
    # the float32-rounded target carries ~6e-8 rad of its own, so compare absolutely
    assert np.abs(got["wrench_w"][:, 3:] - ref["wrench"][:, 3:]).max() < 40 * 1e-6
    assert np.isfinite(got["joint_f"]).all()


def test_rejects_mismatched_shapes(wp_cpu):
    case = random_case(seed=31)
    with pytest.raises(ValueError, match="hand_body"):
        run_kernel(wp_cpu, dict(case, hand_body=case["hand_body"][:-1]), *NULL_ON)
    with pytest.raises(ValueError, match="arm_qd_start"):
        run_kernel(wp_cpu, dict(case, arm_qd_start=DOFS_PER_WORLD - 6), *NULL_ON)


def test_singular_hand_jacobian_gives_finite_bounded_torque(wp_cpu):
    """Rank-5 hand Jacobian (a kinematic singularity): the regularized task matrix keeps the Cholesky
    finite and the kernel still follows the (equally regularized) float64 reference."""
    case = random_case(seed=37)
    jac = case["jacobian"].astype(np.float64)
    for a in case["robot_articulation"]:
        block = jac[a, 6 * HAND_LINK:6 * HAND_LINK + 6, :7]
        u, s, vt = np.linalg.svd(block, full_matrices=False)
        s[-1] = 0.0
        jac[a, 6 * HAND_LINK:6 * HAND_LINK + 6, :7] = u @ np.diag(s) @ vt
    case["jacobian"] = jac.astype(np.float32)
    got = run_kernel(wp_cpu, case, *NULL_ON)
    ref = reference(case, *NULL_ON)
    assert np.isfinite(got["joint_f"]).all()
    assert_close(got["tau"], ref["tau"], 1e-3, "torque at a singularity")


# ------------------------------------------------------------------ against Newton on a Franka model


@pytest.fixture(scope="module")
def franka(wp_cpu):
    """Six Franka worlds (Newton model from vkgrl_newton/tools/bench_kernels.py) with their Jacobian and mass matrix."""
    newton = pytest.importorskip("newton")
    from vkgrl_newton.tools.bench_kernels import franka_model

    model, state = franka_model(6, "cpu", seed=1)
    jac = newton.eval_jacobian(model, state)
    mass = newton.eval_mass_matrix(model, state, J=jac)
    return model, state, jac, mass


def run_on_franka(wp, franka, kp, kd, kp_null, kd_null, tcp=0.1034, seed=0):
    from vkgrl_newton.assets_usd.dimensions import FACTORY_NULL_JOINTS
    from vkgrl_newton.kernels.kmp_horizon import vec6f
    from vkgrl_newton.kernels.osc import osc_torques

    model, state, jac, mass = franka
    e = model.articulation_count
    hand_body = np.arange(e, dtype=np.int32) * N_LINKS + HAND_LINK
    rng = np.random.default_rng(seed)
    hand = state.body_q.numpy()[hand_body]
    target_pos = hand[:, :3] + rng.uniform(-0.03, 0.03, (e, 3))
    target_quat = hand[:, 3:] + 0.15 * rng.normal(size=(e, 4))
    target_quat /= np.linalg.norm(target_quat, axis=1, keepdims=True)
    control = model.control()
    out = dict(tcp_pos_w=wp.zeros(e, dtype=wp.vec3), tcp_quat_w=wp.zeros(e, dtype=wp.quat),
               tcp_twist_w=wp.zeros(e, dtype=wp.spatial_vector), wrench_w=wp.zeros(e, dtype=vec6f))
    osc_torques(
        jacobian=jac, mass_matrix=mass, robot_articulation=wp.array(np.arange(e, dtype=np.int32)),
        hand_link=HAND_LINK, arm_dof_start=0, body_q=state.body_q, body_qd=state.body_qd,
        body_com=model.body_com, hand_body=wp.array(hand_body), tcp_offset_hand=(0.0, 0.0, tcp),
        joint_q=state.joint_q.reshape((e, N_DOFS)), joint_qd=state.joint_qd.reshape((e, N_DOFS)),
        arm_q_start=0, arm_qd_start=0, target_pos_w=wp.array(target_pos, dtype=wp.vec3),
        target_quat_w=wp.array(target_quat, dtype=wp.quat), kp=wp.array(np.tile(kp, (e, 1)), dtype=vec6f),
        kd=wp.array(np.tile(kd, (e, 1)), dtype=vec6f), dead_zone=wp.zeros(e, dtype=vec6f),
        q_null=wp.array(np.array(FACTORY_NULL_JOINTS, np.float32)), kp_null=kp_null, kd_null=kd_null,
        torque_limit=wp.array(np.full(7, 1e9, np.float32)), joint_f=control.joint_f.reshape((e, N_DOFS)), **out)
    res = {k: v.numpy() for k, v in out.items()}
    res["tau"] = control.joint_f.numpy().reshape(e, N_DOFS)
    res["target"] = np.concatenate([target_pos, target_quat], axis=1).astype(np.float32)
    return res


def newton_controller(wp, franka, target, **kwargs):
    from newton.controllers import ControllerOperationalSpace

    from vkgrl_newton.assets_usd.dimensions import FACTORY_NULL_JOINTS

    model, state, _, _ = franka
    osc = ControllerOperationalSpace(model, joints=[f"joint{i}" for i in range(1, 8)], tool_sites="tool_site",
                                     use_gravity_compensation=False, **kwargs)
    control = model.control()
    inp, out = osc.input(), osc.output()
    out.joint_f = control.joint_f[osc.qd_start]
    inp.joint_q, inp.joint_qd = state.joint_q, state.joint_qd
    inp.desired_tool_pose_operational.assign(target)
    if inp.joint_q_des_null is not None:
        inp.joint_q_des_null.assign(np.tile(np.array(FACTORY_NULL_JOINTS, np.float32), model.articulation_count))
    osc.step(inputs=inp, outputs=out, dt=0.01)
    return osc, control.joint_f.numpy().reshape(model.articulation_count, N_DOFS)


def test_franka_model_conventions(franka):
    """The bench's Franka: hand at (0.088, 0, 0.926) at q = 0; J_hand qd = body_qd[hand] (COM linear
    velocity, angular velocity, world); the fingers do not move the hand."""
    import newton

    from vkgrl_newton.tools.bench_kernels import franka_builder

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.replicate(franka_builder(), 1)
    model0 = builder.finalize("cpu")
    state0 = model0.state()
    newton.eval_fk(model0, state0.joint_q, state0.joint_qd, state0)
    assert np.abs(state0.body_q.numpy()[HAND_LINK, :3] - [0.088, 0.0, 0.926]).max() < 1e-5

    model, state, jac, _ = franka
    assert jac.shape == (6, 6 * N_LINKS, N_DOFS)
    hand_rows = jac.numpy()[:, 6 * HAND_LINK:6 * HAND_LINK + 6]
    qd = state.joint_qd.numpy().reshape(6, N_DOFS)
    hand_body = np.arange(6) * N_LINKS + HAND_LINK
    assert np.abs(np.einsum("eij,ej->ei", hand_rows, qd) - state.body_qd.numpy()[hand_body]).max() < 1e-6
    assert np.abs(hand_rows[:, :, 7:]).max() == 0.0


def test_task_torque_matches_newton_controller(wp_cpu, franka):
    """Without null space and inertia decoupling, Newton's ControllerOperationalSpace computes the same
    J^T (Kp e - Kd v) at its tool site: same TCP pose and twist, same torques."""
    kp = np.array([300, 300, 300, 30, 30, 30], np.float32)
    kd = 2.0 * np.sqrt(kp)
    ours = run_on_franka(wp_cpu, franka, kp, kd, 0.0, 0.0)
    osc, tau = newton_controller(wp_cpu, franka, ours["target"], motion_stiffness=wp_cpu.spatial_vector(*kp),
                                 motion_damping=wp_cpu.spatial_vector(*kd), use_inertia_decoupling=False)
    assert np.abs(osc.tool_pose_world.numpy()[:, :3] - ours["tcp_pos_w"]).max() < 1e-6
    assert np.abs(osc.tool_pose_world.numpy()[:, 3:] - ours["tcp_quat_w"]).max() < 1e-6
    assert np.abs(osc.tool_twist_world.numpy() - ours["tcp_twist_w"]).max() < 1e-6
    assert np.abs(ours["tau"]).max() > 1.0
    assert_close(ours["tau"], tau, 1e-5, "task torque vs Newton")


def test_null_torque_matches_newton_controller(wp_cpu, franka):
    """Zero task gains: our null-space torque equals Newton's dynamically consistent null-space posture
    term N^T M (Kp_null (q_null - q) - Kd_null qd) (inertia decoupling on), within the regularization."""
    zeros = np.zeros(6, np.float32)
    ours = run_on_franka(wp_cpu, franka, zeros, zeros, 10.0, 6.3246)
    _, tau = newton_controller(wp_cpu, franka, ours["target"], motion_stiffness=0.0, motion_damping=0.0,
                               use_inertia_decoupling=True, use_null_space_control=True,
                               null_space_stiffness=10.0, null_space_damping=6.3246)
    assert np.abs(ours["tau"]).max() > 1.0
    assert_close(ours["tau"], tau, 3e-5, "null torque vs Newton")
