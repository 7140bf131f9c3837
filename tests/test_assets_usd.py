"""The authored USD stages (assets_usd/author.py) against the published Franka facts and brute force.

References, all independent of author.py's own tables: the modified-DH table and limits of Franka's
interface specification and the inertial table of Gaz et al. (RA-L 2019) (transcribed below), a float64
modified-DH forward kinematics written here (Craig convention), scipy's Rotation for quaternions, and a
brute-force point-in-box test of the socket's collision boxes.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

# ------------------------------------------------------------------ published facts (Franka, Gaz et al.)

# Craig / modified DH, one row per joint: (a_{i-1}, d_i, alpha_{i-1}), then the flange
DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
]
FLANGE_D = 0.107
HAND_YAW = -math.pi / 4  # hand frame: -45 degrees about the flange z
FINGER_Z = 0.0584  # finger frames along the hand z
TCP_Z = 0.112071  # Isaac Lab Factory's panda_fingertip_centered, along the hand z
ARM_LIMITS = [
    (-2.8973, 2.8973),
    (-1.7628, 1.7628),
    (-2.8973, 2.8973),
    (-3.0718, -0.0698),
    (-2.8973, 2.8973),
    (-0.0175, 3.7525),
    (-2.8973, 2.8973),
]
ARM_VEL = [2.175] * 4 + [2.61] * 3
ARM_EFFORT = [87.0] * 4 + [12.0] * 3
ARMATURE = [0.3] * 4 + [0.11] * 3 + [0.15] * 2  # Isaac Lab Newton Factory port
FINGER_RANGE = (0.0, 0.04)
# body: (mass, COM, (ixx, iyy, izz, ixy, ixz, iyz)) about the COM, body frame
INERTIAL = {
    "link0": (0.629769, (-0.041018, -0.00014, 0.049974), (0.00315, 0.00388, 0.004285, 8.2904e-7, 0.00015, 8.2299e-6)),
    "link1": (4.970684, (0.003875, 0.002081, -0.04762), (0.70337, 0.70661, 0.009117, -0.000139, 0.006772, 0.019169)),
    "link2": (0.646926, (-0.003141, -0.02872, 0.003495), (0.007962, 0.02811, 0.025995, -0.003925, 0.010254, 0.000704)),
    "link3": (3.228604, (0.027518, 0.039252, -0.066502),
              (0.037242, 0.036155, 0.01083, -0.004761, -0.011396, -0.012805)),
    "link4": (3.587895, (-0.05317, 0.104419, 0.027454), (0.025853, 0.019552, 0.028323, 0.007796, -0.001332, 0.008641)),
    "link5": (1.225946, (-0.011953, 0.041065, -0.038437),
              (0.035549, 0.029474, 0.008627, -0.002117, -0.004037, 0.000229)),
    "link6": (1.666555, (0.060149, -0.014117, -0.010517), (0.001964, 0.004354, 0.005433, 0.000109, -0.001158, 0.000341)),
    "link7": (0.735522, (0.010517, -0.004252, 0.061597),
              (0.012516, 0.010027, 0.004815, -0.000428, -0.001196, -0.000741)),
    "hand": (0.73, (-0.01, 0.0, 0.03), (0.001, 0.0025, 0.0017, 0.0, 0.0, 0.0)),
    "left_finger": (0.015, (0.0, 0.0, 0.0), (2.375e-6, 2.375e-6, 7.5e-7, 0.0, 0.0, 0.0)),
    "right_finger": (0.015, (0.0, 0.0, 0.0), (2.375e-6, 2.375e-6, 7.5e-7, 0.0, 0.0, 0.0)),
}
BODY_NAMES = ["link0", "link1", "link2", "link3", "link4", "link5", "link6", "link7", "hand", "left_finger",
              "right_finger"]

# PegInsert (Isaac Lab Factory Peg8mm / Hole8mm, 16-gon hole as documented in author.py)
PEG_RADIUS = 0.007986 / 2
PEG_HALF_LENGTH = 0.025
PEG_MASS = 0.019
HOLE_APOTHEM = 0.0081 / 2
HOLE_DEPTH = 0.025
HOLE_SEGMENTS = 16
CHAMFER = 0.00075


# ------------------------------------------------------------------ float64 helpers


def tensor6(i6):
    ixx, iyy, izz, ixy, ixz, iyz = i6
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=np.float64)


def quat_xyzw_to_matrix(q):
    """Rotation matrix of a (not necessarily normalized) xyzw quaternion, by scipy."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    t = np.eye(4)
    t[1:3, 1:3] = [[c, -s], [s, c]]
    return t


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    t = np.eye(4)
    t[0:2, 0:2] = [[c, -s], [s, c]]
    return t


