"""Closed triangle meshes of the GearMesh and NutThread parts, for the mesh + SDF collision variant.

Newton builds signed distance fields of meshes on CUDA only, so these are the GPU variant's
geometry (the CPU variant is the primitives of author.py). Plain numpy, no boolean library:
- `gear_outline`: the gear's plan-view outline (root circle between straight box teeth, the
  same teeth as author.gear_teeth), counter-clockwise;
- `extrude`: a plan-view region between an outer loop and an optional inner loop (a bore), both
  star-shaped about the origin, swept along z into a closed mesh with outward normals;
- `threaded_rod` / `threaded_bore`: the bolt's shank and the nut, with an ISO 68-1 basic thread
  profile (60 degrees, crest flat P/8, root flat P/4, depth 5/8 H) as a radius field r(theta, z)
  on a grid, right-hand (a point of the ridge rises one pitch per counter-clockwise turn).
Every mesh returns (vertices (V, 3) float64, faces (F, 3) int64), closed and consistently
oriented (tests/test_part_meshes.py checks both, and the volumes against independent sums).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["gear_outline", "extrude", "iso_thread_radius", "threaded_rod", "threaded_bore", "hex_outline"]


def gear_outline(teeth: int, root_radius: float, tip_radius: float, tooth_width: float,
                 arc_points: int = 4) -> np.ndarray:
    """(n, 2) counter-clockwise outline: tooth k (a box of `tooth_width` centred on angle
    2 pi k / teeth, from the root circle to `tip_radius`), root-circle arcs between teeth."""
    half = tooth_width / 2
    x_root = math.sqrt(root_radius**2 - half**2)
    a_root = math.asin(half / root_radius)  # angular half width of a tooth at the root
    pitch = 2 * math.pi / teeth
    pts = []
    for k in range(teeth):
        c = k * pitch
        rot = np.array([[math.cos(c), -math.sin(c)], [math.sin(c), math.cos(c)]])
        # tooth, counter-clockwise: root (right flank), tip corners, root (left flank)
        for p in ((x_root, -half), (tip_radius, -half), (tip_radius, half), (x_root, half)):
            pts.append(rot @ np.array(p))
        # root arc to the next tooth (interior points only)
        a0, a1 = c + a_root, c + pitch - a_root
        for t in np.linspace(0.0, 1.0, arc_points + 2)[1:-1]:
            a = a0 + (a1 - a0) * t
            pts.append(np.array([root_radius * math.cos(a), root_radius * math.sin(a)]))
    return np.array(pts)


def hex_outline(across_flats: float) -> np.ndarray:
    """(6, 2) counter-clockwise hexagon, flats facing +-y and 60 degrees on (as author.nut_hex_pieces)."""
    r = across_flats / 2 / math.cos(math.pi / 6)  # corner radius
    return np.array([[r * math.cos(k * math.pi / 3), r * math.sin(k * math.pi / 3)] for k in range(6)])


def _angles(loop: np.ndarray) -> np.ndarray:
    return np.arctan2(loop[:, 1], loop[:, 0])


def _zipper(outer: np.ndarray, inner: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles (counter-clockwise seen from +z) filling the ring between two closed,
    counter-clockwise loops that are star-shaped about the origin; indices into
    concatenate([outer, inner]). Walks both loops by angle, one vertex at a time."""
    n, m = len(outer), len(inner)
    a_out, a_in = _angles(outer), _angles(inner)
    i0, j0 = int(np.argmin(np.mod(a_out, 2 * math.pi))), int(np.argmin(np.mod(a_in, 2 * math.pi)))
    start = min(np.mod(a_out[i0], 2 * math.pi), np.mod(a_in[j0], 2 * math.pi))

    def unwrap(a, i):
        return np.mod(a[i] - start, 2 * math.pi)

    tris = []
    i = j = 0  # steps taken along each loop
    while i < n or j < m:
        oi, oi1 = (i0 + i) % n, (i0 + i + 1) % n
        ij, ij1 = (j0 + j) % m, (j0 + j + 1) % m
        next_out = unwrap(a_out, oi1) if i + 1 < n else 2 * math.pi
        next_in = unwrap(a_in, ij1) if j + 1 < m else 2 * math.pi
        if j >= m or (i < n and next_out <= next_in):
            tris.append((oi, oi1, n + ij))
            i += 1
        else:
            tris.append((oi, n + ij1, n + ij))
            j += 1
    return tris


