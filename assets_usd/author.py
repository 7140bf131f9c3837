"""Author the USD stages the simulator loads: `python assets_usd/author.py [--check]`.

Writes, deterministically (same bytes on every run), next to this file:
- franka_panda.usda  the Franka Emika Panda arm and hand, fixed base at the origin;
- peg_insert.usda    the PegInsert parts: table, socket (fixed asset) and peg (held asset);
- gear_mesh.usda     the GearMesh parts: table, gear base with its shaft and the small and large
                     gears (fixed asset) and the medium gear (held asset);
- nut_thread.usda    the NutThread parts: table, M16 bolt (fixed asset) and nut (held asset).

`--check` regenerates into memory and fails if a file on disk differs (used by the tests, so
the committed stages never drift from this script) in anything but the last bits of its float64
numbers, which differ between CPU vendors (`same_stage_text`).

Units: metres, kilograms, seconds; Z up. Quaternions in USD are (w, x, y, z); everything else
in this project uses (x, y, z, w) (vkgrl_newton.rotations; `_xyzw` / `_wxyz` convert here).

Where the numbers come from. The parts' dimensions, masses, friction and the fixed asset's
nominal pose are in dimensions.py (with their sources), shared with the simulator; the robot's
are here:
- Kinematics: Franka's modified-DH table (Franka interface specification) written as a body
  tree, each arm joint rotating about its body's local z. Joint limits and torque limits from
  the same specification.
- Inertial parameters: the identified values of Gaz et al., RA-L 2019 ("Dynamic Identification
  of the Franka Emika Panda Robot With Retrieval of Feasible Parameters Using Penalty-Based
  Optimization"), also used by the MuJoCo Menagerie model. Inertia tensors are about the COM in
  the body frame; USD wants principal moments + principal axes, computed here by eigh.
- Joint armature: 0.3 (joints 1-4), 0.11 (joints 5-7), 0.15 (fingers), Isaac Lab's Newton port of
  Factory (`factory_newton_setup.py`).
- Fingers: prismatic 0..0.04 m along +y of each finger frame, the right finger rotated 180 deg
  about z; mimic-coupled (right follows left). Position drive ke 2000 N/m, kd 20 N s/m
  (measured for this project on a CPU to hold the peg with a 20 N squeeze at 4 substeps per
  1/120 s). Finger pad boxes as in the Menagerie model.
- TCP: Isaac Lab Factory's `panda_fingertip_centered`, 0.112071 m along the hand's z
  (hand -> finger origin 0.0584 + finger origin -> bottom of the pads 0.053671, IsaacGymEnvs
  factory_asset_info_franka_table.yaml). Authored as a site (NewtonSiteAPI) named `tcp`.
- Link collision capsules: a rough hull of each link (this script's own choice: segment from a
  link's origin to its child's, radius by link size). They are authored as colliders, as a robot
  description should be; the simulator lets only the finger pads touch the task parts (measured:
  link shapes that never touch the parts change nothing and cost about 25 % of a step).
- Factory's reset posture is stored on the robot's root prim (customData
  `vkgrl:factory_reset_joints`).
The parts' collision geometry, from primitives:
- PegInsert: the round hole is a ring of 16 boxes whose inner faces form a regular 16-gon with
  apothem 4.05 mm, a 0.75 mm 45-degree chamfer ring at the entry, and a bottom plate (measured
  for this project: 160 of 162 scripted insertions of a gripper-held peg succeeded with this
  geometry on a CPU). The peg is a cylinder.
- GearMesh: box teeth on cores for the small and large gears and on a 12-box bore ring for the
  held medium gear, a capsule shaft and a grip hub on the held gear.
- NutThread: capsule helices for the threads, a capsule core and a box head for the bolt, a
  ring of six boxes for the hex nut.
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import newton_usd_schemas  # noqa: F401  registers Newton's USD schemas (NewtonMimicAPI, NewtonSiteAPI) before pxr is used
import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade, Vt

# absolute imports: this file also runs as a script (python assets_usd/author.py)
from vkgrl_newton.assets_usd.dimensions import (
    BOLT_BASE_HEIGHT, BOLT_CORE_RADIUS, BOLT_FRICTION, BOLT_HEAD_HALF, BOLT_TIP_HEIGHT, FACTORY_RESET_JOINTS,
    FIXED_ASSET_NOMINAL_POS, GEAR_BASE_HEIGHT, GEAR_BORE_APOTHEM, GEAR_BORE_SEGMENTS, GEAR_HEIGHT, GEAR_HUB_RADIUS,
    GEAR_HUB_TOP, GEAR_MEDIUM_MASS, GEAR_MEDIUM_X, GEAR_MODULE, GEAR_SHAFT_RADIUS, GEAR_TEETH, HOLE_CHAMFER,
    HOLE_DEPTH, HOLE_DIAMETER, HOLE_SEGMENTS, NUT_ACROSS_FLATS, NUT_BORE_APOTHEM, NUT_FRICTION, NUT_HEIGHT,
    NUT_MASS, PART_FRICTION, PEG_DIAMETER, PEG_LENGTH, PEG_MASS, ROBOT_FRICTION, SOCKET_BOTTOM, SOCKET_FRICTION,
    SOCKET_WALL, TABLE_HALF, TABLE_POS, THREAD_BOLT_RADIUS, THREAD_BOLT_TOP, THREAD_BOLT_TURNS,
    THREAD_CAPSULE_RADIUS, THREAD_CHORDS_PER_TURN, THREAD_NUT_BOTTOM, THREAD_NUT_RADIUS, THREAD_NUT_TURNS,
    THREAD_PITCH, gear_centres, gear_root_radius, gear_tooth_width,
)
from vkgrl_newton.rotations import quat_mul

HERE = Path(__file__).resolve().parent
FRANKA_FILE = "franka_panda.usda"
PEG_INSERT_FILE = "peg_insert.usda"

# ---------------------------------------------------------------------------------------------
# Franka Panda facts

# (name, parent, pos in parent, quat (w, x, y, z) in parent)
ARM_BODY_TREE = [
    ("link0", None, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
    ("link1", "link0", (0.0, 0.0, 0.333), (1.0, 0.0, 0.0, 0.0)),
    ("link2", "link1", (0.0, 0.0, 0.0), (0.70710678, -0.70710678, 0.0, 0.0)),
    ("link3", "link2", (0.0, -0.316, 0.0), (0.70710678, 0.70710678, 0.0, 0.0)),
    ("link4", "link3", (0.0825, 0.0, 0.0), (0.70710678, 0.70710678, 0.0, 0.0)),
    ("link5", "link4", (-0.0825, 0.384, 0.0), (0.70710678, -0.70710678, 0.0, 0.0)),
    ("link6", "link5", (0.0, 0.0, 0.0), (0.70710678, 0.70710678, 0.0, 0.0)),
    ("link7", "link6", (0.088, 0.0, 0.0), (0.70710678, 0.70710678, 0.0, 0.0)),
    ("hand", "link7", (0.0, 0.0, 0.107), (0.92387953, 0.0, 0.0, -0.38268343)),
    ("left_finger", "hand", (0.0, 0.0, 0.0584), (1.0, 0.0, 0.0, 0.0)),
    ("right_finger", "hand", (0.0, 0.0, 0.0584), (0.0, 0.0, 0.0, 1.0)),
]

# joint i (1..7): limits (rad), max velocity (rad/s), max torque (N m)
ARM_JOINT_LIMITS = [
    (-2.8973, 2.8973, 2.175, 87.0),
    (-1.7628, 1.7628, 2.175, 87.0),
    (-2.8973, 2.8973, 2.175, 87.0),
    (-3.0718, -0.0698, 2.175, 87.0),
    (-2.8973, 2.8973, 2.61, 12.0),
    (-0.0175, 3.7525, 2.61, 12.0),
    (-2.8973, 2.8973, 2.61, 12.0),
]
ARM_ARMATURE = (0.3, 0.3, 0.3, 0.3, 0.11, 0.11, 0.11)
FINGER_ARMATURE = 0.15
FINGER_LIMIT = (0.0, 0.04)  # m, each finger
FINGER_DRIVE_KE = 2000.0  # N/m
FINGER_DRIVE_KD = 20.0  # N s/m
FINGER_MAX_FORCE = 70.0  # N, Franka's continuous grasp force

# name: (mass, com, (ixx, iyy, izz, ixy, ixz, iyz)) about the COM, body frame
INERTIALS = {
    "link0": (0.629769, (-0.041018, -0.00014, 0.049974), (0.00315, 0.00388, 0.004285, 8.2904e-7, 0.00015, 8.2299e-6)),
    "link1": (4.970684, (0.003875, 0.002081, -0.04762), (0.70337, 0.70661, 0.009117, -0.000139, 0.006772, 0.019169)),
    "link2": (0.646926, (-0.003141, -0.02872, 0.003495), (0.007962, 0.02811, 0.025995, -0.003925, 0.010254, 0.000704)),
    "link3": (3.228604, (0.027518, 0.039252, -0.066502), (0.037242, 0.036155, 0.01083, -0.004761, -0.011396, -0.012805)),
    "link4": (3.587895, (-0.05317, 0.104419, 0.027454), (0.025853, 0.019552, 0.028323, 0.007796, -0.001332, 0.008641)),
    "link5": (1.225946, (-0.011953, 0.041065, -0.038437), (0.035549, 0.029474, 0.008627, -0.002117, -0.004037, 0.000229)),
    "link6": (1.666555, (0.060149, -0.014117, -0.010517), (0.001964, 0.004354, 0.005433, 0.000109, -0.001158, 0.000341)),
    "link7": (0.735522, (0.010517, -0.004252, 0.061597), (0.012516, 0.010027, 0.004815, -0.000428, -0.001196, -0.000741)),
    "hand": (0.73, (-0.01, 0.0, 0.03), (0.001, 0.0025, 0.0017, 0.0, 0.0, 0.0)),
    "left_finger": (0.015, (0.0, 0.0, 0.0), (2.375e-6, 2.375e-6, 7.5e-7, 0.0, 0.0, 0.0)),
    "right_finger": (0.015, (0.0, 0.0, 0.0), (2.375e-6, 2.375e-6, 7.5e-7, 0.0, 0.0, 0.0)),
}

# Finger pad collision boxes in the finger frame: (half sizes, centre) (Menagerie)
FINGER_PADS = [
    ((0.0085, 0.004, 0.0085), (0.0, 0.0055, 0.0445)),
    ((0.003, 0.002, 0.003), (0.0055, 0.002, 0.05)),
    ((0.003, 0.002, 0.003), (-0.0055, 0.002, 0.05)),
    ((0.003, 0.002, 0.0035), (0.0055, 0.002, 0.0395)),
    ((0.003, 0.002, 0.0035), (-0.0055, 0.002, 0.0395)),
]
# Finger body (visual + collider, not touching the parts): a box behind the pads
FINGER_BODY_BOX = ((0.01, 0.008, 0.022), (0.0, 0.0175, 0.022))

TCP_OFFSET_HAND = (0.0, 0.0, 0.112071)

# Link capsules in the link frame: (p0, p1, radius)
LINK_CAPSULES = {
    "link0": ((-0.04, 0.0, 0.03), (0.0, 0.0, 0.19), 0.07),
    "link1": ((0.0, 0.0, -0.19), (0.0, 0.0, -0.03), 0.065),
    "link2": ((0.0, 0.0, -0.06), (0.0, -0.15, 0.0), 0.065),
    "link3": ((0.0, 0.0, -0.12), (0.08, 0.0, 0.0), 0.06),
    "link4": ((0.0, 0.0, 0.0), (-0.08, 0.1, 0.0), 0.06),
    "link5": ((0.0, 0.0, -0.22), (0.0, 0.08, -0.02), 0.055),
    "link6": ((0.0, 0.0, -0.02), (0.088, 0.0, 0.0), 0.05),
    "link7": ((0.0, 0.0, 0.03), (0.0, 0.0, 0.09), 0.045),
}
HAND_BOX = ((0.025, 0.1, 0.03), (0.0, 0.0, 0.03))  # half sizes, centre in the hand frame

COLORS = {
    "link": (0.92, 0.92, 0.92),
    "hand": (0.2, 0.2, 0.22),
    "pad": (0.1, 0.1, 0.1),
    "peg": (0.95, 0.5, 0.1),
    "socket": (0.15, 0.35, 0.8),
    "gear_base": (0.15, 0.35, 0.8),
    "gear_fixed": (0.2, 0.55, 0.3),
    "gear_held": (0.95, 0.5, 0.1),
    "bolt": (0.15, 0.35, 0.8),
    "nut": (0.95, 0.5, 0.1),
    "table": (0.55, 0.4, 0.25),
}


# ---------------------------------------------------------------------------------------------
# small maths (float64)


def _xyzw(q_wxyz) -> tuple[float, float, float, float]:
    """USD's (w, x, y, z) -> this project's (x, y, z, w)."""
    w, x, y, z = q_wxyz
    return (x, y, z, w)


def _wxyz(q_xyzw) -> tuple[float, float, float, float]:
    """(x, y, z, w), a sequence or tensor -> USD's (w, x, y, z) as floats."""
    x, y, z, w = (float(v) for v in q_xyzw)
    return (w, x, y, z)


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (w, x, y, z) (the body tree composes matrices)."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat_wxyz(r: np.ndarray) -> tuple[float, float, float, float]:
    """Rotation matrix -> unit quaternion (w >= 0), Shepperd's method."""
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = ((r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s)
    q = np.array(q)
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return tuple(float(v) for v in q)


def principal_inertia(inertia6) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """(ixx, iyy, izz, ixy, ixz, iyz) -> principal moments and the principal-axes quat (w, x, y, z)."""
    ixx, iyy, izz, ixy, ixz, iyz = inertia6
    tensor = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    moments, axes = np.linalg.eigh(tensor)
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return tuple(float(m) for m in moments), matrix_to_quat_wxyz(axes)


def body_world_poses() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World pose (position, rotation matrix) of every robot body at q = 0."""
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, parent, pos, quat in ARM_BODY_TREE:
        r_local = quat_wxyz_to_matrix(quat)
        if parent is None:
            poses[name] = (np.array(pos, dtype=float), r_local)
        else:
            p_parent, r_parent = poses[parent]
            poses[name] = (p_parent + r_parent @ np.array(pos), r_parent @ r_local)
    return poses


# ---------------------------------------------------------------------------------------------
# USD helpers


def _new_stage(default_prim: str) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, f"/{default_prim}")
    stage.SetDefaultPrim(root.GetPrim())
    return stage


def _set_pose(xformable: UsdGeom.Xformable, pos, quat_wxyz=(1.0, 0.0, 0.0, 0.0)) -> None:
    xformable.ClearXformOpOrder()
    xformable.AddTranslateOp(precision=UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*pos))
    xformable.AddOrientOp(precision=UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(quat_wxyz[0], *quat_wxyz[1:]))


def _material(stage: Usd.Stage, path: str, friction: float) -> UsdShade.Material:
    mat = UsdShade.Material.Define(stage, path)
    api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    api.CreateStaticFrictionAttr(friction)
    api.CreateDynamicFrictionAttr(friction)
    api.CreateRestitutionAttr(0.0)
    return mat


def _bind_physics_material(prim: Usd.Prim, material: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(
        material, UsdShade.Tokens.weakerThanDescendants, materialPurpose="physics"
    )


def _collider(prim: Usd.Prim, material: UsdShade.Material | None) -> None:
    UsdPhysics.CollisionAPI.Apply(prim)
    if material is not None:
        _bind_physics_material(prim, material)


def _box(stage, path, half, pos, quat_wxyz=(1.0, 0.0, 0.0, 0.0), color=(0.5, 0.5, 0.5), material=None, collide=True):
    cube = UsdGeom.Cube.Define(stage, path)
    cube.CreateSizeAttr(2.0)
    _set_pose(cube, pos, quat_wxyz)
    cube.AddScaleOp(precision=UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*half))
    cube.CreateDisplayColorAttr([Gf.Vec3f(*color)])
    if collide:
        _collider(cube.GetPrim(), material)
    return cube


def _capsule(stage, path, p0, p1, radius, color, material=None):
    """Capsule between two points (z-axis capsule rotated onto the segment)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    z = axis / length
    # rotation taking +z onto the segment direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    quat = matrix_to_quat_wxyz(np.stack([x, y, z], axis=1))
    cap = UsdGeom.Capsule.Define(stage, path)
    cap.CreateAxisAttr(UsdGeom.Tokens.z)
    cap.CreateRadiusAttr(radius)
    cap.CreateHeightAttr(length)
    _set_pose(cap, tuple((p0 + p1) / 2), quat)
    cap.CreateDisplayColorAttr([Gf.Vec3f(*color)])
    _collider(cap.GetPrim(), material)
    return cap


def _mass(prim: Usd.Prim, mass: float, com, inertia6) -> None:
    api = UsdPhysics.MassAPI.Apply(prim)
    api.CreateMassAttr(mass)
    api.CreateCenterOfMassAttr(Gf.Vec3f(*com))
    moments, axes = principal_inertia(inertia6)
    api.CreateDiagonalInertiaAttr(Gf.Vec3f(*moments))
    api.CreatePrincipalAxesAttr(Gf.Quatf(axes[0], *axes[1:]))


def _joint_frames(joint, body0_path, body1_path, pos0, quat0_wxyz) -> None:
    if body0_path is not None:
        joint.CreateBody0Rel().SetTargets([body0_path])
    joint.CreateBody1Rel().SetTargets([body1_path])
    joint.CreateLocalPos0Attr(Gf.Vec3f(*pos0))
    joint.CreateLocalRot0Attr(Gf.Quatf(quat0_wxyz[0], *quat0_wxyz[1:]))
    joint.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    joint.CreateLocalRot1Attr(Gf.Quatf(1.0, 0.0, 0.0, 0.0))


# ---------------------------------------------------------------------------------------------
# stages


def author_franka() -> Usd.Stage:
    stage = _new_stage("franka")
    root = stage.GetDefaultPrim()
    UsdPhysics.ArticulationRootAPI.Apply(root)
    material = _material(stage, "/franka/materials/robot", ROBOT_FRICTION)
    poses = body_world_poses()
    parent_of = {name: parent for name, parent, _, _ in ARM_BODY_TREE}
    local = {name: (pos, quat) for name, _, pos, quat in ARM_BODY_TREE}

    for name, _, _, _ in ARM_BODY_TREE:
        body = UsdGeom.Xform.Define(stage, f"/franka/{name}")
        pos, rot = poses[name]
        _set_pose(body, tuple(pos), matrix_to_quat_wxyz(rot))
        UsdPhysics.RigidBodyAPI.Apply(body.GetPrim())
        _mass(body.GetPrim(), *INERTIALS[name])

    for name, (p0, p1, radius) in LINK_CAPSULES.items():
        _capsule(stage, f"/franka/{name}/collision_capsule", p0, p1, radius, COLORS["link"], material)
    _box(stage, "/franka/hand/collision_box", HAND_BOX[0], HAND_BOX[1], color=COLORS["hand"], material=material)
    for finger in ("left_finger", "right_finger"):
        _box(stage, f"/franka/{finger}/collision_body", FINGER_BODY_BOX[0], FINGER_BODY_BOX[1],
             color=COLORS["hand"], material=material)
        for k, (half, centre) in enumerate(FINGER_PADS):
            _box(stage, f"/franka/{finger}/pad_{k}", half, centre, color=COLORS["pad"], material=material)

    # TCP site: fingertip centre, hand orientation
    # (a site is a non-colliding reference shape; Newton loads sites only from geometric prims)
    tcp = UsdGeom.Sphere.Define(stage, "/franka/hand/tcp")
    tcp.CreateRadiusAttr(0.002)
    _set_pose(tcp, TCP_OFFSET_HAND)
    tcp.CreatePurposeAttr(UsdGeom.Tokens.guide)
    tcp.GetPrim().AddAppliedSchema("NewtonSiteAPI")

    joints = UsdGeom.Scope.Define(stage, "/franka/joints")
    del joints
    fixed = UsdPhysics.FixedJoint.Define(stage, "/franka/joints/base_fixed")
    _joint_frames(fixed, None, "/franka/link0", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
    for i in range(1, 8):
        child = f"link{i}"
        lo, hi, vmax, tmax = ARM_JOINT_LIMITS[i - 1]
        joint = UsdPhysics.RevoluteJoint.Define(stage, f"/franka/joints/joint{i}")
        _joint_frames(joint, f"/franka/{parent_of[child]}", f"/franka/{child}", *local[child])
        joint.CreateAxisAttr(UsdPhysics.Tokens.z)
        joint.CreateLowerLimitAttr(math.degrees(lo))  # UsdPhysics revolute limits are in degrees
        joint.CreateUpperLimitAttr(math.degrees(hi))
        # a drive with zero gains: direct torque (effort) control, capped at the rated torque
        drive = UsdPhysics.DriveAPI.Apply(joint.GetPrim(), UsdPhysics.Tokens.angular)
        drive.CreateStiffnessAttr(0.0)
        drive.CreateDampingAttr(0.0)
        drive.CreateMaxForceAttr(tmax)
        prim = joint.GetPrim()
        prim.CreateAttribute("newton:armature", Sdf.ValueTypeNames.Float).Set(ARM_ARMATURE[i - 1])
        prim.CreateAttribute("newton:velocityLimit", Sdf.ValueTypeNames.Float).Set(math.degrees(vmax))
    hand_joint = UsdPhysics.FixedJoint.Define(stage, "/franka/joints/hand_fixed")
    _joint_frames(hand_joint, "/franka/link7", "/franka/hand", *local["hand"])
    for finger in ("left_finger", "right_finger"):
        joint = UsdPhysics.PrismaticJoint.Define(stage, f"/franka/joints/{finger}")
        _joint_frames(joint, "/franka/hand", f"/franka/{finger}", *local[finger])
        # the joint frame is the finger frame (localRot1 = identity), so +y opens both fingers
        joint.CreateAxisAttr(UsdPhysics.Tokens.y)
        joint.CreateLowerLimitAttr(FINGER_LIMIT[0])
        joint.CreateUpperLimitAttr(FINGER_LIMIT[1])
        drive = UsdPhysics.DriveAPI.Apply(joint.GetPrim(), UsdPhysics.Tokens.linear)
        drive.CreateStiffnessAttr(FINGER_DRIVE_KE)
        drive.CreateDampingAttr(FINGER_DRIVE_KD)
        drive.CreateMaxForceAttr(FINGER_MAX_FORCE)
        drive.CreateTargetPositionAttr(FINGER_LIMIT[1])
        joint.GetPrim().CreateAttribute("newton:armature", Sdf.ValueTypeNames.Float).Set(FINGER_ARMATURE)
    # right finger mimics the left (Franka's coupled gripper)
    right = stage.GetPrimAtPath("/franka/joints/right_finger")
    right.AddAppliedSchema("NewtonMimicAPI")
    right.CreateRelationship("newton:mimicJoint").SetTargets([Sdf.Path("/franka/joints/left_finger")])
    right.CreateAttribute("newton:mimicCoef0", Sdf.ValueTypeNames.Float).Set(0.0)
    right.CreateAttribute("newton:mimicCoef1", Sdf.ValueTypeNames.Float).Set(1.0)

    root.SetCustomDataByKey("vkgrl:factory_reset_joints", Vt.DoubleArray(list(FACTORY_RESET_JOINTS)))
    return stage


@dataclass(frozen=True)
class BoxPiece:
    half: tuple[float, float, float]
    pos: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]


def socket_pieces() -> list[tuple[str, BoxPiece]]:
    """The socket as boxes in its own frame (origin at the hole bottom on the axis, z up).

    Per ring segment k at angle theta_k: a wall box whose inner face is the 16-gon flat at the
    apothem r up to the chamfer foot, an upper box whose inner face is at r + c, and a 45-degree
    box whose face runs from (r, top - c) to (r + c, top). Boxes reach tangentially to the
    polygon's outer corners so neighbours overlap behind the faces (no gaps). A bottom plate
    closes the hole below z = 0.
    """
    r = HOLE_DIAMETER / 2
    c = HOLE_CHAMFER
    t = SOCKET_WALL
    top = HOLE_DEPTH
    n = HOLE_SEGMENTS
    tan_half = math.tan(math.pi / n)
    pieces: list[tuple[str, BoxPiece]] = []
    for k in range(n):
        theta = 2 * math.pi * k / n
        cos_t, sin_t = math.cos(theta), math.sin(theta)
        yaw = (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))  # local x radial, y tangential
        half_tan = (r + t) * tan_half
        # wall, z in [0, top - c]
        rc = r + t / 2
        pieces.append((f"wall_{k:02d}", BoxPiece((t / 2, half_tan, (top - c) / 2), (rc * cos_t, rc * sin_t, (top - c) / 2), yaw)))
        # upper ring, z in [top - c, top], inner face at r + c
        ru = r + c + (t - c) / 2
        pieces.append((f"upper_{k:02d}", BoxPiece(((t - c) / 2, half_tan, c / 2), (ru * cos_t, ru * sin_t, top - c / 2), yaw)))
        # chamfer: face exactly from (r, top - c) to (r + c, top), box behind it (outward, downward).
        # No overhang along the face: 0.1 mm past the lower end already reaches 0.07 mm into the
        # 0.057 mm radial clearance and jams the peg at the chamfer foot (measured).
        h = 0.002
        mid_r, mid_z = r + c / 2, top - c / 2
        cr = mid_r + h / 2 / math.sqrt(2)
        cz = mid_z - h / 2 / math.sqrt(2)
        # +45 degrees about the local tangential (y) axis puts the box's x (thickness) along
        # (1, 0, -1)/sqrt2, behind the face, and its z along the face (1, 0, 1)/sqrt2
        tilt = (math.cos(math.pi / 8), 0.0, math.sin(math.pi / 8), 0.0)  # (w, x, y, z)
        quat = _wxyz(quat_mul(_xyzw(yaw), _xyzw(tilt)))
        pieces.append((f"chamfer_{k:02d}", BoxPiece((h / 2, half_tan, c / math.sqrt(2)), (cr * cos_t, cr * sin_t, cz), quat)))
    outer = r + t
    pieces.append(("bottom", BoxPiece((outer, outer, SOCKET_BOTTOM / 2), (0.0, 0.0, -SOCKET_BOTTOM / 2), (1.0, 0.0, 0.0, 0.0))))
    return pieces


