"""GearMesh and NutThread parts: what the stages hold, checked against the published facts and
brute-force geometry, and what the contact geometry does in the solver (vkgrl_newton.tools.parts).

References: Isaac Lab Factory's factory_tasks_cfg.py (masses 0.012 / 0.03 kg, M16 x 2, 24 mm across
flats; the medium shaft's offset, dimensions.GEAR_MEDIUM_X), a plan-view polygon test of the gear teeth
written here, and the helix written out in float64 from the pitch.
"""

import math

import numpy as np
import pytest

from vkgrl_newton.assets_usd import author
from vkgrl_newton.assets_usd import dimensions as dims

M16_PITCH = 0.002
MEDIUM_SHAFT_X = dims.GEAR_MEDIUM_X  # Factory's medium-shaft offset along the gear base's x


@pytest.fixture(scope="module")
def gear_model(wp_cpu):
    from vkgrl_newton.tools.parts import build_parts

    return build_parts("GearMesh", num_worlds=2)


@pytest.fixture(scope="module")
def gear_mesh_model(wp_cpu):
    """The mesh variant on a CPU: no SDFs, the tooth meshes collide through the triangle BVH."""
    from vkgrl_newton.tools.parts import build_parts
    from vkgrl_newton.sim.scene import SimConfig

    return build_parts("GearMesh", config=SimConfig(num_worlds=2, device="cpu", geometry="mesh"))


@pytest.fixture(scope="module")
def nut_model(wp_cpu):
    from vkgrl_newton.tools.parts import build_parts

    return build_parts("NutThread", num_worlds=1)


@pytest.fixture(scope="module")
def nut_mesh_model(wp_cpu):
    """ISO-profile thread meshes on a CPU: no SDFs, the triangle BVH (scene.THREAD_MESH_GRID)."""
    from vkgrl_newton.tools.parts import build_parts
    from vkgrl_newton.sim.scene import SimConfig

    return build_parts("NutThread", config=SimConfig(num_worlds=1, device="cpu", geometry="mesh"))


def _shapes(model, prefix):
    return [i for i, lbl in enumerate(model.shape_label) if lbl.startswith(prefix)]


# ------------------------------------------------------------------ stage contents


def test_gear_stage_parts(gear_model):
    m = gear_model.model
    labels = list(m.shape_label)
    per_world = len(labels) // 2
    labels = labels[:per_world]
    held = [lbl for lbl in labels if lbl.startswith("/gear_mesh/medium_gear/")]
    assert sum("/tooth_" in lbl for lbl in held) == 19
    assert sum("/bore_" in lbl for lbl in held) == 12
    assert sum(lbl.startswith("/gear_mesh/gear_base/small_tooth") for lbl in labels) == 9
    assert sum(lbl.startswith("/gear_mesh/gear_base/large_tooth") for lbl in labels) == 29
    body_mass = m.body_mass.numpy()
    assert body_mass[gear_model.held_body] == pytest.approx(0.012, rel=1e-6)  # Factory's medium gear
    # every fixed-asset shape is static; the held gear's shapes are on its body
    shape_body = m.shape_body.numpy()
    for i, lbl in enumerate(labels):
        if lbl.startswith("/gear_mesh/gear_base/"):
            assert shape_body[i] == -1, lbl
        if lbl.startswith("/gear_mesh/medium_gear/"):
            assert shape_body[i] == gear_model.held_body, lbl
    # the medium shaft sits at Factory's offset in the base frame
    tf = m.shape_transform.numpy()
    shaft = labels.index("/gear_mesh/gear_base/shaft")
    assert tf[shaft][0] - dims.FIXED_ASSET_NOMINAL_POS[0] == pytest.approx(MEDIUM_SHAFT_X, abs=1e-6)  # two float32 x ~0.62 m (ulp 6e-8), one subtraction: <= 1.2e-7


def test_nut_stage_parts(nut_model):
    m = nut_model.model
    labels = list(m.shape_label)
    assert m.body_mass.numpy()[nut_model.held_body] == pytest.approx(0.03, rel=1e-6)  # Factory's M16 nut
    nut_thread = [i for i, lbl in enumerate(labels) if lbl.startswith("/nut_thread/nut/thread_")]
    bolt_thread = [i for i, lbl in enumerate(labels) if lbl.startswith("/nut_thread/bolt/thread_")]
    assert len(nut_thread) == dims.THREAD_NUT_TURNS * 24 and len(bolt_thread) == dims.THREAD_BOLT_TURNS * 24
    # the hex: six flats 24 mm across (outer faces at 12 mm from the axis)
    hexes = [i for i, lbl in enumerate(labels) if lbl.startswith("/nut_thread/nut/hex_")]
    tf, scale = m.shape_transform.numpy(), m.shape_scale.numpy()
    for i in hexes:
        r_centre = math.hypot(tf[i][0], tf[i][1])
        # float32 storage (IEEE conversion, the same on any CPU) of positions ~0.6 m: <= 6e-8 each; 1e-6 bounds it
        assert r_centre + scale[i][0] == pytest.approx(0.012, abs=1e-6)