def trans(x=0.0, y=0.0, z=0.0):
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def dh_forward(q_arm, q_finger):
    """World frames of link0..7, hand, fingers and TCP by the modified-DH table (float64 4x4)."""
    frames = {"link0": np.eye(4)}
    t = np.eye(4)
    for i, (a, d, alpha) in enumerate(DH):
        t = t @ rot_x(alpha) @ trans(x=a) @ rot_z(q_arm[i]) @ trans(z=d)
        frames[f"link{i + 1}"] = t
    hand = t @ trans(z=FLANGE_D) @ rot_z(HAND_YAW)
    frames["hand"] = hand
    frames["left_finger"] = hand @ trans(z=FINGER_Z) @ trans(y=q_finger)
    frames["right_finger"] = hand @ trans(z=FINGER_Z) @ rot_z(math.pi) @ trans(y=q_finger)
    frames["tcp"] = hand @ trans(z=TCP_Z)
    return frames


def pose_to_matrix(p, q_xyzw):
    t = np.eye(4)
    t[:3, :3] = quat_xyzw_to_matrix(q_xyzw)
    t[:3, 3] = np.asarray(p, dtype=np.float64)
    return t


def rotation_angle(r_a, r_b):
    """Angle (rad) of r_a^T r_b, robust near zero."""
    d = r_a.T @ r_b
    s = 0.5 * np.linalg.norm([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
    c = 0.5 * (np.trace(d) - 1.0)
    return math.atan2(s, c)


# ------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def author(wp_cpu):
    # Newton registers its USD schemas (newton_usd_schemas) when it is imported. pxr must not build its schema
    # registry before that, or NewtonMimicAPI is silently ignored on load (see the import-order tests below);
    # import Newton first so that this process's order is fixed. Authoring itself runs in fresh processes.
    import newton  # noqa: F401

    from vkgrl_newton.assets_usd import author as author_module

    return author_module


@pytest.fixture(scope="module")
def franka_builder(wp_cpu):
    import newton

    from vkgrl_newton.assets_usd import FRANKA_USD

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_usd(str(FRANKA_USD), enable_self_collisions=False)
    return builder


@pytest.fixture(scope="module")
def peg_builder(wp_cpu):
    import newton

    from vkgrl_newton.assets_usd import TASK_USD

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_usd(str(TASK_USD["PegInsert"]))
    return builder


def _index(labels, name):
    hits = [i for i, lbl in enumerate(labels) if lbl.split("/")[-1] == name]
    assert len(hits) == 1, (name, labels)
    return hits[0]


# ------------------------------------------------------------------ authoring (fresh processes)


def _run_python(args, code=None, timeout=300):
    import os
    import subprocess
    import sys

    cmd = [sys.executable] + (["-c", code] if code is not None else []) + list(args)
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="")
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)


def _author_script():
    from vkgrl_newton.assets_usd import ASSET_DIR

    return str(ASSET_DIR / "author.py")


def test_committed_stages_match_author_script():
    out = _run_python([_author_script(), "--check"])
    assert out.returncode == 0, out.stderr[-2000:]


def test_stage_comparison_allows_only_last_bit_differences():
    from vkgrl_newton.assets_usd.author import same_stage_text

    a = "double height = 0.21540659228538017\nquatd q = (0.6943480198872283, -0.13371921058204456)\n"
    assert same_stage_text(a, a.replace("0.21540659228538017", "0.2154065922853802"))  # 2 ulps
    assert same_stage_text(a, a.replace("-0.13371921058204456", "-0.13371921058204453"))
    assert not same_stage_text(a, a.replace("0.21540659228538017", "0.21540659228638017"))  # 1e-12 m off
    assert not same_stage_text(a, a.replace("height", "radius"))
    assert not same_stage_text(a, a.replace("0.6943480198872283, ", ""))  # a number missing


