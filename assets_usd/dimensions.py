"""Dimensions and nominal poses of the task parts and the robot's postures: plain data, no pxr.

The runtime (sim, envs) and the authoring script (author.py, which writes them into the USD
stages) both read them from here. Units: metres, kilograms, radians. Part frames (Isaac Lab
Factory's "assembled coordinates", `factory_tasks_cfg.py`): z up; the held part's origin
coincides with the fixed part's origin when assembled (gear, nut), the peg's origin is its
bottom face and the hole's its bottom.

Sources: Isaac Lab Factory's `factory_tasks_cfg.py` (asset sizes, masses, friction, the fixed
asset's default position) and `factory_env_cfg.py` (the postures); IsaacGymEnvs'
`factory_asset_info_gears.yaml` (gear plate and face heights). Where this project's primitive
geometry departs from Factory's meshes (tooth form, thread helices, clearances) the numbers are
its own, measured on a CPU to block, slide, mesh and thread (docs/log/benchmarks.md, "GearMesh and
NutThread, CPU").
"""

from __future__ import annotations

import math

# Apart from vkgrl_newton/tasks.py (the thesis's per-task training facts): this is the authored-asset geometry that
# author.py writes into the USD stages and the sim and env read back, one source for both, at the bottom of the
# data flow (assets -> sim -> env), below tasks; it is per part and posture, not per training parameter.

__all__ = [
    "FACTORY_RESET_JOINTS", "FACTORY_NULL_JOINTS", "FIXED_ASSET_NOMINAL_POS", "FIXED_ASSET_PRIM",
    "TABLE_HALF", "TABLE_POS",
    "PEG_DIAMETER", "PEG_LENGTH", "PEG_MASS", "HOLE_DIAMETER", "HOLE_DEPTH", "HOLE_SEGMENTS", "HOLE_CHAMFER",
    "SOCKET_WALL", "SOCKET_BOTTOM",
    "GEAR_MODULE", "GEAR_TEETH", "GEAR_BASE_HEIGHT", "GEAR_HEIGHT", "GEAR_MEDIUM_X", "GEAR_TOOTH_CLEARANCE",
    "GEAR_SHAFT_RADIUS", "GEAR_BORE_APOTHEM", "GEAR_BORE_SEGMENTS", "GEAR_HUB_RADIUS", "GEAR_HUB_TOP",
    "GEAR_MEDIUM_MASS", "gear_tooth_width", "gear_root_radius", "gear_centres",
    "THREAD_PITCH", "BOLT_HEAD_HALF", "BOLT_BASE_HEIGHT", "BOLT_SHANK_HEIGHT", "BOLT_TIP_HEIGHT", "BOLT_CORE_RADIUS",
    "THREAD_BOLT_RADIUS", "THREAD_NUT_RADIUS", "THREAD_CAPSULE_RADIUS", "THREAD_CHORDS_PER_TURN", "THREAD_BOLT_TOP",
    "THREAD_BOLT_TURNS", "THREAD_NUT_BOTTOM", "THREAD_NUT_TURNS", "NUT_ACROSS_FLATS", "NUT_BORE_APOTHEM",
    "NUT_HEIGHT", "NUT_MASS",
    "ROBOT_FRICTION", "PART_FRICTION", "SOCKET_FRICTION", "NUT_FRICTION", "BOLT_FRICTION",
]

# ---------------------------------------------------------------------------------------------
# Robot postures (factory_env_cfg.py), arm joints 1..7, rad

# Factory's reset posture (`ctrl.reset_joints`); the episode starts from it (then the reset IK)
FACTORY_RESET_JOINTS = (1.5178e-3, -0.19651, -1.4364e-3, -1.9761, -2.7717e-4, 1.7796, 0.78556)
# Factory's null-space posture (`ctrl.default_dof_pos_tensor`)
FACTORY_NULL_JOINTS = (-1.3003, -0.4015, 1.1791, -2.1493, 0.4001, 1.9425, 0.4754)