def author_peg_insert() -> Usd.Stage:
    stage = _new_stage("peg_insert")
    part_material = _material(stage, "/peg_insert/materials/part", PART_FRICTION)
    socket_material = _material(stage, "/peg_insert/materials/socket", SOCKET_FRICTION)

    table = UsdGeom.Xform.Define(stage, "/peg_insert/table")
    del table
    _box(stage, "/peg_insert/table/top", TABLE_HALF, TABLE_POS, color=COLORS["table"], material=part_material)

    # the fixed asset: static colliders under one frame; the simulator moves the frame per reset
    socket = UsdGeom.Xform.Define(stage, "/peg_insert/socket")
    _set_pose(socket, FIXED_ASSET_NOMINAL_POS)
    socket.GetPrim().SetCustomDataByKey("vkgrl:role", "fixed_asset")
    for name, piece in socket_pieces():
        _box(stage, f"/peg_insert/socket/{name}", piece.half, piece.pos, piece.quat_wxyz,
             color=COLORS["socket"], material=socket_material)

    # the held asset: origin at the peg's bottom face, axis +z; placed above the socket
    peg = UsdGeom.Xform.Define(stage, "/peg_insert/peg")
    _set_pose(peg, (FIXED_ASSET_NOMINAL_POS[0], FIXED_ASSET_NOMINAL_POS[1], FIXED_ASSET_NOMINAL_POS[2] + HOLE_DEPTH + 0.02))
    peg.GetPrim().SetCustomDataByKey("vkgrl:role", "held_asset")
    UsdPhysics.RigidBodyAPI.Apply(peg.GetPrim())
    radius = PEG_DIAMETER / 2
    i_axial = 0.5 * PEG_MASS * radius**2
    i_trans = PEG_MASS * (3 * radius**2 + PEG_LENGTH**2) / 12
    _mass(peg.GetPrim(), PEG_MASS, (0.0, 0.0, PEG_LENGTH / 2), (i_trans, i_trans, i_axial, 0.0, 0.0, 0.0))
    cyl = UsdGeom.Cylinder.Define(stage, "/peg_insert/peg/collision_cylinder")
    cyl.CreateAxisAttr(UsdGeom.Tokens.z)
    cyl.CreateRadiusAttr(radius)
    cyl.CreateHeightAttr(PEG_LENGTH)
    _set_pose(cyl, (0.0, 0.0, PEG_LENGTH / 2))
    cyl.CreateDisplayColorAttr([Gf.Vec3f(*COLORS["peg"])])
    _collider(cyl.GetPrim(), part_material)
    return stage