def test_authoring_is_deterministic_and_equals_committed(tmp_path):
    from vkgrl_newton.assets_usd import ASSET_DIR

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    for d in (a, b):
        out = _run_python([_author_script(), "--out-dir", str(d)])
        assert out.returncode == 0, out.stderr[-2000:]
    from vkgrl_newton.assets_usd.author import same_stage_text

    for name in ("franka_panda.usda", "peg_insert.usda"):
        first, second = (a / name).read_bytes(), (b / name).read_bytes()
        assert first == second, f"{name}: two authoring runs differ"
        # the committed stage, up to the float64 last bits that differ between CPU vendors
        assert same_stage_text(first.decode(), (ASSET_DIR / name).read_text()), f"{name}: committed stage differs"
        assert first.startswith(b"#usda 1.0\n")


# Regression: Newton's USD schemas must be registered (assets_usd imports newton_usd_schemas) before
# pxr is used, or the authored text differs and a stage loaded early loses the finger mimic.

CHECK_AFTER_NEWTON = """
import sys
import newton  # registers newton_usd_schemas
from vkgrl_newton.assets_usd import author
sys.exit(author.main(["--check"]))
"""

MIMIC_AFTER_PXR = """
from vkgrl_newton.assets_usd import author
author.author_franka()  # pxr stage work that consults the schema registry, before newton is imported
import newton
from vkgrl_newton.assets_usd import FRANKA_USD
b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
b.add_usd(str(FRANKA_USD), enable_self_collisions=False)
right = b.joint_label.index("/franka/joints/right_finger")
print("MIMIC", b.joint_mimic_joint[right], b.joint_label.index("/franka/joints/left_finger"))
"""


def test_authored_text_does_not_depend_on_newton_import():
    out = _run_python([], code=CHECK_AFTER_NEWTON)
    assert out.returncode == 0, out.stderr[-2000:]


def test_mimic_survives_pxr_used_before_newton():
    out = _run_python([], code=MIMIC_AFTER_PXR)
    assert out.returncode == 0, out.stderr[-2000:]
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("MIMIC")][-1]
    follower_ref, left = (int(v) for v in line.split()[1:])
    assert follower_ref == left


# ------------------------------------------------------------------ Franka: structure and parameters


def test_franka_bodies_joints_and_parameters(franka_builder):
    import newton

    b = franka_builder
    assert [lbl.split("/")[-1] for lbl in b.body_label] == BODY_NAMES
    types = list(b.joint_type)
    assert types.count(newton.JointType.REVOLUTE) == 7
    assert types.count(newton.JointType.PRISMATIC) == 2
    assert types.count(newton.JointType.FIXED) == 2
    assert len(types) == 11
    names = [lbl.split("/")[-1] for lbl in b.joint_label]
    for i in range(1, 8):
        j = names.index(f"joint{i}")
        assert b.joint_type[j] == newton.JointType.REVOLUTE
        assert b.joint_child[j] == BODY_NAMES.index(f"link{i}")
        assert b.joint_parent[j] == BODY_NAMES.index(f"link{i - 1}")
    for finger in ("left_finger", "right_finger"):
        j = names.index(finger)
        assert b.joint_type[j] == newton.JointType.PRISMATIC
        assert b.joint_parent[j] == BODY_NAMES.index("hand")
        assert b.joint_child[j] == BODY_NAMES.index(finger)
        np.testing.assert_allclose(np.array(b.joint_axis[b.joint_qd_start[j]]), [0.0, 1.0, 0.0], atol=1e-7)

    # masses and COMs (published table)
    for k, name in enumerate(BODY_NAMES):
        mass, com, _ = INERTIAL[name]
        assert abs(b.body_mass[k] - mass) < 1e-6, name
        np.testing.assert_allclose(np.array(b.body_com[k], dtype=np.float64), com, atol=1e-6, err_msg=name)

    # per-DoF parameters: 7 arm DoF then left, right finger
    assert b.joint_dof_count == 9
    lower = np.array(b.joint_limit_lower, dtype=np.float64)
    upper = np.array(b.joint_limit_upper, dtype=np.float64)
    np.testing.assert_allclose(lower[:7], [lo for lo, _ in ARM_LIMITS], atol=1e-6)  # radians, not degrees
    np.testing.assert_allclose(upper[:7], [hi for _, hi in ARM_LIMITS], atol=1e-6)
    np.testing.assert_allclose(lower[7:], [FINGER_RANGE[0]] * 2, atol=1e-7)
    np.testing.assert_allclose(upper[7:], [FINGER_RANGE[1]] * 2, atol=1e-7)
    np.testing.assert_allclose(np.array(b.joint_velocity_limit[:7]), ARM_VEL, rtol=1e-6)
    np.testing.assert_allclose(np.array(b.joint_effort_limit[:7]), ARM_EFFORT, rtol=1e-7)
    np.testing.assert_allclose(np.array(b.joint_effort_limit[7:]), [70.0, 70.0], rtol=1e-7)  # continuous grasp force
    np.testing.assert_allclose(np.array(b.joint_armature), ARMATURE, rtol=1e-6)
    # arm: torque control (zero drive gains); fingers: position drive ke 2000 N/m, kd 20 N s/m
    np.testing.assert_array_equal(np.array(b.joint_target_ke[:7]), 0.0)
    np.testing.assert_array_equal(np.array(b.joint_target_kd[:7]), 0.0)
    np.testing.assert_allclose(np.array(b.joint_target_ke[7:]), [2000.0, 2000.0], rtol=1e-7)
    np.testing.assert_allclose(np.array(b.joint_target_kd[7:]), [20.0, 20.0], rtol=1e-7)

    # the right finger mimics the left one: q_right = 0 + 1 * q_left
    left, right = names.index("left_finger"), names.index("right_finger")
    assert b.joint_mimic_joint[right] == left
    assert b.joint_mimic_joint[left] == -1
    np.testing.assert_allclose(np.array(b.joint_mimic_coeffs[right], dtype=np.float64), [0.0, 1.0], atol=1e-7)


