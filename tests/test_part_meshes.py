"""The mesh + SDF variant's part meshes (assets_usd/part_meshes.py): closed, outward, and the
right size, against independent references (shoelace areas, a numerical integral of the
thread's radius field, the ISO 68-1 profile's closed-form dimensions)."""

import math

import numpy as np
import pytest
import trimesh

from vkgrl_newton.assets_usd import author
from vkgrl_newton.assets_usd import dimensions as dims
from vkgrl_newton.assets_usd import part_meshes as pm

P = 0.002  # M16 x 2
R_MAJOR = 0.008
H = P * math.sqrt(3) / 2


def _shoelace(p):
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _check_closed(verts, faces):
    mesh = trimesh.Trimesh(verts, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    return mesh


def _circle(r, n=48):
    a = 2 * math.pi * np.arange(n) / n
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


def test_gear_meshes_closed_with_the_outline_area():
    outline = pm.gear_outline(19, dims.gear_root_radius("medium"), 0.021, dims.gear_tooth_width())
    assert _shoelace(outline) > 0  # counter-clockwise
    bore = _circle(dims.GEAR_BORE_APOTHEM)
    solid = _check_closed(*pm.extrude(outline, None, 0.005, 0.025))
    holed = _check_closed(*pm.extrude(outline, bore, 0.005, 0.025))
    assert solid.volume == pytest.approx(_shoelace(outline) * 0.020, rel=1e-9)
    assert holed.volume == pytest.approx((_shoelace(outline) - _shoelace(bore)) * 0.020, rel=1e-9)
    # the outline's teeth are author.gear_teeth's boxes: every tip vertex is a box corner
    corners = []
    for _, piece in author.gear_teeth("medium", dims.gear_root_radius("medium")):
        a = 2 * math.atan2(piece.quat_wxyz[3], piece.quat_wxyz[0])
        c, s = math.cos(a), math.sin(a)
        for sy in (-1, 1):
            x, y = piece.half[0], sy * piece.half[1]
            corners.append((piece.pos[0] + c * x - s * y, piece.pos[1] + s * x + c * y))
    tips = outline[np.isclose(np.hypot(outline[:, 0], outline[:, 1]), math.hypot(0.021, dims.gear_tooth_width() / 2))]
    assert len(tips) == 38
    d = np.min(np.linalg.norm(tips[:, None, :] - np.array(corners)[None], axis=-1), axis=1)
    assert d.max() < 1e-12


def test_iso_thread_profile():
    theta = np.zeros(4001)
    z = np.linspace(0.0, 2 * P, 4001)
    r = pm.iso_thread_radius(theta, z, P, R_MAJOR)
    assert r.max() == pytest.approx(R_MAJOR) and r.min() == pytest.approx(R_MAJOR - 5 * H / 8)
    # crest flat P/8 and root flat P/4 per pitch; 60-degree flanks: dr/dz = tan(60 deg) / ... = H / (P/2)
    per = len(z) // 2
    assert np.mean(np.isclose(r[:per], R_MAJOR)) == pytest.approx(1 / 8, abs=0.002)
    assert np.mean(np.isclose(r[:per], R_MAJOR - 5 * H / 8)) == pytest.approx(1 / 4, abs=0.002)
    slope = np.abs(np.diff(r) / np.diff(z))
    flank = slope[slope > 1e-6]
    np.testing.assert_allclose(flank, 2 * H / P * np.ones_like(flank), rtol=1e-6)  # = sqrt(3): 30 deg half angle
    # right hand: the profile rises one pitch per counter-clockwise turn
    th = np.linspace(0, 4 * math.pi, 50)
    z0 = np.linspace(0, P, 50)
    np.testing.assert_allclose(pm.iso_thread_radius(th, z0 + P * th / (2 * math.pi), P, R_MAJOR),
                               pm.iso_thread_radius(np.zeros(50), z0, P, R_MAJOR), atol=1e-12)


def _field_volume(r_fn, z0, z1, n=2000):
    """Volume inside r(theta, z) by a midpoint sum of r^2 / 2 dtheta dz (independent of the mesh)."""
    th = (np.arange(720) + 0.5) * 2 * math.pi / 720
    z = z0 + (np.arange(n) + 0.5) * (z1 - z0) / n
    r = r_fn(th[None, :], z[:, None])
    return float(np.sum(0.5 * r**2) * (2 * math.pi / 720) * ((z1 - z0) / n))


def test_bolt_and_nut_meshes_closed_and_sized_and_they_clear():
    z0, z1, chamfer = 0.010, 0.035, 0.001
    rod = _check_closed(*pm.threaded_rod(P, R_MAJOR, z0, z1, chamfer))
    root = R_MAJOR - 5 * H / 8

    def rod_r(th, z):
        r = pm.iso_thread_radius(th, z, P, R_MAJOR)
        return np.minimum(r, root + np.maximum(z1 - z, 0.0) * (R_MAJOR - root + chamfer) / chamfer)

    # the mesh is a 96-gon per row: its area per row is r^2/2 * 96 sin(2 pi / 96) of a circle's pi r^2
    polygon = 96 * math.sin(2 * math.pi / 96) / (2 * math.pi)
    assert rod.volume == pytest.approx(_field_volume(rod_r, z0, z1) * polygon, rel=5e-3)
    # with a pilot: thread out at 33.5 mm, root-radius pilot above with a 0.5 mm chamfer at the tip
    top = 0.0335
    piloted = _check_closed(*pm.threaded_rod(P, R_MAJOR, z0, z1, chamfer, thread_top=top))

    def piloted_r(th, z):
        r = pm.iso_thread_radius(th, z, P, R_MAJOR)
        r = np.minimum(r, root + np.maximum(top - z, 0.0) * (R_MAJOR - root + chamfer) / chamfer)
        return np.minimum(r, root - chamfer / 2 + np.maximum(z1 - z, 0.0))

    assert piloted.volume == pytest.approx(_field_volume(piloted_r, z0, z1) * polygon, rel=5e-3)
    v = piloted.vertices
    r_v = np.hypot(v[:, 0], v[:, 1])
    above = v[:, 2] > top + 1e-9
    assert r_v[above].max() == pytest.approx(root, rel=1e-6)  # a plain pilot above the thread
    assert r_v[v[:, 2] < top - 0.001].max() == pytest.approx(R_MAJOR, rel=1e-3)  # full thread below
    nut = _check_closed(*pm.threaded_bore(P, R_MAJOR, 0.00015, 0.010, 0.024, 0.0005))
    hex_area = _shoelace(pm.hex_outline(0.024))
    assert hex_area == pytest.approx(math.sqrt(3) / 2 * 0.024**2, rel=1e-12)  # 24 mm across flats

    def bore_r(th, z):
        r = pm.iso_thread_radius(th, z, P, R_MAJOR) + 0.00015
        return np.maximum(r, R_MAJOR + 0.00015 + 0.0005 - np.minimum(z, 0.010 - z))

    assert nut.volume == pytest.approx(hex_area * 0.010 - _field_volume(bore_r, 0.0, 0.010) * polygon, rel=5e-3)
    # seated on the same phase, the nut's thread clears the bolt's by the clearance everywhere
    th = np.linspace(0, 2 * math.pi, 181)[None, :]
    z = np.linspace(0.0, 0.010, 401)[:, None]
    gap = bore_r(th, z) - pm.iso_thread_radius(th, z, P, R_MAJOR)
    assert gap.min() == pytest.approx(0.00015, abs=1e-12)