# ---------------------------------------------------------------------------------------------
# GearMesh


def _yaw_wxyz(angle: float) -> tuple[float, float, float, float]:
    return (math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2))


def gear_teeth(name: str, r_in: float, centre=(0.0, 0.0)) -> list[tuple[str, BoxPiece]]:
    """Box teeth of gear `name`, tooth k at angle 2 pi k / z from the frame's +x, radially r_in .. tip.

    Phase 0 for all three gears meshes them with the medium gear at yaw 0 in the base frame: the
    medium (19, odd) has a tooth towards +x (the small gear) and a gap towards -x (the large);
    the small (9) has a gap towards -x, the large (29) a tooth towards +x.
    """
    z = GEAR_TEETH[name]
    r_tip = GEAR_MODULE * z / 2 + GEAR_MODULE
    half = ((r_tip - r_in) / 2, gear_tooth_width() / 2, GEAR_HEIGHT / 2)
    rc = (r_tip + r_in) / 2
    zc = GEAR_BASE_HEIGHT + GEAR_HEIGHT / 2
    pieces = []
    for k in range(z):
        a = 2 * math.pi * k / z
        pieces.append((f"tooth_{k:02d}", BoxPiece(half, (centre[0] + rc * math.cos(a), centre[1] + rc * math.sin(a), zc),
                                                 _yaw_wxyz(a))))
    return pieces