def test_franka_tcp_site(franka_builder):
    import newton

    b = franka_builder
    s = _index(b.shape_label, "tcp")
    assert b.shape_body[s] == BODY_NAMES.index("hand")
    assert b.shape_flags[s] & int(newton.ShapeFlags.SITE)
    assert not b.shape_flags[s] & int(newton.ShapeFlags.COLLIDE_SHAPES)
    tf = np.array(b.shape_transform[s], dtype=np.float64)
    np.testing.assert_allclose(tf[:3], [0.0, 0.0, TCP_Z], atol=1e-7)
    assert rotation_angle(np.eye(3), quat_xyzw_to_matrix(tf[3:])) < 1e-6


def test_franka_inertia_reproduces_published_tensor(franka_builder):
    """Principal moments/axes (USD MassAPI) and Newton's body_inertia both give R diag(I) R^T = table."""
    from pxr import Usd, UsdPhysics

    from vkgrl_newton.assets_usd import FRANKA_USD

    stage = Usd.Stage.Open(str(FRANKA_USD))
    for k, name in enumerate(BODY_NAMES):
        expected = tensor6(INERTIAL[name][2])
        tol = 1e-6 * np.abs(expected).max()
        api = UsdPhysics.MassAPI(stage.GetPrimAtPath(f"/franka/{name}"))
        moments = np.array(api.GetDiagonalInertiaAttr().Get(), dtype=np.float64)
        q = api.GetPrincipalAxesAttr().Get()  # Gf.Quatf, (w, (x, y, z))
        r = quat_xyzw_to_matrix([*q.GetImaginary(), q.GetReal()])
        assert np.all(moments > 0), name
        np.testing.assert_allclose(r @ np.diag(moments) @ r.T, expected, atol=tol, err_msg=f"USD {name}")
        newton_i = np.array(franka_builder.body_inertia[k], dtype=np.float64).reshape(3, 3)
        np.testing.assert_allclose(newton_i, expected, atol=tol, err_msg=f"Newton {name}")


