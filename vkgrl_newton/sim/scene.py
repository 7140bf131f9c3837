"""Build the Newton model of one assembly task: USD stages -> ModelBuilder -> N worlds.

The robot stage (assets_usd/franka_panda.usda) and the task stage (assets_usd/<task>.usda) are
loaded into one template builder, collision settings are applied per shape, and the template
is replicated into `num_worlds` separate worlds (worlds never collide with each other).

Gravity (documented choice, as Isaac Lab's Newton port of Factory): the model's gravity is 0.
In Factory the robot and the held part ignore gravity (`disable_gravity=True`) and the fixed
part is welded, so nothing in the scene feels gravity during an episode; Newton has no per-body
gravity switch that every solver honours, so the world gravity is set to zero instead.

The fixed part (socket) is made of static shapes (body -1). Static shapes cannot be moved by
joints, so the env re-places them per world at reset by writing `model.shape_transform`
(see `socket_shapes` / `socket_local`): the collision pipeline reads static shape transforms
from the model every step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

import newton

from ..assets_usd import FRANKA_USD, TASK_USD
from ..assets_usd import dimensions as dims
from ..assets_usd.dimensions import FACTORY_NULL_JOINTS, FACTORY_RESET_JOINTS  # noqa: F401  the env takes them from here
from ..rotations import quat_conjugate, quat_mul, quat_rotate
from ..runtime import default_device
from ..tasks import DECIMATION, GEOMETRIES, MESH_TASKS, SIM_DT, SOLVERS, geometry_error, get_task  # noqa: F401  (names of this module too)

__all__ = ["SimConfig", "Scene", "build_scene", "default_device", "SOLVERS"]

# Collision geometry of the GearMesh / NutThread parts: the authored primitives (box teeth,
# capsule threads; the default), or closed triangle meshes (solid box-tooth gears, ISO 68-1
# threads; assets_usd/part_meshes.py) which on CUDA get signed distance fields (Newton builds
# mesh SDFs on CUDA only) and on a CPU collide through Newton's triangle BVH path (slow: NutThread
# env steps ~30x slower than on the primitives with newton 1.8.0; docs/log/benchmarks.md, "The mesh variant")
SDF_VOXEL = {"GearMesh": 0.00025, "NutThread": 0.0001}  # m (keys: tasks.MESH_TASKS): a quarter of a tooth clearance, half a thread crest
SDF_BAND = (-0.002, 0.002)  # m, narrow band of the SDFs
SDF_MARGIN = 0.005  # m, AABB padding of the SDFs (more than any contact gap here)
# Thread mesh grid (columns per turn, rows per pitch). With an SDF the grid only sets how exact the
# field is; without one (a CPU) every vertex is a BVH query per substep, so the grid sets the cost:
# 48 x 8 threads as well as 96 x 32 (2.01 vs 1.96 mm/turn) at about a ninth of the cost per frame.
THREAD_MESH_GRID = {"sdf": (96, 32), "bvh": (48, 8)}


ARM_DOFS = 7


@dataclass(frozen=True)
class SimConfig:
    """Physics settings. Defaults: measured for this project on a CPU (newton 1.8.0) with a gripper-held
    peg: with them 160 of 162 scripted insertions succeeded; 2 substeps let the fingers pass through
    the peg, SolverSteel jammed."""

    num_worlds: int = 16
    device: str | None = None  # None: cuda:0 when present, else cpu
    solver: str = "mujoco"  # SolverMuJoCo (MuJoCo-Warp) with Newton's collision pipeline
    substeps: int = 4  # per 1/120 s physics step; 2 let the fingers tunnel through the peg
    world_spacing: float = 0.0  # m between worlds along x; 0 keeps every world at the origin (Newton's advice)
    contact_gap: float = 0.001  # m, Newton shape gap (contacts generated within this distance)
    contact_ke: float = 4.0e4  # N/m -> MuJoCo solref timeconst 5 ms, damping ratio 1
    contact_kd: float = 400.0
    impratio: float = 10.0  # cuts the peg's creep along the fingers from ~1.5 mm to 0.12 mm
    # contacts and constraint rows per world; None: the task's (TASK_CONTACT_LIMITS: about 130
    # contacts during a peg insertion, a few hundred with the nut on its capsule thread)
    nconmax: int | None = None
    njmax: int | None = None
    # Newton's collision pipeline every substep (True), or once per 1/120 s physics step, its
    # contacts reused by the other substeps (docs/log/benchmarks.md measures both)
    collide_every_substep: bool = True
    robot_usd: str | None = None  # a user's own robot stage (same body/joint names); None: the bundled Franka
    geometry: str = "primitives"  # GEOMETRIES

    def __post_init__(self):
        if not isinstance(self.num_worlds, int) or self.num_worlds < 1:
            raise ValueError(f"num_worlds must be an integer >= 1, got {self.num_worlds!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if self.geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {GEOMETRIES}, got {self.geometry!r}")
        if not isinstance(self.substeps, int) or self.substeps < 1:
            raise ValueError(f"substeps must be an integer >= 1, got {self.substeps!r}")
        for name in ("nconmax", "njmax"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
                raise ValueError(f"{name} must be None or an integer >= 1, got {v!r}")
        for name in ("contact_gap", "contact_ke", "contact_kd", "impratio"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not isinstance(self.collide_every_substep, bool):
            raise ValueError(f"collide_every_substep must be True or False, got {self.collide_every_substep!r}")
        if self.world_spacing < 0:
            raise ValueError(f"world_spacing must be >= 0, got {self.world_spacing!r}")

    @property
    def sim_dt(self) -> float:
        return SIM_DT

    @property
    def substep_dt(self) -> float:
        return SIM_DT / self.substeps

    @property
    def decimation(self) -> int:
        return DECIMATION


# (nconmax, njmax) per world when SimConfig leaves them None: 1.5x the peaks measured over one scripted
# and one random episode of 4 worlds (`python -m vkgrl_newton.tools.contact_peaks`, docs/log/benchmarks.md),
# rounded up to a multiple of 32. Contacts share one buffer across worlds (peak total / worlds);
# constraint rows are per world. MuJoCo-Warp's cost grows with the allocation, not just the use, and
# an overflow is counted and warned (AssemblyEnv.contact_overflows_total), never silent.
# Peaks (contacts / rows per world): PegInsert 121 / 208 (the rows from the graph test's pressing
# rollout, tests/test_physics_graph.py); GearMesh 223 / 466 (its old 256 contacts overflowed now and
# then); NutThread 418 / 313 (it had 1024 / 4096). 4 worlds, one episode per policy: thin evidence
# for what a learning policy may do, hence the counting.
TASK_CONTACT_LIMITS = {"PegInsert": (192, 320), "GearMesh": (352, 704), "NutThread": (640, 480)}


def contact_limits(task: str, config: SimConfig) -> tuple[int, int]:
    """(nconmax, njmax) per world: the config's, or the task's default where it gives None."""
    nconmax, njmax = TASK_CONTACT_LIMITS[task]
    return (config.nconmax if config.nconmax is not None else nconmax,
            config.njmax if config.njmax is not None else njmax)


@dataclass
class Scene:
    """A built model and the indices the env and the kernels need (all per world, on device)."""

    task: str
    config: SimConfig
    model: newton.Model
    device: str
    num_worlds: int
    bodies_per_world: int
    coords_per_world: int
    dofs_per_world: int
    env_origins: np.ndarray  # (E, 3) world position of each robot base, m
    hand_body: wp.array  # (E,) int32 global body index of the hand
    held_body: wp.array  # (E,) int32 global body index of the held part
    robot_articulation: wp.array  # (E,) int32
    robot_articulation_mask: wp.array  # (A,) bool, True for robot articulations (Jacobian/mass only for these)
    hand_link: int  # link row of the hand in its articulation (Jacobian row block)
    tcp_offset_hand: tuple[float, float, float]  # TCP position in the hand frame, m
    held_q_start: int  # first joint_q column of the held part's free joint in a world
    held_qd_start: int
    socket_shapes: wp.array  # (E, Ns) int32 global shape indices of the fixed part
    socket_local: wp.array  # (Ns,) transform of each socket shape in the socket frame
    gripper_group: wp.array  # (S,) int32: 1 for the held part and finger pads, 0 otherwise
    labels: dict = field(default_factory=dict)


def _find(labels: list[str], suffix: str) -> int:
    hits = [i for i, lbl in enumerate(labels) if lbl.endswith(suffix)]
    if len(hits) != 1:
        raise ValueError(f"expected exactly one entry ending in {suffix!r}, found {len(hits)}")
    return hits[0]


def build_template(task: str, config: SimConfig) -> tuple[newton.ModelBuilder, dict]:
    """One world: the robot and the task parts, with this project's collision settings."""
    get_task(task)  # validates the name
    if task not in TASK_USD:
        raise ValueError(f"task {task!r} has no USD stage yet; available: {sorted(TASK_USD)}")
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    robot_usd = config.robot_usd or str(FRANKA_USD)
    builder.add_usd(robot_usd, enable_self_collisions=False, load_visual_shapes=True)
    builder.add_usd(str(TASK_USD[task]))
    if config.geometry == "mesh":
        device = config.device or default_device()
        add_part_meshes(builder, task, sdf_device=device if str(device).startswith("cuda") else None)

    bodies = builder.body_label
    shapes = builder.shape_label
    info = {
        "hand": _find(bodies, "/hand"),
        "left_finger": _find(bodies, "/left_finger"),
        "right_finger": _find(bodies, "/right_finger"),
        "held": next(i for i, lbl in enumerate(bodies) if lbl.startswith(f"/{stage_root(task)}/")),
        "tcp_site": _find(shapes, "/hand/tcp"),
    }
    finger_bodies = {info["left_finger"], info["right_finger"]}
    fixed_prefix = f"/{stage_root(task)}/{dims.FIXED_ASSET_PRIM[task]}/"
    robot_bodies = {i for i, lbl in enumerate(bodies) if not lbl.startswith(f"/{stage_root(task)}/")}
    collide = int(newton.ShapeFlags.COLLIDE_SHAPES)
    pads, socket, group = [], [], []
    for s, lbl in enumerate(shapes):
        body = builder.shape_body[s]
        is_site = bool(builder.shape_flags[s] & int(newton.ShapeFlags.SITE))
        if is_site:
            continue
        is_pad = body in finger_bodies and "/pad_" in lbl
        if body in robot_bodies and not is_pad:
            # only the finger pads touch the parts; the rest of the arm is visual here (measured: its
            # shapes never touch the parts and colliding them costs about 25 % of a step)
            builder.shape_flags[s] &= ~collide
            continue
        apply_contact_settings(builder, s, config)
        if is_pad:
            pads.append(s)
            group.append(s)
        elif body == info["held"]:
            group.append(s)
        elif body == -1 and fixed_prefix in lbl:
            socket.append(s)
    if not pads or not socket:
        raise ValueError(f"stage for {task!r}: found {len(pads)} finger pads and {len(socket)} fixed-asset shapes")
    info.update(pads=pads, socket=socket, group=group)

    tcp_xform = builder.shape_transform[info["tcp_site"]]
    info["tcp_offset_hand"] = tuple(float(v) for v in tcp_xform[:3])

    # initial posture: Factory's reset joints, fingers open
    arm_q0 = builder.joint_q_start[_find(builder.joint_label, "/joint1")]
    builder.joint_q[arm_q0 : arm_q0 + ARM_DOFS] = list(FACTORY_RESET_JOINTS)
    return builder, info