def gear_bore_pieces() -> list[tuple[str, BoxPiece]]:
    """The held gear's bore: a 12-gon ring of boxes, inner faces at GEAR_BORE_APOTHEM, 2 mm thick."""
    t = 0.002
    n = GEAR_BORE_SEGMENTS
    half_tan = (GEAR_BORE_APOTHEM + t) * math.tan(math.pi / n)
    rc = GEAR_BORE_APOTHEM + t / 2
    zc = GEAR_BASE_HEIGHT + GEAR_HEIGHT / 2
    pieces = []
    for k in range(n):
        a = 2 * math.pi * (k + 0.5) / n
        pieces.append((f"bore_{k:02d}", BoxPiece((t / 2, half_tan, GEAR_HEIGHT / 2),
                                                 (rc * math.cos(a), rc * math.sin(a), zc), _yaw_wxyz(a))))
    return pieces


def _cylinder(stage, path, radius, z0, z1, centre=(0.0, 0.0), color=(0.5, 0.5, 0.5), material=None):
    cyl = UsdGeom.Cylinder.Define(stage, path)
    cyl.CreateAxisAttr(UsdGeom.Tokens.z)
    cyl.CreateRadiusAttr(radius)
    cyl.CreateHeightAttr(z1 - z0)
    _set_pose(cyl, (centre[0], centre[1], (z0 + z1) / 2))
    cyl.CreateDisplayColorAttr([Gf.Vec3f(*color)])
    _collider(cyl.GetPrim(), material)
    return cyl