def test_franka_forward_kinematics_matches_modified_dh(franka_builder):
    """Newton eval_fk (1 world, CPU) vs a float64 modified-DH chain, several configurations within limits."""
    import newton
    import warp as wp

    model = franka_builder.finalize(device="cpu")
    state = model.state()
    tcp_site = _index(franka_builder.shape_label, "tcp")
    tcp_local = np.array(model.shape_transform.numpy()[tcp_site], dtype=np.float64)
    rng = np.random.default_rng(20240611)
    lo = np.array([lim[0] for lim in ARM_LIMITS])
    hi = np.array([lim[1] for lim in ARM_LIMITS])
    configs = [np.zeros(7), np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])]  # zero, Menagerie home
    configs += [rng.uniform(lo, hi) for _ in range(6)]
    for n, q_arm in enumerate(configs):
        q_finger = float(rng.uniform(*FINGER_RANGE))
        q = np.concatenate([q_arm, [q_finger, q_finger]]).astype(np.float32)
        joint_q = wp.array(q, dtype=wp.float32, device="cpu")
        joint_qd = wp.zeros(model.joint_dof_count, dtype=wp.float32, device="cpu")
        newton.eval_fk(model, joint_q, joint_qd, state)
        body_q = state.body_q.numpy().astype(np.float64)
        ref = dh_forward(q.astype(np.float64)[:7], float(q[7]))
        # float32 Newton FK against float64 DH: up to 9 chained transforms of positions <~ 1 m, each ~10 roundings
        # of 6e-8 plus the joint angle's float32 sin/cos: worst case (all adding up) ~5e-6 m or rad; 1e-5 bounds it
        for k, name in enumerate(BODY_NAMES):
            got = pose_to_matrix(body_q[k, :3], body_q[k, 3:])
            dp = np.linalg.norm(got[:3, 3] - ref[name][:3, 3])
            dr = rotation_angle(got[:3, :3], ref[name][:3, :3])
            assert dp < 1e-5 and dr < 1e-5, f"config {n}, {name}: position error {dp:.2e} m, rotation {dr:.2e} rad"
        hand = pose_to_matrix(body_q[8, :3], body_q[8, 3:])
        tcp = hand @ pose_to_matrix(tcp_local[:3], tcp_local[3:])
        assert np.linalg.norm(tcp[:3, 3] - ref["tcp"][:3, 3]) < 1e-5, f"config {n}: TCP"
        assert rotation_angle(tcp[:3, :3], ref["tcp"][:3, :3]) < 1e-5, f"config {n}: TCP orientation"


# ------------------------------------------------------------------ PegInsert stage


def test_peg_body(peg_builder):
    import newton

    b = peg_builder
    assert [lbl.split("/")[-1] for lbl in b.body_label] == ["peg"]
    assert list(b.joint_type) == [newton.JointType.FREE]
    assert abs(b.body_mass[0] - PEG_MASS) < 1e-7
    np.testing.assert_allclose(np.array(b.body_com[0]), [0.0, 0.0, PEG_HALF_LENGTH], atol=1e-7)  # origin: bottom face
    # solid cylinder about its COM (closed form)
    i_axial = 0.5 * PEG_MASS * PEG_RADIUS**2
    i_trans = PEG_MASS * (3 * PEG_RADIUS**2 + (2 * PEG_HALF_LENGTH) ** 2) / 12
    np.testing.assert_allclose(np.array(b.body_inertia[0], dtype=np.float64).reshape(3, 3),
                               np.diag([i_trans, i_trans, i_axial]), rtol=1e-5, atol=1e-12)
    cyl = [s for s in range(len(b.shape_label)) if b.shape_body[s] == 0]
    assert len(cyl) == 1
    s = cyl[0]
    assert b.shape_type[s] == newton.GeoType.CYLINDER
    np.testing.assert_allclose(np.array(b.shape_scale[s])[:2], [PEG_RADIUS, PEG_HALF_LENGTH], atol=1e-8)
    tf = np.array(b.shape_transform[s], dtype=np.float64)
    np.testing.assert_allclose(tf[:3], [0.0, 0.0, PEG_HALF_LENGTH], atol=1e-8)  # spans z in [0, 0.05]
    assert rotation_angle(np.eye(3), quat_xyzw_to_matrix(tf[3:])) < 1e-6
    # the table: 1.2 x 0.6 x 0.04 m, top at z = 0
    t = _index(b.shape_label, "top")
    assert b.shape_body[t] == -1 and b.shape_type[t] == newton.GeoType.BOX
    half = np.array(b.shape_scale[t], dtype=np.float64)
    top = np.array(b.shape_transform[t][:3], dtype=np.float64)[2] + half[2]
    np.testing.assert_allclose(half, [0.6, 0.3, 0.02], atol=1e-7)
    assert abs(top) < 1e-7


