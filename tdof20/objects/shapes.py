"""Procedural builders of watertight triangle meshes (millimetres, z up).

Everything here returns plain ``(vertices (V,3) float64, faces (F,3) int64)`` pairs or
``trimesh.Trimesh`` objects that are closed, consistently wound 2-manifolds with outward normals.

Profiles live in the (s, z) half-plane, s >= 0 (for a surface of revolution s is the radius).
A *closed* profile is a polyline that starts and ends on the axis (s = 0); the segment along the
axis from its last point back to its first closes it. :func:`loft` places a scaled copy of a
closed 2D *section* loop (a unit circle for :func:`revolve`, a rounded regular polygon for
prismatic bodies) at every profile point and stitches neighbouring rings; the two axis points
become single pole vertices, so the result is watertight by construction.

Curve helpers (:func:`arc`, :func:`wall_curve`, :func:`join`, :func:`offset_curve`,
:func:`vessel_profile`) build the profiles of hollow vessels with real walls: the outer surface
from the bottom centre up to the rim, a rounded rim, and the inner surface (the outer one offset
by the wall thickness along its normals) down to a thicker floor.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

if TYPE_CHECKING:
    import trimesh

_EPS = 1e-9


# ------------------------------------------------------------------------------------------
# 2D curves in the (s, z) half-plane
# ------------------------------------------------------------------------------------------
def arc(centre: Sequence[float], radius: float, a0_deg: float, a1_deg: float, n: int) -> np.ndarray:
    """``n`` points (n,2) on a circular arc from angle a0 to a1 (degrees, from the +s axis, CCW)."""
    a = np.radians(np.linspace(a0_deg, a1_deg, max(int(n), 2)))
    return np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)], axis=1)


def join(*parts: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    """Concatenate polylines (each (k,2)), dropping points that repeat their predecessor."""
    pts = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in parts], axis=0)
    keep = np.ones(len(pts), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-7
    return pts[keep]


def resample(curve: np.ndarray, n: int, bend_weight: float = 3.0) -> np.ndarray:
    """Resample a dense polyline (k,2) to ``n`` points, denser where it bends.

    The spacing is uniform in ``length / total_length + bend_weight * turning / total_turning``
    (only the first term when the curve is straight); the end points are kept.
    """
    c = np.asarray(curve, dtype=np.float64)
    seg = np.diff(c, axis=0)
    ds = np.linalg.norm(seg, axis=1)
    ang = np.arctan2(seg[:, 1], seg[:, 0])
    turn_v = np.zeros(len(c))
    turn_v[1:-1] = np.abs(np.angle(np.exp(1j * np.diff(ang))))  # turning at interior vertices
    turn = 0.5 * (turn_v[:-1] + turn_v[1:])  # shared by the two segments at each vertex
    cost = ds / ds.sum()
    if turn.sum() > 1e-6:
        cost = cost + bend_weight * turn / turn.sum()
    cum = np.concatenate([[0.0], np.cumsum(cost)])
    u = np.linspace(0.0, cum[-1], max(int(n), 2))
    return np.stack([np.interp(u, cum, c[:, 0]), np.interp(u, cum, c[:, 1])], axis=1)


def wall_curve(knots: Sequence[Sequence[float]], n: int, bend_weight: float = 3.0) -> np.ndarray:
    """A smooth wall through knots ``(s, z)`` with z strictly increasing -> (n,2).

    s(z) is a shape-preserving (PCHIP) interpolant, so the wall does not overshoot the knots;
    points are spread by :func:`resample` (denser at shoulders and necks).
    """
    k = np.asarray(knots, dtype=np.float64)
    if np.any(np.diff(k[:, 1]) <= 0):
        raise ValueError("wall_curve knots need strictly increasing z")
    z = np.linspace(k[0, 1], k[-1, 1], 800)
    from scipy.interpolate import PchipInterpolator

    s = PchipInterpolator(k[:, 1], k[:, 0])(z)
    return resample(np.stack([s, z], axis=1), n, bend_weight)


def base_with_fillet(r_base: float, fillet: float, z0: float = 0.0, n_fillet: int = 6,
                     wall_angle_deg: float = 90.0) -> np.ndarray:
    """Bottom of a vessel: from the axis at z0 out to ``r_base - fillet``, then a fillet arc that
    ends heading at ``wall_angle_deg`` (90 = straight up). Returns (k,2) from (0, z0)."""
    c = (r_base - fillet, z0 + fillet)
    a1 = wall_angle_deg - 90.0
    return join([[0.0, z0]], arc(c, fillet, -90.0, a1, n_fillet))


def offset_curve(curve: np.ndarray, dist: float) -> np.ndarray:
    """Offset a polyline (k,2) by ``dist`` to its left (mitred vertex normals).

    Travelling up an outer wall (z increasing, s on the right-hand side), 'left' is towards the
    axis, i.e. into the glass: this gives the inner wall of a vessel.
    """
    c = np.asarray(curve, dtype=np.float64)
    d = np.diff(c, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nseg = np.stack([-d[:, 1], d[:, 0]], axis=1)  # left normals of the segments
    nv = np.empty_like(c)
    nv[0], nv[-1] = nseg[0], nseg[-1]
    mid = nseg[:-1] + nseg[1:]
    mid /= np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), _EPS)
    cos_half = np.clip(np.sum(mid * nseg[1:], axis=1), 0.5, 1.0)  # mitre, limited at 120 deg turns
    nv[1:-1] = mid / cos_half[:, None]
    return c + dist * nv


def truncate_from_floor(inner: np.ndarray, floor_z: float) -> np.ndarray:
    """Inner curve (from its bottom up to the rim) cut at z = floor_z and closed to the axis there."""
    above = np.flatnonzero(inner[:, 1] >= floor_z)
    if len(above) == 0:
        raise ValueError("the floor lies above the whole inner wall")
    k = int(above[0])
    if k == 0:  # the inner wall starts above the floor already
        if inner[0, 0] > 1e-6:
            return join([[0.0, inner[0, 1]]], inner)
        return inner
    p, q = inner[k - 1], inner[k]
    t = (floor_z - p[1]) / (q[1] - p[1])
    cut = p + t * (q - p)
    return join([[0.0, floor_z]], [cut], inner[k:])


def vessel_profile(outer: np.ndarray, wall: float, floor_z: float | None = None,
                   inner_from: np.ndarray | None = None, rim_points: int = 7) -> np.ndarray:
    """Closed profile of a hollow vessel with real walls.

    outer: (k,2) the outside from the bottom centre on the axis (0, z_bottom) up to the rim.
    wall: glass thickness; the inner wall is ``inner_from`` (default: ``outer``) offset inwards
    by ``wall``. floor_z: the inner floor height (a thicker base than the wall); the inner wall is
    cut there and closed to the axis. The rim is a half-round joining outer and inner rim points.
    Returns the closed profile: outer bottom -> outer wall -> rim -> inner wall -> floor -> axis.
    """
    outer = np.asarray(outer, dtype=np.float64)
    if abs(outer[0, 0]) > 1e-9:
        raise ValueError("a vessel's outer profile starts on the axis")
    src = outer if inner_from is None else np.asarray(inner_from, dtype=np.float64)
    inner = offset_curve(src, wall)
    if floor_z is not None:
        inner = truncate_from_floor(inner, floor_z)
    elif abs(inner[0, 0]) < wall:  # the offset of the bottom centre stays on the axis
        inner[0, 0] = 0.0
    p_out, p_in = outer[-1], inner[-1]
    m = 0.5 * (p_out + p_in)
    v = p_out - m
    half = np.linalg.norm(v)
    tangent = outer[-1] - outer[-2]
    u = np.array([-v[1], v[0]])
    u /= np.linalg.norm(u)
    if np.dot(u, tangent) < 0:
        u = -u
    a = np.linspace(0.0, np.pi, max(rim_points, 3))[1:-1]
    rim = m + np.cos(a)[:, None] * v + np.sin(a)[:, None] * half * u
    return join(outer, rim, inner[::-1])


def check_profile(profile: np.ndarray) -> None:
    """Raise ValueError unless ``profile`` is a closed profile: first and last point on the axis,
    every other point off it, and the polygon (closed along the axis) simple."""
    p = np.asarray(profile, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise ValueError("a profile is an (N,2) array with N >= 3")
    if abs(p[0, 0]) > 1e-9 or abs(p[-1, 0]) > 1e-9:
        raise ValueError("a closed profile starts and ends on the axis (s = 0)")
    if np.any(p[1:-1, 0] <= 1e-9):
        raise ValueError("only the first and last profile points may lie on the axis")
    a = p
    b = np.roll(p, -1, axis=0)  # segment i: a[i] -> b[i]; the last one runs along the axis
    n = len(a)

    def orient(p0, p1, q):
        return (p1[..., 0] - p0[..., 0]) * (q[..., 1] - p0[..., 1]) - (p1[..., 1] - p0[..., 1]) * (q[..., 0] - p0[..., 0])

    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # first and last segments share a point
    i, j = i[keep], j[keep]
    o1 = orient(a[i], b[i], a[j])
    o2 = orient(a[i], b[i], b[j])
    o3 = orient(a[j], b[j], a[i])
    o4 = orient(a[j], b[j], b[i])
    hit = (o1 * o2 < 0) & (o3 * o4 < 0)
    if np.any(hit):
        k = int(np.flatnonzero(hit)[0])
        raise ValueError(f"profile self-intersects (segments {i[k]} and {j[k]})")


def signed_area(profile: np.ndarray) -> float:
    """Shoelace area of the closed profile polygon (positive when counter-clockwise in (s, z))."""
    p = np.asarray(profile, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    return 0.5 * float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]))


# ------------------------------------------------------------------------------------------
# Sections (closed loops in the xy plane, counter-clockwise, star-shaped about the origin)
# ------------------------------------------------------------------------------------------
def circle_section(segments: int) -> np.ndarray:
    """Unit circle with ``segments`` points, the first at angle 0 (on +x)."""
    a = 2.0 * np.pi * np.arange(segments) / segments
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def polygon_section(n_sides: int, corner_radius: float = 0.0, corner_points: int = 4,
                    edge_points: int = 1) -> np.ndarray:
    """Regular polygon with unit apothem (flat sides at distance 1), optionally with rounded
    corners of radius ``corner_radius`` (in units of the apothem). The first side faces +x.

    The loop is built from one side and one corner rotated ``n_sides`` times, so it is exactly
    invariant under rotations by multiples of 360/n degrees.
    """
    if n_sides < 3:
        raise ValueError("a polygon has at least 3 sides")
    half = np.pi / n_sides
    rc = float(corner_radius)
    if not 0.0 <= rc < 1.0:
        raise ValueError("corner_radius must be in [0, 1) apothems")
    # side k=0 is the line x = 1, between the corners at angles -half and +half
    y_end = (1.0 - rc) * np.tan(half)  # where the side meets the corner's fillet arc
    pts = []
    ys = np.linspace(-y_end, y_end, edge_points + 2)[1:-1] if edge_points > 0 else np.zeros(0)
    for y in ys:
        pts.append([1.0, y])
    # corner between side 0 (normal at 0) and side 1 (normal at 2*half)
    cc = (1.0 - rc) / np.cos(half) * np.array([np.cos(half), np.sin(half)])
    if rc > 0:
        for a in np.linspace(0.0, 2.0 * half, corner_points):
            pts.append(cc + rc * np.array([np.cos(a), np.sin(a)]))
    else:
        pts.append(cc)
    unit = np.asarray(pts)
    loop = []
    for k in range(n_sides):
        c, s = exact_cos_sin(2.0 * half * k)
        R = np.array([[c, -s], [s, c]])
        loop.append(unit @ R.T)
    return np.concatenate(loop, axis=0)


def exact_cos_sin(angle: float) -> tuple[float, float]:
    c, s = np.cos(angle), np.sin(angle)
    c = round(c) if abs(c - round(c)) < 1e-12 else c
    s = round(s) if abs(s - round(s)) < 1e-12 else s
    return float(c), float(s)


# ------------------------------------------------------------------------------------------
# Meshes from profiles
# ------------------------------------------------------------------------------------------
def loft(profile: np.ndarray, section: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sweep a closed profile (N,2) of (scale, z) over a section loop (M,2).

    Profile point (s, z) becomes the ring ``s * section`` at height z; the first and last
    profile points (s = 0) become the two poles. Returns (vertices (2 + (N-2) M, 3), faces)
    forming a closed, consistently wound 2-manifold with outward normals and no duplicate
    vertices. The profile may run either way round; it must be simple (see :func:`check_profile`).
    """
    prof = np.asarray(profile, dtype=np.float64)
    check_profile(prof)
    if signed_area(prof) < 0:
        prof = prof[::-1]
    sec = np.asarray(section, dtype=np.float64)
    M = len(sec)
    # the section must run counter-clockwise seen from +z
    if 0.5 * np.sum(sec[:, 0] * np.roll(sec[:, 1], -1) - np.roll(sec[:, 0], -1) * sec[:, 1]) < 0:
        sec = sec[::-1]
    rings = prof[1:-1]
    n_r = len(rings)
    verts = np.empty((2 + n_r * M, 3))
    verts[0] = [0.0, 0.0, prof[0, 1]]
    ring_xyz = rings[:, 0, None, None] * sec[None, :, :]
    verts[1:-1, :2] = ring_xyz.reshape(-1, 2)
    verts[1:-1, 2] = np.repeat(rings[:, 1], M)
    verts[-1] = [0.0, 0.0, prof[-1, 1]]
    j = np.arange(M)
    jn = (j + 1) % M
    faces = []
    first = 1 + j  # ring 0
    faces.append(np.stack([np.zeros(M, dtype=np.int64), first[jn], first[j]], axis=1))
    for r in range(n_r - 1):
        a = 1 + r * M + j
        b = 1 + r * M + jn
        c = 1 + (r + 1) * M + jn
        d = 1 + (r + 1) * M + j
        faces.append(np.stack([a, b, c], axis=1))
        faces.append(np.stack([a, c, d], axis=1))
    last = 1 + (n_r - 1) * M + j
    pole = len(verts) - 1
    faces.append(np.stack([last[j], last[jn], np.full(M, pole)], axis=1))
    return verts, np.concatenate(faces, axis=0).astype(np.int64)