def author_gear_mesh() -> Usd.Stage:
    root = "/gear_mesh"
    stage = _new_stage("gear_mesh")
    part_material = _material(stage, f"{root}/materials/part", PART_FRICTION)
    _box(stage, f"{root}/table/top", TABLE_HALF, TABLE_POS, color=COLORS["table"], material=part_material)

    # the fixed asset: base plate, the medium shaft (a capsule: its round top leads the bore in)
    # and the two flanking gears, all static under one frame the simulator moves per reset. The
    # flanking gears do not turn (Factory's are free bodies resting on their shafts): for
    # inserting the medium gear what matters is that their teeth block it unless it is aligned.
    base = UsdGeom.Xform.Define(stage, f"{root}/gear_base")
    _set_pose(base, FIXED_ASSET_NOMINAL_POS)
    base.GetPrim().SetCustomDataByKey("vkgrl:role", "fixed_asset")
    centres = gear_centres()
    x_lo = centres["large"][0] - GEAR_MODULE * (GEAR_TEETH["large"] / 2 + 1) - 0.004
    x_hi = centres["small"][0] + GEAR_MODULE * (GEAR_TEETH["small"] / 2 + 1) + 0.004
    y_half = GEAR_MODULE * (GEAR_TEETH["large"] / 2 + 1) + 0.004
    _box(stage, f"{root}/gear_base/plate", ((x_hi - x_lo) / 2, y_half, GEAR_BASE_HEIGHT / 2),
         ((x_hi + x_lo) / 2, 0.0, GEAR_BASE_HEIGHT / 2), color=COLORS["gear_base"], material=part_material)
    shaft_top = GEAR_BASE_HEIGHT + GEAR_HEIGHT - 0.0005  # under the held gear's hub when seated
    _capsule(stage, f"{root}/gear_base/shaft", (centres["medium"][0], 0.0, 0.0),
             (centres["medium"][0], 0.0, shaft_top - GEAR_SHAFT_RADIUS), GEAR_SHAFT_RADIUS, COLORS["gear_base"],
             part_material)
    for name in ("small", "large"):
        c = centres[name]
        r_root = gear_root_radius(name)
        _cylinder(stage, f"{root}/gear_base/{name}_core", r_root, GEAR_BASE_HEIGHT, GEAR_BASE_HEIGHT + GEAR_HEIGHT,
                  c, COLORS["gear_fixed"], part_material)
        for tooth, piece in gear_teeth(name, r_root - 0.0005, c):
            _box(stage, f"{root}/gear_base/{name}_{tooth}", piece.half, piece.pos, piece.quat_wxyz,
                 color=COLORS["gear_fixed"], material=part_material)

    # the held asset: the medium gear, origin on its axis at the base plate's bottom level (so it
    # coincides with the target frame, base + (GEAR_MEDIUM_X, 0, 0), when seated), bore + spoke
    # teeth + a grip hub above the teeth
    gear = UsdGeom.Xform.Define(stage, f"{root}/medium_gear")
    _set_pose(gear, (FIXED_ASSET_NOMINAL_POS[0] + GEAR_MEDIUM_X, FIXED_ASSET_NOMINAL_POS[1], FIXED_ASSET_NOMINAL_POS[2] + 0.03))
    gear.GetPrim().SetCustomDataByKey("vkgrl:role", "held_asset")
    UsdPhysics.RigidBodyAPI.Apply(gear.GetPrim())
    r_tip = GEAR_MODULE * (GEAR_TEETH["medium"] / 2 + 1)
    m = GEAR_MEDIUM_MASS
    i_axial = 0.5 * m * r_tip**2
    i_trans = m * (3 * r_tip**2 + GEAR_HEIGHT**2) / 12
    _mass(gear.GetPrim(), m, (0.0, 0.0, GEAR_BASE_HEIGHT + GEAR_HEIGHT / 2), (i_trans, i_trans, i_axial, 0.0, 0.0, 0.0))
    for name, piece in gear_bore_pieces() + gear_teeth("medium", GEAR_BORE_APOTHEM + 0.0018):
        _box(stage, f"{root}/medium_gear/{name}", piece.half, piece.pos, piece.quat_wxyz, color=COLORS["gear_held"],
             material=part_material)
    _cylinder(stage, f"{root}/medium_gear/hub", GEAR_HUB_RADIUS, GEAR_BASE_HEIGHT + GEAR_HEIGHT, GEAR_HUB_TOP,
              color=COLORS["gear_held"], material=part_material)
    return stage