def _socket_boxes(builder, nominal_pos):
    """(centres, rotations, half extents) of the socket boxes in the socket frame, float64."""
    import newton

    idx = [s for s, lbl in enumerate(builder.shape_label) if "/socket/" in lbl]
    assert len(idx) == 3 * HOLE_SEGMENTS + 1
    centres, rots, halves = [], [], []
    for s in idx:
        assert builder.shape_body[s] == -1
        assert builder.shape_type[s] == newton.GeoType.BOX
        tf = np.array(builder.shape_transform[s], dtype=np.float64)
        centres.append(tf[:3] - np.asarray(nominal_pos, dtype=np.float64))  # socket frame: identity rotation
        rots.append(quat_xyzw_to_matrix(tf[3:]))
        halves.append(np.array(builder.shape_scale[s], dtype=np.float64))
    return np.array(centres), np.array(rots), np.array(halves)


def _inside_any_box(points, boxes):
    """(P,) bool: point inside (or on) at least one box. points (P, 3) in the socket frame."""
    centres, rots, halves = boxes
    local = np.einsum("bji,bpj->bpi", rots, points[None, :, :] - centres[:, None, :])  # R^T (p - c)
    return np.all(np.abs(local) <= halves[:, None, :], axis=-1).any(axis=0)


def _ring(radius, z, n_angles=720):
    ang = np.linspace(0.0, 2 * math.pi, n_angles, endpoint=False)
    return np.stack([radius * np.cos(ang), radius * np.sin(ang), np.full_like(ang, z)], -1), ang


def test_socket_hole_clear_for_peg_and_tight_beyond(author, peg_builder):
    from vkgrl_newton.assets_usd.dimensions import FIXED_ASSET_NOMINAL_POS

    boxes = _socket_boxes(peg_builder, FIXED_ASSET_NOMINAL_POS)

    # the peg's surface, over the hole depth (below the chamfer foot at 24.25 mm and into it)
    for z in np.linspace(0.0005, 0.0245, 25):
        pts, _ = _ring(PEG_RADIUS, z)
        assert not _inside_any_box(pts, boxes).any(), f"peg surface at z={z:.4f} intersects the socket"
    # the axis itself is free down to the hole bottom
    axis = np.stack([np.zeros(50), np.zeros(50), np.linspace(0.0001, 0.03, 50)], -1)
    assert not _inside_any_box(axis, boxes).any()

    # between the 16-gon's apothem (4.05 mm) and circumradius (4.129 mm): inside the wall exactly where
    # the 16-gon says (r cos(angle to the nearest flat normal) > apothem), i.e. at most angles
    r = 0.00410
    flat_half = math.pi / HOLE_SEGMENTS
    for z in np.linspace(0.001, 0.023, 12):
        pts, ang = _ring(r, z)
        hit = _inside_any_box(pts, boxes)
        rel = (ang + flat_half) % (2 * flat_half) - flat_half  # flat normals at 2 pi k / 16
        predicted = r * np.cos(rel) > HOLE_APOTHEM
        assert hit.mean() > 0.7, f"z={z:.4f}: only {hit.mean():.0%} of the ring at r={r} hits the wall"
        margin = np.abs(r * np.cos(rel) - HOLE_APOTHEM) > 2e-7
        np.testing.assert_array_equal(hit[margin], predicted[margin], err_msg=f"z={z:.4f}: not a 16-gon")

    # beyond the circumradius every angle is blocked, up to the chamfer foot
    for z in np.linspace(0.001, 0.024, 12):
        pts, _ = _ring(HOLE_APOTHEM / math.cos(flat_half) + 2e-5, z)
        assert _inside_any_box(pts, boxes).all(), f"gap in the socket wall at z={z:.4f}"

    # the chamfer: 0.2 mm below the top the opening is wider than the hole (face at 4.05 + 0.55 mm)...
    z_top = HOLE_DEPTH - 0.0002
    pts, _ = _ring(0.0042, z_top)
    assert not _inside_any_box(pts, boxes).any(), "the chamfer does not open the hole entry"
    # ... and it is a real 45-degree face: beyond its 16-gon circumradius everything is blocked
    face = HOLE_APOTHEM + (z_top - (HOLE_DEPTH - CHAMFER))
    pts, _ = _ring(face / math.cos(flat_half) + 5e-5, z_top)
    assert _inside_any_box(pts, boxes).all(), "no chamfer ring at the hole entry"
    # the socket ends at its top
    pts, _ = _ring(0.006, HOLE_DEPTH + 0.0002)
    assert not _inside_any_box(pts, boxes).any()

    # a bottom plate closes the hole below z = 0
    assert _inside_any_box(np.array([[0.0, 0.0, -0.002]]), boxes).all()