def add_part_meshes(builder: newton.ModelBuilder, task: str, sdf_device: str | None = None) -> list[int]:
    """The mesh variant: switch off the primitive teeth / threads of the task's parts and add
    closed triangle meshes in their place, on the same bodies; with `sdf_device` (a CUDA device)
    each mesh gets its SDF built there first. Returns the new shape indices. Call it after every
    other shape is added: the filter pairs cover the colliding shapes that exist at the call.

    The meshes collide only with each other (mesh-mesh: SDF on CUDA, the triangle BVH on a CPU):
    the tooth flanks and thread flanks, the contacts the task is about. Everything else stays on
    the primitives, which are exact for it: the gear's bore ring on its round shaft and flat
    plate, the nut's hex on the finger pads, the hub in the fingers. Why: Newton pairs a mesh
    with a primitive triangle by triangle and drops the triangles that face away from the
    primitive's centre, which fails for a concave part: a solid disc mesh rests on a box plate
    within 0.01 mm, the same disc with a bore sinks 2.5 mm to the plate's mid-plane
    (docs/log/benchmarks.md). PegInsert has no mesh variant (its primitives are exact)."""
    from ..assets_usd import part_meshes as pm

    error = geometry_error(task, "mesh")
    if error is not None:
        raise ValueError(f"SimConfig.{error}")
    root = f"/{stage_root(task)}/"
    labels = list(builder.shape_label)
    collide = int(newton.ShapeFlags.COLLIDE_SHAPES)

    visible = int(newton.ShapeFlags.VISIBLE)

    def clear(flags, *prefixes):
        for s, lbl in enumerate(labels):
            if any(lbl.startswith(root + p) for p in prefixes):
                builder.shape_flags[s] &= ~flags

    def cfg(mu):
        return newton.ModelBuilder.ShapeConfig(density=0.0, mu=mu)  # mass stays the authored MassAPI's

    def colour(prefix):  # the authored colour of the part the mesh stands in for
        hit = next((s for s, lbl in enumerate(labels) if lbl.startswith(root + prefix)), None)
        if hit is None:
            raise ValueError(f"{task} stage has no shape {root + prefix}*; re-author it (assets_usd/author.py)")
        return builder.shape_color[hit]

    def mesh(vf):
        v, f = vf
        m = newton.Mesh(v.astype(np.float32), f.reshape(-1).astype(np.int32), compute_inertia=False)
        if sdf_device is not None:  # margin: the SDF must reach past the contact gap
            m.build_sdf(device=sdf_device, target_voxel_size=SDF_VOXEL[task], narrow_band_range=SDF_BAND,
                        margin=SDF_MARGIN)
        return m

    held = next(i for i, lbl in enumerate(builder.body_label) if lbl.startswith(root))
    nominal = wp.transform(dims.FIXED_ASSET_NOMINAL_POS, wp.quat_identity())
    z0, z1 = dims.GEAR_BASE_HEIGHT, dims.GEAR_BASE_HEIGHT + dims.GEAR_HEIGHT
    added = []
    if task == "GearMesh":
        clear(collide | visible, "medium_gear/tooth_", "gear_base/small_", "gear_base/large_")  # replaced
        clear(visible, "medium_gear/bore_")  # still colliding, drawn by the mesh around it
        width = dims.gear_tooth_width()

        def outline(name):
            z = dims.GEAR_TEETH[name]
            return pm.gear_outline(z, dims.gear_root_radius(name), dims.GEAR_MODULE * (z / 2 + 1), width)

        a = 2 * np.pi * np.arange(48) / 48
        bore = np.column_stack([dims.GEAR_BORE_APOTHEM * np.cos(a), dims.GEAR_BORE_APOTHEM * np.sin(a)])
        added.append(builder.add_shape_mesh(held, mesh=mesh(pm.extrude(outline("medium"), bore, z0, z1)),
                                            cfg=cfg(dims.PART_FRICTION), color=colour("medium_gear/tooth_"),
                                            label=root + "medium_gear/gear_mesh"))
        for name, (cx, cy) in dims.gear_centres().items():
            if name == "medium":
                continue
            xform = wp.transform((dims.FIXED_ASSET_NOMINAL_POS[0] + cx, dims.FIXED_ASSET_NOMINAL_POS[1] + cy,
                                  dims.FIXED_ASSET_NOMINAL_POS[2]), wp.quat_identity())
            added.append(builder.add_shape_mesh(-1, xform=xform, mesh=mesh(pm.extrude(outline(name), None, z0, z1)),
                                                cfg=cfg(dims.PART_FRICTION), color=colour(f"gear_base/{name}_"),
                                                label=root + f"gear_base/{name}_gear_mesh"))
    else:
        clear(collide | visible, "nut/thread_", "bolt/thread_")
        clear(visible, "nut/hex_")
        major = dims.THREAD_BOLT_RADIUS + dims.THREAD_CAPSULE_RADIUS  # 7.75 mm: the capsule thread's crest
        tip = dims.BOLT_TIP_HEIGHT
        columns, rows = THREAD_MESH_GRID["sdf" if sdf_device is not None else "bvh"]
        # threaded up to where the capsule thread ends, a pilot above (as the primitives' core): both
        # variants land the nut at the same height, centred, and it descends only by turning
        rod = pm.threaded_rod(dims.THREAD_PITCH, major, dims.BOLT_BASE_HEIGHT, tip, chamfer=0.001,
                              thread_top=dims.THREAD_BOLT_TOP, columns=columns, rows_per_pitch=rows)
        nut = pm.threaded_bore(dims.THREAD_PITCH, major, 0.00015, dims.NUT_HEIGHT, dims.NUT_ACROSS_FLATS,
                               countersink=0.0005, columns=columns, rows_per_pitch=rows)
        added.append(builder.add_shape_mesh(-1, xform=nominal, mesh=mesh(rod), cfg=cfg(dims.BOLT_FRICTION),
                                            color=colour("bolt/thread_"), label=root + "bolt/thread_mesh"))
        added.append(builder.add_shape_mesh(held, mesh=mesh(nut), cfg=cfg(dims.NUT_FRICTION),
                                            color=colour("nut/hex_"), label=root + "nut/thread_mesh"))
    meshes = set(added)
    for s in range(len(builder.shape_label)):
        if s not in meshes and builder.shape_flags[s] & collide:
            for m in added:
                builder.add_shape_collision_filter_pair(m, s)
    return added