# ---------------------------------------------------------------------------------------------
# NutThread


def helix_points(radius: float, z_start: float, turns: float, theta_start: float = 0.0) -> np.ndarray:
    """(n + 1, 3) points of a right-hand helix: z rises by THREAD_PITCH per counter-clockwise turn."""
    n = int(round(turns * THREAD_CHORDS_PER_TURN))
    theta = theta_start + 2 * math.pi * np.arange(n + 1) / THREAD_CHORDS_PER_TURN
    z = z_start + THREAD_PITCH * (theta - theta_start) / (2 * math.pi)
    return np.column_stack([radius * np.cos(theta), radius * np.sin(theta), z])


def bolt_thread_points() -> np.ndarray:
    """The bolt ridge's centreline, ending (top) at THREAD_BOLT_TOP on the bolt frame's +x."""
    return helix_points(THREAD_BOLT_RADIUS, THREAD_BOLT_TOP - THREAD_BOLT_TURNS * THREAD_PITCH, THREAD_BOLT_TURNS)


def nut_thread_points() -> np.ndarray:
    """The nut ridge's centreline in the nut frame, starting (bottom) on the nut frame's +x."""
    return helix_points(THREAD_NUT_RADIUS, THREAD_NUT_BOTTOM, THREAD_NUT_TURNS)