def test_bolt_thread_is_an_m16x2_right_hand_helix(nut_model):
    """Capsule centres of the bolt thread, in the bolt frame, lie on a helix rising 2 mm per
    counter-clockwise turn (right hand) at the authored radius (the chord midpoints sag inwards by
    r (1 - cos(pi / 24)))."""
    m = nut_model.model
    labels = list(m.shape_label)
    tf = m.shape_transform.numpy()
    idx = [i for i, lbl in enumerate(labels) if lbl.startswith("/nut_thread/bolt/thread_")]
    c = np.array([tf[i][:3] for i in idx], dtype=np.float64) - np.array(dims.FIXED_ASSET_NOMINAL_POS)
    theta = np.unwrap(np.arctan2(c[:, 1], c[:, 0]))
    slope = np.polyfit(theta / (2 * math.pi), c[:, 2], 1)[0]
    assert slope == pytest.approx(M16_PITCH, rel=1e-4)
    r = np.hypot(c[:, 0], c[:, 1])
    # the centres are float32 positions ~0.6 m (IEEE conversion: half an ulp, 3e-8 m per axis, on any CPU):
    # r ~ 7.9 mm to <= 4.2e-8 m, 5.4e-6 relative; the fit's slope over hundreds of centres far better
    np.testing.assert_allclose(r, dims.THREAD_BOLT_RADIUS * math.cos(math.pi / 24), rtol=1e-5)


def _tooth_polygons(pieces, yaw=0.0, centre=(0.0, 0.0)):
    polys = []
    c, s = math.cos(yaw), math.sin(yaw)
    for _, p in pieces:
        hx, hy, _ = p.half
        w, _, _, qz = p.quat_wxyz
        a = 2 * math.atan2(qz, w)
        corners = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        pts = corners @ rot.T + np.array(p.pos[:2])
        pts = pts @ np.array([[c, -s], [s, c]]).T + np.array(centre)
        polys.append(pts)
    return polys


def _separated(a, b) -> bool:
    """Separating-axis test for two convex polygons (float64): True if they do not overlap."""
    for poly in (a, b):
        for k in range(len(poly)):
            e = poly[(k + 1) % len(poly)] - poly[k]
            n = np.array([-e[1], e[0]])
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return True
    return False


def test_gear_teeth_mesh_only_when_aligned():
    """Plan view, brute force over all tooth pairs: at yaw 0 the medium gear's teeth clear both
    neighbours' teeth and cores; turned by half a tooth pitch some tooth overlaps a neighbour's."""
    centres = dims.gear_centres()
    neighbours = []
    for name in ("small", "large"):
        neighbours += _tooth_polygons(author.gear_teeth(name, dims.gear_root_radius(name) - 0.0005, centres[name]))
    pitch = 2 * math.pi / 19

    def clashes(yaw):
        medium = _tooth_polygons(author.gear_teeth("medium", dims.GEAR_BORE_APOTHEM + 0.0018), yaw,
                                 centres["medium"])
        n = sum(not _separated(a, b) for a in medium for b in neighbours)
        # cores: the tooth corners must stay outside the neighbours' root circles
        for name in ("small", "large"):
            r_core = dims.gear_root_radius(name)
            for poly in medium:
                n += int(np.any(np.hypot(*(poly - np.array(centres[name])).T) < r_core))
        return n

    assert clashes(0.0) == 0
    for k in (-1, 1, 5):
        assert clashes(k * pitch) == 0  # any whole tooth pitch meshes too
    assert clashes(pitch / 2) > 0
    assert clashes(0.25 * pitch) > 0


# ------------------------------------------------------------------ physics (MuJoCo-Warp on CPU)


# The mesh runs are short: the thread meshes cost ~0.4 s per frame on a CPU (docs/log/benchmarks.md).
# They start one turn lower: the mesh bolt's thread runs out over its top turn into the pilot.
NUT_GEOMETRIES = [("primitives", 0.8, 0.4, 0.0), ("mesh", 0.3, 0.15, M16_PITCH)]