# ---------------------------------------------------------------------------------------------
# Scene

# World position of every task's fixed-asset frame as authored (identity rotation): Factory's
# default fixed-asset position (factory_tasks_cfg.py). The env moves the frame per reset.
FIXED_ASSET_NOMINAL_POS = (0.6, 0.0, 0.05)
# The prim (under the stage's root) holding each task's fixed asset; its shapes are static
FIXED_ASSET_PRIM = {"PegInsert": "socket", "GearMesh": "gear_base", "NutThread": "bolt"}
# Table: Isaac Lab's Newton port of Factory, 1.2 x 0.6 x 0.04 m centred at (0.55, 0, -0.02), top at z = 0
TABLE_HALF = (0.6, 0.3, 0.02)
TABLE_POS = (0.55, 0.0, -0.02)

# ---------------------------------------------------------------------------------------------
# PegInsert: Factory's Peg8mm / Hole8mm. Peg origin at its bottom face; hole origin at its
# bottom, on the axis. The round hole is a ring of HOLE_SEGMENTS boxes (a regular polygon with
# apothem HOLE_DIAMETER / 2) with a 45-degree chamfer ring at the entry and a bottom plate.

PEG_DIAMETER = 0.007986
PEG_LENGTH = 0.050
PEG_MASS = 0.019
HOLE_DIAMETER = 0.0081
HOLE_DEPTH = 0.025  # = Factory's fixed-asset height: the hole's top (the fixed tip) is at z = 0.025
HOLE_SEGMENTS = 16
HOLE_CHAMFER = 0.00075
SOCKET_WALL = 0.006  # radial wall thickness
SOCKET_BOTTOM = 0.005  # bottom plate thickness, below the hole bottom (socket origin)

# ---------------------------------------------------------------------------------------------
# GearMesh: Factory's gear base and medium gear (factory_tasks_cfg.py: base height 0.02 above
# base_height 0.005, medium shaft at +0.02025 along the base x, medium gear 0.012 kg).
# Frame of the gear base: origin at the base plate's bottom on the base's x axis, z up; the gears
# sit on the plate (z 5..25 mm). Module 2 mm, straight box teeth 0.5 mm slimmer per side than
# half the circular pitch. Tooth counts 9 / 19 / 29 (tip diameters 22 / 42 / 62 mm: Factory's
# small and medium gears measure 22 and 41.9 mm) put the small and large shafts 28 and 48 mm from
# the medium one (Factory's meshes: 30.5 and 50.5 mm with their own tooth form).
GEAR_MODULE = 0.002
GEAR_TEETH = {"small": 9, "medium": 19, "large": 29}
GEAR_BASE_HEIGHT = 0.005  # plate thickness = the gears' bottom
GEAR_HEIGHT = 0.020  # tooth face width; the fixed tip (medium shaft top) is at GEAR_BASE_HEIGHT + GEAR_HEIGHT
GEAR_MEDIUM_X = 0.02025  # Factory's medium-shaft offset along the base x
GEAR_TOOTH_CLEARANCE = 0.0005  # per flank
GEAR_SHAFT_RADIUS = 0.005
GEAR_BORE_APOTHEM = 0.0052  # 12-gon bore of the held gear: 0.2 mm radial play on the shaft
GEAR_BORE_SEGMENTS = 12
GEAR_HUB_RADIUS = 0.010  # grip hub on top of the held gear (z 25..45 mm): the fingers hold it
GEAR_HUB_TOP = 0.045
GEAR_MEDIUM_MASS = 0.012  # Factory


def gear_tooth_width() -> float:
    """Tangential width of a box tooth: half the circular pitch less the clearance per flank, m."""
    return math.pi * GEAR_MODULE / 2 - 2 * GEAR_TOOTH_CLEARANCE