def nut_hex_pieces() -> list[tuple[str, BoxPiece]]:
    """Six boxes forming the hex nut, flats facing +-y (and 60 deg on), bore flats at NUT_BORE_APOTHEM."""
    t = NUT_ACROSS_FLATS / 2 - NUT_BORE_APOTHEM
    half_tan = NUT_ACROSS_FLATS / 2 * math.tan(math.pi / 6)
    rc = NUT_BORE_APOTHEM + t / 2
    pieces = []
    for k in range(6):
        a = math.pi / 6 + k * math.pi / 3
        pieces.append((f"hex_{k}", BoxPiece((t / 2, half_tan, NUT_HEIGHT / 2),
                                            (rc * math.cos(a), rc * math.sin(a), NUT_HEIGHT / 2), _yaw_wxyz(a))))
    return pieces


def author_nut_thread() -> Usd.Stage:
    root = "/nut_thread"
    stage = _new_stage("nut_thread")
    part_material = _material(stage, f"{root}/materials/part", PART_FRICTION)
    bolt_material = _material(stage, f"{root}/materials/bolt", BOLT_FRICTION)
    nut_material = _material(stage, f"{root}/materials/nut", NUT_FRICTION)
    _box(stage, f"{root}/table/top", TABLE_HALF, TABLE_POS, color=COLORS["table"], material=part_material)

    # the fixed asset: head, core (a capsule: its round top leads the nut on) and the thread
    bolt = UsdGeom.Xform.Define(stage, f"{root}/bolt")
    _set_pose(bolt, FIXED_ASSET_NOMINAL_POS)
    bolt.GetPrim().SetCustomDataByKey("vkgrl:role", "fixed_asset")
    _box(stage, f"{root}/bolt/head", BOLT_HEAD_HALF, (0.0, 0.0, BOLT_HEAD_HALF[2]), color=COLORS["bolt"],
         material=bolt_material)
    tip = BOLT_TIP_HEIGHT
    _capsule(stage, f"{root}/bolt/core", (0.0, 0.0, BOLT_BASE_HEIGHT), (0.0, 0.0, tip - BOLT_CORE_RADIUS),
             BOLT_CORE_RADIUS, COLORS["bolt"], bolt_material)
    pts = bolt_thread_points()
    for k in range(len(pts) - 1):
        _capsule(stage, f"{root}/bolt/thread_{k:03d}", pts[k], pts[k + 1], THREAD_CAPSULE_RADIUS, COLORS["bolt"],
                 bolt_material)

    # the held asset: the nut, origin on its axis at its bottom face
    nut = UsdGeom.Xform.Define(stage, f"{root}/nut")
    _set_pose(nut, (FIXED_ASSET_NOMINAL_POS[0], FIXED_ASSET_NOMINAL_POS[1], FIXED_ASSET_NOMINAL_POS[2] + tip + 0.015))
    nut.GetPrim().SetCustomDataByKey("vkgrl:role", "held_asset")
    UsdPhysics.RigidBodyAPI.Apply(nut.GetPrim())
    # inertia of a hex ring ~ a thick cylinder r 8.3 .. 13 mm: diag(2, 2, 3.3)e-6 kg m^2, the value the
    # capsule threads were measured to turn with on a CPU
    _mass(nut.GetPrim(), NUT_MASS, (0.0, 0.0, NUT_HEIGHT / 2), (2.0e-6, 2.0e-6, 3.3e-6, 0.0, 0.0, 0.0))
    for name, piece in nut_hex_pieces():
        _box(stage, f"{root}/nut/{name}", piece.half, piece.pos, piece.quat_wxyz, color=COLORS["nut"],
             material=nut_material)
    pts = nut_thread_points()
    for k in range(len(pts) - 1):
        _capsule(stage, f"{root}/nut/thread_{k:03d}", pts[k], pts[k + 1], THREAD_CAPSULE_RADIUS, COLORS["nut"],
                 nut_material)
    return stage