@pytest.mark.slow
@pytest.mark.parametrize("geometry, duration, min_turns, start_depth", NUT_GEOMETRIES)
def test_nut_advances_one_pitch_per_turn(request, geometry, duration, min_turns, start_depth):
    """Started resting on the bolt's top thread turn and turned clockwise under a 0.5 N push, the
    nut screws down 2 mm per turn (Factory's M16 x 2) within 10 %, without tilting off the thread.
    Both geometries: the capsule helices and the ISO-profile meshes."""
    from vkgrl_newton.tools.parts import advance_per_turn, nut_rest_height, run_drive

    nut_model = request.getfixturevalue("nut_model" if geometry == "primitives" else "nut_mesh_model")
    yaw0 = math.pi / 2
    r = run_drive(nut_model, (0.0, 0.0, nut_rest_height(yaw0) - start_depth), yaw0, duration, force_z=-0.5,
                  omega_des=-2 * math.pi, torque_kd=1e-3)
    turns = (yaw0 - r.yaw[-1, 0]) / (2 * math.pi)
    assert turns > min_turns  # it turned, clockwise
    assert advance_per_turn(r) == pytest.approx(M16_PITCH, rel=0.1)
    assert r.tilt.max() < math.radians(5.0)
    # and it stays on the axis (radial play 0.25 mm by design, author.py)
    assert np.hypot(r.pos[-1, 0, 0], r.pos[-1, 0, 1]) < 0.0005


@pytest.mark.slow
@pytest.mark.parametrize("geometry, start_depth", [(g, d) for g, _, _, d in NUT_GEOMETRIES])
def test_nut_does_not_descend_without_turning(request, geometry, start_depth):
    from vkgrl_newton.tools.parts import nut_rest_height, run_drive

    nut_model = request.getfixturevalue("nut_model" if geometry == "primitives" else "nut_mesh_model")
    yaw0 = math.pi / 2
    z0 = nut_rest_height(yaw0) - start_depth
    r = run_drive(nut_model, (0.0, 0.0, z0), yaw0, 0.3, force_z=-0.5)
    assert abs(r.yaw[-1, 0] - yaw0) < math.radians(3.0)
    assert r.pos[-1, 0, 2] > z0 - 0.0003  # settles by less than the thread clearance


@pytest.mark.parametrize("geometry", ["primitives", "mesh"])
def test_gear_slides_when_aligned_and_is_blocked_when_not(request, geometry):
    """Pushed down (1 N) from above its shaft: at yaw 0 (teeth facing the neighbours' gaps) the
    medium gear seats on the base plate; turned by half a tooth pitch it rests on the neighbours'
    tooth tops, one face width (20 mm) higher. Both collision geometries (the mesh variant's
    tooth meshes meet through the triangle BVH here, no SDF on a CPU)."""
    from vkgrl_newton.tools.parts import run_drive

    model = request.getfixturevalue("gear_model" if geometry == "primitives" else "gear_mesh_model")
    pitch = 2 * math.pi / 19
    r = run_drive(model, (MEDIUM_SHAFT_X, 0.0, 0.03), [0.0, pitch / 2], 0.4, force_z=-1.0)
    z_aligned, z_blocked = r.pos[-1, 0, 2], r.pos[-1, 1, 2]
    assert abs(z_aligned) < 0.0005  # seated: origin at the base frame's level
    assert z_blocked == pytest.approx(dims.GEAR_HEIGHT, abs=0.0005)
    assert np.hypot(r.pos[-1, 0, 0] - MEDIUM_SHAFT_X, r.pos[-1, 0, 1]) < 0.0005