def revolve(profile: np.ndarray, segments: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Surface of revolution about z of a closed (r, z) profile, ``segments`` around."""
    return loft(profile, circle_section(segments))


def tube(path: np.ndarray, radius: float | np.ndarray, sections: int = 20,
         radius_b: float | np.ndarray | None = None, up: Sequence[float] | None = None
         ) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube swept along a 3D polyline ``path`` (K,3), capped flat at both ends.

    radius: scalar or (K,) (a taper); with ``radius_b`` the cross-section is an ellipse with
    semi-axis ``radius`` along the path's normal and ``radius_b`` along its binormal. Frames are
    parallel-transported from ``up`` (default: a fixed vector not parallel to the first tangent),
    so planar paths get planar-consistent frames. The path's curvature radius must exceed the
    tube radius (no self-intersection).
    """
    P = np.asarray(path, dtype=np.float64)
    K = len(P)
    ra = np.broadcast_to(np.asarray(radius, dtype=np.float64), (K,))
    rb = ra if radius_b is None else np.broadcast_to(np.asarray(radius_b, dtype=np.float64), (K,))
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    ref = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    if abs(np.dot(ref, T[0])) > 0.9:
        ref = np.array([1.0, 0.0, 0.0])
    B = np.cross(T[0], ref)
    B /= np.linalg.norm(B)
    frames_n = np.empty_like(P)
    frames_b = np.empty_like(P)
    for k in range(K):
        if k > 0:
            B = B - np.dot(B, T[k]) * T[k]
            B /= np.linalg.norm(B)
        N = np.cross(B, T[k])
        frames_n[k], frames_b[k] = N, B
    a = 2.0 * np.pi * np.arange(sections) / sections
    ca, sa = np.cos(a), np.sin(a)
    rings = (P[:, None, :] + (ra[:, None] * ca[None, :])[..., None] * frames_n[:, None, :]
             + (rb[:, None] * sa[None, :])[..., None] * frames_b[:, None, :])
    verts = np.concatenate([P[:1], rings.reshape(-1, 3), P[-1:]], axis=0)
    j = np.arange(sections)
    jn = (j + 1) % sections
    faces = [np.stack([np.zeros(sections, dtype=np.int64), 1 + jn, 1 + j], axis=1)]
    for k in range(K - 1):
        p0, p1 = 1 + k * sections, 1 + (k + 1) * sections
        faces.append(np.stack([p0 + j, p0 + jn, p1 + jn], axis=1))
        faces.append(np.stack([p0 + j, p1 + jn, p1 + j], axis=1))
    last = 1 + (K - 1) * sections
    faces.append(np.stack([last + j, last + jn, np.full(sections, len(verts) - 1)], axis=1))
    F = np.concatenate(faces, axis=0).astype(np.int64)
    return orient_outward(verts, F)


def bezier(ctrl: np.ndarray, n: int) -> np.ndarray:
    """Points (n, D) on the Bezier curve with control points ``ctrl`` (k, D)."""
    C = np.asarray(ctrl, dtype=np.float64)
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = [C[i] for i in range(len(C))]
    while len(pts) > 1:
        pts = [(1 - t) * pts[i] + t * pts[i + 1] for i in range(len(pts) - 1)]
    return pts[0]


# ------------------------------------------------------------------------------------------
# Mesh utilities
# ------------------------------------------------------------------------------------------
def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def orient_outward(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip every face when the (consistently wound) mesh has negative volume."""
    F = np.asarray(faces, dtype=np.int64)
    if signed_volume(vertices, F) < 0:
        F = F[:, ::-1].copy()
    return np.asarray(vertices, dtype=np.float64), F


def to_mesh(vf: tuple[np.ndarray, np.ndarray] | trimesh.Trimesh) -> trimesh.Trimesh:
    import trimesh  # imported on first use: importing the shapes (as the CLI does) stays light

    if isinstance(vf, trimesh.Trimesh):
        return vf
    v, f = vf
    return trimesh.Trimesh(vertices=np.asarray(v, dtype=np.float64), faces=np.asarray(f, dtype=np.int64),
                           process=False)


def _clean(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    import trimesh

    m = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64),
                        faces=np.asarray(mesh.faces, dtype=np.int64), process=True)
    m.remove_unreferenced_vertices()
    return m


def union(*parts) -> trimesh.Trimesh:
    """Boolean union of closed meshes (manifold3d backend); the result is watertight."""
    import trimesh

    return _clean(trimesh.boolean.union([to_mesh(p) for p in parts], engine="manifold"))


def difference(a, *b) -> trimesh.Trimesh:
    """``a`` minus every mesh in ``b`` (manifold3d backend)."""
    import trimesh

    return _clean(trimesh.boolean.difference([to_mesh(a)] + [to_mesh(p) for p in b], engine="manifold"))


def intersection(*parts) -> trimesh.Trimesh:
    """Boolean intersection of closed meshes (manifold3d backend)."""
    import trimesh

    return _clean(trimesh.boolean.intersection([to_mesh(p) for p in parts], engine="manifold"))


def box(lo: Sequence[float], hi: Sequence[float]) -> trimesh.Trimesh:
    """Axis-aligned box between corners ``lo`` and ``hi``."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    import trimesh

    b = trimesh.creation.box(extents=hi - lo)
    b.apply_translation((lo + hi) / 2.0)
    return b


def deform_radial(vertices: np.ndarray, bump: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """Move every vertex away from the z axis by ``bump(phi, z)`` mm (phi = atan2(y, x)).

    The map (r, phi, z) -> (r + bump, phi, z) is one-to-one for bump >= 0, so a closed mesh
    stays free of self-intersections (for smooth bumps and fine enough triangles): used to pull
    pouring spouts out of a rim.
    """
    v = np.array(vertices, dtype=np.float64)
    r = np.hypot(v[:, 0], v[:, 1])
    phi = np.arctan2(v[:, 1], v[:, 0])
    d = np.asarray(bump(phi, v[:, 2]), dtype=np.float64)
    ok = r > 1e-9
    v[ok, 0] += d[ok] * v[ok, 0] / r[ok]
    v[ok, 1] += d[ok] * v[ok, 1] / r[ok]
    return v


def spout_bump(amplitude: float, width_deg: float, z_start: float, z_top: float,
               direction_deg: float = 0.0) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A pouring spout: a bump of ``amplitude`` mm at the rim (z_top) in direction
    ``direction_deg``, fading to zero at z_start (smoothly, quadratically) and over an angular
    half-width ``width_deg`` (Gaussian)."""
    sigma = np.radians(width_deg)
    d0 = np.radians(direction_deg)

    def bump(phi, z):
        dphi = np.angle(np.exp(1j * (phi - d0)))
        h = np.clip((z - z_start) / (z_top - z_start), 0.0, None)
        return amplitude * np.exp(-0.5 * (dphi / sigma) ** 2) * h * h

    return bump


def handle_path(r_top: float, z_top: float, r_bottom: float, z_bottom: float, reach: float,
                direction_deg: float = 180.0, stub: float = 6.0, n: int = 28) -> np.ndarray:
    """Centre line (k,3) of a C-shaped handle in the vertical half-plane at ``direction_deg``.

    It starts at radius ``r_top`` (mid-wall of the body) at height z_top, runs straight out by
    ``stub`` mm, loops out to about ``reach`` mm beyond the body and comes back to r_bottom at
    z_bottom, ending radially again, so both flat end caps sit inside the body's wall.
    """
    u0, u1 = r_top + stub, r_bottom + stub
    a = reach / 0.75  # a cubic with horizontal end tangents bulges out by 3/4 of its handles
    loop = bezier([[u0, z_top], [u0 + a, z_top], [u1 + a, z_bottom], [u1, z_bottom]], n)
    uz = join(np.linspace([r_top, z_top], [u0, z_top], 3), loop,
              np.linspace([u1, z_bottom], [r_bottom, z_bottom], 3))
    d = np.radians(direction_deg)
    return np.stack([uz[:, 0] * np.cos(d), uz[:, 0] * np.sin(d), uz[:, 1]], axis=1)


def radius_at(curve: np.ndarray, z: float) -> float:
    """Radius of a wall curve (k,2) at height z (linear interpolation over its z-monotone part)."""
    c = np.asarray(curve, dtype=np.float64)
    order = np.argsort(c[:, 1], kind="stable")
    return float(np.interp(z, c[order, 1], c[order, 0]))


def closed_solid_profile(curve: np.ndarray) -> np.ndarray:
    """Close an outer curve (from the axis up to its last point) with a segment back to the axis."""
    c = np.asarray(curve, dtype=np.float64)
    return join(c, [[0.0, c[-1, 1]]])


# ------------------------------------------------------------------------------------------
# More sections and a prismatic vessel
# ------------------------------------------------------------------------------------------
def rounded_rect_section(half_x: float, half_y: float, corner_radius: float, corner_points: int = 6,
                         edge_points: int = 2) -> np.ndarray:
    """Rectangle ``2 half_x`` by ``2 half_y`` (mm) with corners rounded by ``corner_radius`` mm,
    counter-clockwise from +x. One quadrant is mirrored into the upper half, which is negated into
    the lower half, so the loop is exactly invariant under the half turn about z (and, for a square,
    under quarter turns up to rounding)."""
    hx, hy, r = float(half_x), float(half_y), float(corner_radius)
    if not 0.0 < r < min(hx, hy):
        raise ValueError("corner_radius must be in (0, min(half_x, half_y))")
    side_x = np.stack([np.full(edge_points + 1, hx), np.linspace(0.0, hy - r, edge_points + 2)[:-1]], axis=1)
    a = np.radians(np.linspace(0.0, 90.0, max(corner_points, 2)))
    corner = np.stack([hx - r + r * np.cos(a), hy - r + r * np.sin(a)], axis=1)
    side_y = np.stack([np.linspace(hx - r, 0.0, edge_points + 2)[1:], np.full(edge_points + 1, hy)], axis=1)
    q1 = np.concatenate([side_x, corner, side_y])  # (hx, 0) ... (0, hy)
    q2 = (q1 * [-1.0, 1.0])[::-1]  # (0, hy) ... (-hx, 0)
    half = np.concatenate([q1[:-1], q2[:-1]])  # (hx, 0) up to just before (-hx, 0)
    return np.concatenate([half, -half])


def lobed_section(n_lobes: int, amplitude: float, points_per_lobe: int = 16) -> np.ndarray:
    """A unit loop with ``n_lobes`` rounded lobes, r(phi) = 1 + amplitude * cos(n_lobes * phi)
    (a quatrefoil for 4), counter-clockwise from the lobe on +x. One lobe is rotated n times, so
    the loop is exactly invariant under rotations by 360/n degrees."""
    if n_lobes < 2 or not 0.0 < amplitude < 0.5:
        raise ValueError("lobed_section needs n_lobes >= 2 and 0 < amplitude < 0.5")
    step = 2.0 * np.pi / n_lobes
    phi = step * np.arange(points_per_lobe) / points_per_lobe
    r = 1.0 + amplitude * np.cos(n_lobes * phi)
    unit = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
    loops = []
    for k in range(n_lobes):
        c, s = exact_cos_sin(step * k)
        loops.append(unit @ np.array([[c, -s], [s, c]]).T)
    return np.concatenate(loops)


def section_area(section: np.ndarray) -> float:
    """Shoelace area of a closed section loop (M,2), positive when counter-clockwise."""
    p = np.asarray(section, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    return 0.5 * float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]))


def _unit_solid_profile(extent: float, fillet: float, z0: float, top: float, n_fillet: int = 6) -> np.ndarray:
    """Closed solid profile in (scale, z): from the axis at z0 out to scale 1 with a bottom fillet of
    ``fillet`` mm (``fillet / extent`` in scale units across), up to ``top``, back to the axis."""
    a = np.radians(np.linspace(-90.0, 0.0, n_fillet))
    f = fillet / extent
    arc_pts = np.stack([1.0 - f + f * np.cos(a), z0 + fillet + fillet * np.sin(a)], axis=1)
    return join([[0.0, z0]], arc_pts, [[1.0, top], [0.0, top]])


def prism_vessel(outer_section: np.ndarray, inner_section: np.ndarray, height: float, floor: float,
                 fillet: float = 4.0, inner_fillet: float = 3.0) -> trimesh.Trimesh:
    """An open-topped vessel with straight walls of any star-shaped cross-section: the solid loft of
    ``outer_section`` (mm) from z = 0 to ``height`` minus the loft of ``inner_section`` (mm) from the
    floor up through the top. Both bottoms are filleted; the wall thickness is the gap between the
    two sections (uniform for sections that are offsets of each other), the rim is flat."""
    r_out = float(np.linalg.norm(outer_section, axis=1).min())
    r_in = float(np.linalg.norm(inner_section, axis=1).min())
    solid = loft(_unit_solid_profile(r_out, fillet, 0.0, height), outer_section)
    cavity = loft(_unit_solid_profile(r_in, inner_fillet, floor, height + 10.0), inner_section)
    return difference(solid, cavity)