GEAR_MESH_FILE = "gear_mesh.usda"
NUT_THREAD_FILE = "nut_thread.usda"
STAGES = {FRANKA_FILE: author_franka, PEG_INSERT_FILE: author_peg_insert, GEAR_MESH_FILE: author_gear_mesh,
          NUT_THREAD_FILE: author_nut_thread}


def stage_text(stage: Usd.Stage) -> str:
    text = stage.GetRootLayer().ExportToString()
    # the exporter writes a doc line naming the in-memory layer; keep the output reproducible
    lines = [ln for ln in text.splitlines() if not ln.strip().startswith('doc = """Generated from Composed Stage')]
    header = "#usda 1.0\n"
    body = "\n".join(lines[1:]) if lines and lines[0].startswith("#usda") else "\n".join(lines)
    return header + body.rstrip() + "\n"


# A number in a stage's text. The stages are float64 maths (numpy's sin/cos/arctan2), whose last bits
# differ between CPU vendors (AVX-512 vs AVX2 code paths): measured, an AMD EPYC and an Intel Xeon
# disagree in the 16th-17th significant digit of a few quaternions. So a committed stage matches
# when its text is the same apart from numbers within 1e-12 relative (~4500 ulps; 1e-9 m on a metre).
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
STAGE_REL_TOL = 1e-12


def same_stage_text(a: str, b: str) -> bool:
    """True when two stage texts differ at most in the last bits of their numbers (see _NUMBER)."""
    if _NUMBER.sub("#", a) != _NUMBER.sub("#", b):
        return False
    return all(math.isclose(float(x), float(y), rel_tol=STAGE_REL_TOL, abs_tol=1e-15)
               for x, y in zip(_NUMBER.findall(a), _NUMBER.findall(b), strict=True))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="fail if a stage on disk differs from this script's output")
    parser.add_argument("--out-dir", type=Path, default=HERE)
    args = parser.parse_args(argv)
    stale = []
    for filename, author in STAGES.items():
        text = stage_text(author())
        path = args.out_dir / filename
        if args.check:
            if not path.exists() or not same_stage_text(path.read_text(), text):
                stale.append(str(path))
            continue
        tmp = path.with_suffix(".usda.tmp")
        tmp.write_text(text)
        tmp.replace(path)
        print(f"wrote {path}")
    if stale:
        print("stale (rerun `python assets_usd/author.py`): " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