def _fan(loop: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of a star-shaped counter-clockwise loop around a centre vertex (index len(loop))."""
    n = len(loop)
    return [(k, (k + 1) % n, n) for k in range(n)]


def extrude(outer: np.ndarray, inner: np.ndarray | None, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed mesh of the region between `outer` and `inner` (None: solid) from z0 to z1."""
    outer = np.asarray(outer, dtype=np.float64)
    if inner is None:
        ring = np.vstack([outer, [[0.0, 0.0]]])
        cap = _fan(outer)
    else:
        ring = np.vstack([outer, np.asarray(inner, dtype=np.float64)])
        cap = _zipper(outer, np.asarray(inner, dtype=np.float64))
    k = len(ring)
    verts = np.vstack([np.column_stack([ring, np.full(k, z0)]), np.column_stack([ring, np.full(k, z1)])])
    faces = [(c, b, a) for a, b, c in cap]  # bottom, facing -z
    faces += [(a + k, b + k, c + k) for a, b, c in cap]  # top, facing +z
    n = len(outer)
    for e in range(n):  # outer wall: the region is to the left of a counter-clockwise edge
        a, b = e, (e + 1) % n
        faces += [(a, b, b + k), (a, b + k, a + k)]
    if inner is not None:
        m = len(inner)
        for e in range(m):  # bore wall, facing the axis
            a, b = n + e, n + (e + 1) % m
            faces += [(b, a, a + k), (b, a + k, b + k)]
    return verts, np.array(faces, dtype=np.int64)


def iso_thread_radius(theta: np.ndarray, z: np.ndarray, pitch: float, major_radius: float) -> np.ndarray:
    """ISO 68-1 basic external thread: radius at (theta, z) for a right-hand thread whose crest
    centre passes theta = 0 at z = 0. Crest flat P/8 at the major radius, root flat P/4 at
    major - 5H/8 (H = P sqrt(3) / 2), straight 60-degree flanks between."""
    depth = 5.0 / 8.0 * pitch * math.sqrt(3.0) / 2.0
    u = np.mod((z - pitch * theta / (2 * math.pi)) / pitch + 1.0 / 16.0, 1.0)  # 0 at the crest's start
    # crest [0, 1/8], down flank [1/8, 7/16], root [7/16, 11/16], up flank [11/16, 1]
    down = np.clip((u - 1 / 8) / (5 / 16), 0.0, 1.0)
    up = np.clip((u - 11 / 16) / (5 / 16), 0.0, 1.0)
    return major_radius - depth * (down - up)


def _radial_grid(radius: np.ndarray, theta: np.ndarray, z: np.ndarray):
    """Vertices (len(z) x len(theta)) of the surface r(theta, z) and its quads' triangles,
    oriented with the normal pointing away from the axis."""
    t, zz = np.meshgrid(theta, z)  # (nz, nt)
    verts = np.column_stack([(radius * np.cos(t)).ravel(), (radius * np.sin(t)).ravel(), zz.ravel()])
    nz, nt = radius.shape
    faces = []
    for j in range(nz - 1):
        for i in range(nt):
            a, b = j * nt + i, j * nt + (i + 1) % nt
            c, d = a + nt, b + nt
            faces += [(a, b, d), (a, d, c)]
    return verts, faces


def threaded_rod(pitch: float, major_radius: float, z0: float, z1: float, chamfer: float,
                 thread_top: float | None = None, columns: int = 96,
                 rows_per_pitch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The bolt's threaded shank from z0 to z1; flat caps (fans) at both ends.

    thread_top None: threaded to the top, chamfered at 45 degrees down to the root radius over
    `chamfer`. thread_top < z1: the thread runs out the same way at thread_top, and above it is a
    plain pilot of root radius with a 45-degree `chamfer` / 2 at its top edge: it centres a nut
    within the thread clearance before the nut's thread meets the bolt's (a dog point)."""
    if thread_top is not None and not z0 < thread_top <= z1:
        raise ValueError(f"thread_top must lie in ({z0}, {z1}], got {thread_top}")
    theta = 2 * math.pi * np.arange(columns) / columns
    rows = int(math.ceil((z1 - z0) / pitch * rows_per_pitch)) + 1
    z = np.linspace(z0, z1, rows)
    r = iso_thread_radius(theta[None, :], z[:, None], pitch, major_radius)
    root = major_radius - 5.0 / 8.0 * pitch * math.sqrt(3.0) / 2.0
    top = z1 if thread_top is None else thread_top
    r = np.minimum(r, root + np.maximum(top - z[:, None], 0.0) * (major_radius - root + chamfer) / chamfer)
    if thread_top is not None:
        r = np.minimum(r, root - chamfer / 2 + np.maximum(z1 - z[:, None], 0.0))
    verts, faces = _radial_grid(r, theta, z)
    nt = columns
    bottom = len(verts)
    top = bottom + 1
    verts = np.vstack([verts, [[0.0, 0.0, z0], [0.0, 0.0, z1]]])
    last = (rows - 1) * nt
    faces += [((i + 1) % nt, i, bottom) for i in range(nt)]  # bottom cap, facing -z
    faces += [(last + i, last + (i + 1) % nt, top) for i in range(nt)]  # top cap, facing +z
    return verts, np.array(faces, dtype=np.int64)


def threaded_bore(pitch: float, major_radius: float, clearance: float, height: float, across_flats: float,
                  countersink: float, columns: int = 96, rows_per_pitch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The nut, z 0..height: a hex prism with a threaded hole whose surface is the external thread
    (`iso_thread_radius`, same phase) moved out by `clearance`, widened at both faces by a
    45-degree countersink to the major radius + clearance over `countersink`."""
    theta = 2 * math.pi * np.arange(columns) / columns
    rows = int(math.ceil(height / pitch * rows_per_pitch)) + 1
    z = np.linspace(0.0, height, rows)
    r = iso_thread_radius(theta[None, :], z[:, None], pitch, major_radius) + clearance
    edge = np.minimum(z, height - z)[:, None]  # distance to the nearer face
    r = np.maximum(r, major_radius + clearance + countersink - edge)
    bore, bore_faces = _radial_grid(r, theta, z)
    bore_faces = [(a, c, b) for a, b, c in bore_faces]  # the hole's surface faces the axis
    hexagon = hex_outline(across_flats)
    nt = columns
    nb = len(bore)
    verts = np.vstack([bore, np.column_stack([hexagon, np.zeros(6)]), np.column_stack([hexagon, np.full(6, height)])])
    faces = list(bore_faces)
    h0, h1 = nb, nb + 6
    for e in range(6):  # hex walls
        a, b = e, (e + 1) % 6
        faces += [(h0 + a, h0 + b, h1 + b), (h0 + a, h1 + b, h1 + a)]
    for face, (hex_start, ring_start, up) in (("bottom", (h0, 0, False)), ("top", (h1, (rows - 1) * nt, True))):
        ring = bore[ring_start:ring_start + nt, :2]
        for a, b, c in _zipper(hexagon, ring):
            idx = [hex_start + v if v < 6 else ring_start + v - 6 for v in (a, b, c)]
            faces.append(tuple(idx) if up else tuple(idx[::-1]))
    return verts, np.array(faces, dtype=np.int64)