def gear_root_radius(name: str) -> float:
    """Root radius of gear `name` (pitch radius less 1.25 modules), m."""
    return GEAR_MODULE * GEAR_TEETH[name] / 2 - 1.25 * GEAR_MODULE


def gear_centres() -> dict[str, tuple[float, float]]:
    """Shaft positions (x, y) in the gear-base frame, m: the neighbours at the meshing centre distances."""
    r_p = {name: GEAR_MODULE * z / 2 for name, z in GEAR_TEETH.items()}
    return {
        "medium": (GEAR_MEDIUM_X, 0.0),
        "small": (GEAR_MEDIUM_X + r_p["medium"] + r_p["small"], 0.0),
        "large": (GEAR_MEDIUM_X - r_p["medium"] - r_p["large"], 0.0),
    }


# ---------------------------------------------------------------------------------------------
# NutThread: an M16 x 2 bolt and nut (factory_tasks_cfg.py: bolt base_height 0.01, height 0.025,
# thread pitch 0.002; nut 24 mm across flats, 0.01 tall, 0.03 kg). Threads are helices of
# capsules (2.00 mm per turn on MuJoCo-Warp, docs/log/benchmarks.md): bolt centreline r 7.3 mm, nut
# r 7.7 mm, capsule radius 0.45 mm, 24 chords per turn, right-hand. Only where the two can meet
# is threaded: the bolt's top THREAD_BOLT_TURNS turns and the nut's bottom THREAD_NUT_TURNS turns
# (the task ends 1.5 pitches below the bolt tip; the wrist turns less than a revolution).
THREAD_PITCH = 0.002
BOLT_HEAD_HALF = (0.012, 0.012, 0.005)  # head 24 x 24 x 10 mm below the shank, z 0..10 mm
BOLT_BASE_HEIGHT = 0.010
BOLT_SHANK_HEIGHT = 0.025
BOLT_TIP_HEIGHT = BOLT_BASE_HEIGHT + BOLT_SHANK_HEIGHT  # 0.035: the fixed tip
BOLT_CORE_RADIUS = 0.0070  # 0.25 mm inside the nut ridge: the play stays under the 0.5 mm ridge overlap
THREAD_BOLT_RADIUS = 0.0073
THREAD_NUT_RADIUS = 0.0077
THREAD_CAPSULE_RADIUS = 0.00045
THREAD_CHORDS_PER_TURN = 24
THREAD_BOLT_TOP = 0.0335  # the bolt thread's upper end, 1.5 mm under the tip (a lead-in on the core)
THREAD_BOLT_TURNS = 3
THREAD_NUT_BOTTOM = 0.0005  # the nut thread's lower end above the nut's bottom face
THREAD_NUT_TURNS = 2
NUT_ACROSS_FLATS = 0.024
NUT_BORE_APOTHEM = 0.0080  # hex bore flats, 0.25 mm outside the bolt ridge (r 7.75 mm)
NUT_HEIGHT = 0.010
NUT_MASS = 0.03

# ---------------------------------------------------------------------------------------------
# Friction. MuJoCo (and so Newton's SolverMuJoCo) takes the larger coefficient of a pair, PhysX
# the mean. Factory (`set_friction`, factory_tasks_cfg.py) sets the nut 0.01 and everything else
# 0.75; its own comment puts the effective nut-bolt value at 0.25. Here the nut is 0.01 and the
# bolt 0.25: nut on bolt 0.25, nut in the fingers 0.75 (the grip turns it). The socket is 0.6:
# with it (and 0.75 on the finger pads) a gripper-held peg went in, in 160 of 162 scripted trials
# on a CPU (SolverMuJoCo, 4 substeps per 1/120 s; measured for this project).
ROBOT_FRICTION = 0.75
PART_FRICTION = 0.75
SOCKET_FRICTION = 0.6
NUT_FRICTION = 0.01
BOLT_FRICTION = 0.25