def apply_contact_settings(builder: newton.ModelBuilder, shape: int, config: SimConfig) -> None:
    """This project's contact parameters on one colliding shape (no torsional or rolling friction)."""
    if builder.shape_flags[shape] & int(newton.ShapeFlags.COLLIDE_SHAPES):
        builder.shape_material_ke[shape] = config.contact_ke
        builder.shape_material_kd[shape] = config.contact_kd
        builder.shape_gap[shape] = config.contact_gap
        builder.shape_material_mu_torsional[shape] = 0.0
        builder.shape_material_mu_rolling[shape] = 0.0


def stage_root(task: str) -> str:
    """The default prim name of a task stage (PegInsert -> peg_insert)."""
    return "".join("_" + c.lower() if c.isupper() else c for c in task).lstrip("_")


def build_scene(task: str, config: SimConfig | None = None) -> Scene:
    """Build the N-world model of `task` on `config.device` (see module docstring)."""
    config = config or SimConfig()
    device = config.device or default_device()
    template, info = build_template(task, config)

    scene_builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    scene_builder.replicate(template, config.num_worlds, spacing=(config.world_spacing, 0.0, 0.0))
    model = scene_builder.finalize(device=device)

    nw = config.num_worlds
    bpw = template.body_count
    cpw = template.joint_coord_count
    dpw = template.joint_dof_count
    spw = len(template.shape_label)
    if model.body_count != bpw * nw or model.joint_coord_count != cpw * nw or model.shape_count != spw * nw:
        raise RuntimeError("replicated model layout is not world-major; per-world views would be wrong")

    # articulations: in each world the robot's comes first (it was added first)
    art_start = model.articulation_start.numpy()
    joint_child = model.joint_child.numpy()
    art_of_body = {}
    for a in range(model.articulation_count):
        for j in range(art_start[a], art_start[a + 1]):
            art_of_body[int(joint_child[j])] = a
    robot_art = [art_of_body[w * bpw + info["hand"]] for w in range(nw)]
    hand_art = robot_art[0]
    hand_link = [j - art_start[hand_art] for j in range(art_start[hand_art], art_start[hand_art + 1])
                 if joint_child[j] == info["hand"]][0]
    mask = np.zeros(model.articulation_count, dtype=bool)
    mask[robot_art] = True

    held_joint = [j for j in range(template.joint_count) if template.joint_child[j] == info["held"]][0]

    # socket shapes relative to the socket frame at its authored (nominal) pose
    body_q0 = model.body_q.numpy()
    origins = np.array([body_q0[w * bpw + 0, :3] for w in range(nw)], dtype=np.float64)  # robot base link
    socket_ids = np.array([[w * spw + s for s in info["socket"]] for w in range(nw)], dtype=np.int32)
    # x_local = x_socket^-1 x_shape, float64; the socket frame is authored unrotated
    shape_tf = torch.tensor(np.array([template.shape_transform[s] for s in info["socket"]], dtype=np.float64))
    inv_q = quat_conjugate(torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).expand(len(shape_tf), 4)
    local_p = quat_rotate(inv_q, shape_tf[:, :3] - torch.tensor(dims.FIXED_ASSET_NOMINAL_POS, dtype=torch.float64))
    socket_local = [tuple(row) for row in torch.cat((local_p, quat_mul(inv_q, shape_tf[:, 3:])), dim=1).tolist()]

    group = np.zeros(model.shape_count, dtype=np.int32)
    for w in range(nw):
        group[[w * spw + s for s in info["group"]]] = 1

    return Scene(
        task=task,
        config=config,
        model=model,
        device=device,
        num_worlds=nw,
        bodies_per_world=bpw,
        coords_per_world=cpw,
        dofs_per_world=dpw,
        env_origins=origins,
        hand_body=wp.array([w * bpw + info["hand"] for w in range(nw)], dtype=wp.int32, device=device),
        held_body=wp.array([w * bpw + info["held"] for w in range(nw)], dtype=wp.int32, device=device),
        robot_articulation=wp.array(robot_art, dtype=wp.int32, device=device),
        robot_articulation_mask=wp.array(mask, dtype=wp.bool, device=device),
        hand_link=int(hand_link),
        tcp_offset_hand=info["tcp_offset_hand"],
        held_q_start=int(template.joint_q_start[held_joint]),
        held_qd_start=int(template.joint_qd_start[held_joint]),
        socket_shapes=wp.array(socket_ids, dtype=wp.int32, device=device),
        socket_local=wp.array(socket_local, dtype=wp.transform, device=device),
        gripper_group=wp.array(group, dtype=wp.int32, device=device),
        labels={"bodies": list(template.body_label), "shapes": list(template.shape_label)},
    )


def make_solver(scene: Scene):
    """The configured solver and a collision pipeline producing its contacts."""
    return make_solver_for(scene.model, scene.task, scene.config, scene.num_worlds)


def make_solver_for(model: newton.Model, task: str, config: SimConfig, num_worlds: int):
    """`make_solver` for any model of `task` (e.g. the parts alone, tools/parts.py)."""
    nconmax, njmax = contact_limits(task, config)
    pipeline = newton.CollisionPipeline(model, rigid_contact_max=nconmax * num_worlds, broad_phase="explicit")
    if config.solver == "mujoco":
        solver = newton.solvers.SolverMuJoCo(
            model,
            use_mujoco_contacts=False,
            solver="newton",
            integrator="implicitfast",
            cone="elliptic",
            impratio=config.impratio,
            njmax=njmax,
            nconmax=nconmax,
        )
    else:
        solver = newton.solvers.SolverSteel(model)
    return solver, pipeline