@pytest.mark.parametrize("task, meshes, off_prefixes, kept_prefixes", [
    ("GearMesh", {"medium_gear/gear_mesh": "held", "gear_base/small_gear_mesh": -1, "gear_base/large_gear_mesh": -1},
     ("medium_gear/tooth_", "gear_base/small_", "gear_base/large_"), ("medium_gear/bore_", "medium_gear/hub")),
    ("NutThread", {"nut/thread_mesh": "held", "bolt/thread_mesh": -1},
     ("nut/thread_", "bolt/thread_"), ("nut/hex_", "bolt/core")),
])
def test_mesh_variant_replaces_the_primitive_teeth_and_threads(wp_cpu, task, meshes, off_prefixes, kept_prefixes):
    """geometry='mesh' (template only, no SDF on a CPU): the primitives the meshes stand in for
    stop colliding, the meshes sit on the same bodies with the parts' friction, the held part's
    mass is still the authored one (the meshes add none), and the meshes collide with meshes
    only: every other colliding shape (bore ring, hex, plate, finger pads) is filtered against
    each of them and keeps its own contacts."""
    import newton

    from vkgrl_newton.sim.scene import SimConfig, build_template, stage_root

    prim, _ = build_template(task, SimConfig(num_worlds=1, device="cpu"))
    mesh, info = build_template(task, SimConfig(num_worlds=1, device="cpu", geometry="mesh"))
    root = f"/{stage_root(task)}/"
    collide = int(newton.ShapeFlags.COLLIDE_SHAPES)
    labels = list(mesh.shape_label)
    for suffix, body in meshes.items():
        s = labels.index(root + suffix)
        assert mesh.shape_type[s] == newton.GeoType.MESH and mesh.shape_flags[s] & collide
        assert mesh.shape_flags[s] & int(newton.ShapeFlags.VISIBLE)
        assert mesh.shape_body[s] == (info["held"] if body == "held" else -1)
        assert (root + suffix) not in prim.shape_label
    for s, lbl in enumerate(labels):
        if any(lbl.startswith(root + p) for p in off_prefixes) and not lbl.endswith("_mesh"):
            assert not mesh.shape_flags[s] & collide, lbl
            assert not mesh.shape_flags[s] & int(newton.ShapeFlags.VISIBLE), lbl  # the camera sees the mesh
    assert mesh.body_mass[info["held"]] == pytest.approx(prim.body_mass[info["held"]], rel=1e-9)
    fixed_mesh = [root + k for k, b in meshes.items() if b == -1]
    assert all(labels.index(m) in info["socket"] for m in fixed_mesh)  # re-placed with the fixed asset
    kept = [s for s, lbl in enumerate(labels) if any(lbl.startswith(root + p) for p in kept_prefixes)]
    assert kept and all(mesh.shape_flags[s] & collide for s in kept)
    visible = int(newton.ShapeFlags.VISIBLE)
    for s in kept:  # inside a mesh (bore ring, hex) they are not drawn; the hub, core stay visible
        inside = labels[s].startswith((root + "medium_gear/bore_", root + "nut/hex_"))
        assert bool(mesh.shape_flags[s] & visible) != inside, labels[s]
    mesh_shapes = {labels.index(root + k) for k in meshes}
    others = {s for s in range(len(labels)) if s not in mesh_shapes and mesh.shape_flags[s] & collide}
    assert set(info["pads"]) <= others and set(kept) <= others
    filtered = set(mesh.shape_collision_filter_pairs)
    for m in mesh_shapes:
        assert all((min(m, s), max(m, s)) in filtered for s in others)
        assert not any((min(m, n), max(m, n)) in filtered for n in mesh_shapes if n != m)


@pytest.mark.parametrize("task", ["GearMesh", "NutThread"])
def test_mesh_variant_builds_an_sdf_per_mesh_on_cuda(wp_cpu, task, monkeypatch):
    """The SDF build runs on CUDA only (Newton raises on a CPU), so here `Mesh.build_sdf` is
    replaced by a recorder that binds each call to Newton's real signature: every part mesh gets
    one SDF with the task's voxel size, and the threads use the finer SDF grid."""
    import inspect

    import newton

    from vkgrl_newton.sim import scene

    real = inspect.signature(newton.Mesh.build_sdf)
    calls = []

    def record(self, *args, **kwargs):
        real.bind(self, *args, **kwargs)  # TypeError if Newton's API no longer takes these
        calls.append((len(self.vertices), kwargs))

    monkeypatch.setattr(newton.Mesh, "build_sdf", record)
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    from vkgrl_newton.assets_usd import TASK_USD

    builder.add_usd(str(TASK_USD[task]))
    added = scene.add_part_meshes(builder, task, sdf_device="cuda:0")
    assert len(calls) == len(added) == (3 if task == "GearMesh" else 2)
    for _, kw in calls:
        assert kw["device"] == "cuda:0" and kw["target_voxel_size"] == scene.SDF_VOXEL[task]
        assert kw["narrow_band_range"] == scene.SDF_BAND and kw["margin"] == scene.SDF_MARGIN
    if task == "NutThread":  # the threads on the SDF grid: columns x rows over the shank, + 2 cap centres
        columns, rows_per_pitch = scene.THREAD_MESH_GRID["sdf"]
        tip = dims.BOLT_BASE_HEIGHT + dims.BOLT_SHANK_HEIGHT  # as scene.add_part_meshes and threaded_rod
        rows = int(math.ceil((tip - dims.BOLT_BASE_HEIGHT) / dims.THREAD_PITCH * rows_per_pitch)) + 1
        assert calls[0][0] == columns * rows + 2
