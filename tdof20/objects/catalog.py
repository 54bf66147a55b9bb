"""The 20 transparent objects of the TDoF20-style catalog: procedural watertight meshes in mm.

Model frame: millimetres, z up; every object stands upright on its base (opening up). For a
rotationally symmetric object the symmetry axis is the z axis; every object's body axis is the
z axis and the origin lies on it at the mid-height of the bounding box in z. Spouts point
towards +x, handles towards -x; the flat face of ``flask_flat_face`` faces +x.

Each builder below returns a closed, consistently wound mesh with walls of real glass
thickness; :func:`get_object` adds the derived data (diameter, symmetries, keypoints) and
caches the result.
"""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.distance import cdist

from tdof20.errors import TdofError
from tdof20.formats.bop import model_path, write_model_mesh
from tdof20.formats.io import write_json
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.objects import shapes as S
from tdof20.objects.keypoints import surface_keypoints



# ------------------------------------------------------------------------------------------
# The model container
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ObjectModel:
    """One catalog object. Arrays are read-only (models are cached and shared)."""

    obj_id: int
    name: str
    kind: str
    vertices: np.ndarray  # (V,3) float64 mm
    faces: np.ndarray  # (F,3) int64
    diameter: float  # mm, max distance between two vertices
    symmetries_continuous: tuple  # ({"axis": [0,0,1], "offset": [0,0,0]},) or ()
    symmetries_discrete: tuple  # tuple of (4,4) transforms (identity excluded) or ()
    keypoints: np.ndarray  # (9,3): bbox centre, then 8 farthest-point surface samples

    @property
    def symmetric(self) -> bool:
        return bool(self.symmetries_continuous) or bool(self.symmetries_discrete)

    @property
    def bbox_min(self) -> np.ndarray:
        return self.vertices.min(axis=0)

    @property
    def bbox_max(self) -> np.ndarray:
        return self.vertices.max(axis=0)

    @property
    def size(self) -> np.ndarray:
        """(3,) extent of the bounding box in mm."""
        return self.bbox_max - self.bbox_min

    @property
    def centre(self) -> np.ndarray:
        """(3,) centre of the axis-aligned bounding box."""
        return 0.5 * (self.bbox_min + self.bbox_max)

    @property
    def z_min(self) -> float:
        return float(self.vertices[:, 2].min())

    @property
    def footprint_radius(self) -> float:
        return float(np.sqrt((self.vertices[:, 0] ** 2 + self.vertices[:, 1] ** 2).max()))

    def to_trimesh(self) -> trimesh.Trimesh:
        """A fresh, writable trimesh copy of the model."""
        return trimesh.Trimesh(vertices=self.vertices.copy(), faces=self.faces.copy(), process=False)

    def sample_surface(self, n: int, seed: int = 0) -> np.ndarray:
        """(n,3) points uniformly distributed over the surface area; deterministic in ``seed``."""
        return sample_mesh_surface(self.vertices, self.faces, n, seed)

    def models_info(self) -> dict:
        """This object's entry of BOP ``models_info.json``."""
        lo, size = self.bbox_min, self.size
        info = {
            "diameter": float(self.diameter),
            "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2]),
        }
        if self.symmetries_continuous:
            info["symmetries_continuous"] = [
                {"axis": [float(a) for a in s["axis"]], "offset": [float(o) for o in s["offset"]]}
                for s in self.symmetries_continuous]
        if self.symmetries_discrete:
            info["symmetries_discrete"] = [[float(x) for x in np.asarray(T).reshape(-1)]
                                           for T in self.symmetries_discrete]
        return info


def max_pairwise_distance(points: np.ndarray, chunk: int = 1024) -> float:
    """Largest distance between two of ``points`` (N,3), by brute force in chunks."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best = 0.0
    for i in range(0, len(P), chunk):
        best = max(best, float(cdist(P[i:i + chunk], P[i:]).max()))
    return best


def mesh_diameter(vertices: np.ndarray) -> float:
    """Exact diameter: the farthest pair of vertices lies on the convex hull."""
    V = np.asarray(vertices, dtype=np.float64)
    hull = ConvexHull(V)
    return max_pairwise_distance(V[hull.vertices])


# ------------------------------------------------------------------------------------------
# Builders (z0 = 0 at the bottom; the catalog re-centres the bounding box in z)
# ------------------------------------------------------------------------------------------
Mesh = tuple[np.ndarray, np.ndarray] | trimesh.Trimesh


def _tumbler() -> Mesh:
    outer = S.join(S.base_with_fillet(33.0, 4.0, n_fillet=7),
                   S.wall_curve([[33.0, 4.0], [35.2, 50.0], [37.5, 95.0]], 10))
    return S.revolve(S.vessel_profile(outer, wall=2.5, floor_z=9.0), 64)


def _highball_glass() -> Mesh:
    outer = S.join(S.base_with_fillet(31.0, 3.0, n_fillet=6),
                   S.wall_curve([[31.0, 3.0], [31.8, 75.0], [32.5, 150.0]], 12))
    return S.revolve(S.vessel_profile(outer, wall=2.2, floor_z=12.0), 64)


def _wine_glass() -> Mesh:
    foot = S.join([[0.0, 0.0]], S.arc((36.0, 1.5), 1.5, -90.0, 90.0, 7))
    body = S.wall_curve([[36.0, 3.0], [20.0, 4.6], [9.0, 7.0], [5.0, 12.0], [4.0, 20.0], [4.0, 76.0],
                         [6.0, 84.0], [15.0, 92.0], [29.0, 104.0], [38.5, 124.0], [41.0, 145.0],
                         [39.5, 170.0], [35.5, 198.0]], 50)
    outer = S.join(foot, body)
    bowl = S.wall_curve([[6.0, 84.0], [15.0, 92.0], [29.0, 104.0], [38.5, 124.0], [41.0, 145.0],
                         [39.5, 170.0], [35.5, 198.0]], 30)
    bowl = S.join([[0.0, 84.0]], bowl)
    return S.revolve(S.vessel_profile(outer, wall=2.0, floor_z=93.0, inner_from=bowl), 64)


def _shot_glass() -> Mesh:
    outer = S.join(S.base_with_fillet(21.5, 2.5, n_fillet=6),
                   S.wall_curve([[21.5, 2.5], [25.0, 60.0]], 6))
    return S.revolve(S.vessel_profile(outer, wall=3.0, floor_z=16.0), 64)


def _beaker_with_spout() -> Mesh:
    outer = S.join(S.base_with_fillet(35.0, 3.0, n_fillet=6),
                   S.wall_curve([[35.0, 3.0], [35.0, 68.0]], 3),
                   S.wall_curve([[35.0, 68.0], [35.0, 90.0], [36.8, 95.0]], 14, bend_weight=0.5))
    v, f = S.revolve(S.vessel_profile(outer, wall=1.8, floor_z=2.6), 96)
    v = S.deform_radial(v, S.spout_bump(7.0, 13.0, 72.0, 95.0))
    return v, f


def _erlenmeyer_flask() -> Mesh:
    base = S.base_with_fillet(42.5, 7.0, n_fillet=7, wall_angle_deg=105.0)
    p = base[-1]
    body = [[p[0], p[1]], [33.0, 40.0], [20.5, 90.0], [17.5, 100.0], [17.0, 108.0]]
    outer = S.join(base, S.wall_curve(body + [[17.0, 139.0], [18.6, 141.0], [18.6, 145.0]], 34))
    inner_src = S.join(base, S.wall_curve(body + [[17.0, 145.0]], 30))
    return S.revolve(S.vessel_profile(outer, wall=2.0, floor_z=3.2, inner_from=inner_src), 64)


def _round_bottom_flask() -> Mesh:
    R, r_base = 42.5, 15.0
    zc = float(np.sqrt(R * R - r_base * r_base))
    a0 = float(np.degrees(np.arctan2(-zc, r_base)))
    sphere = S.arc((0.0, zc), R, a0, 58.0, 26)
    p = sphere[-1]
    neck = [[p[0], p[1]], [17.0, zc + R - 2.0], [14.5, zc + R + 7.0], [14.0, zc + R + 14.0]]
    top = zc + R + 62.0
    outer = S.join([[0.0, 0.0]], sphere,
                   S.wall_curve(neck + [[14.0, top - 6.0], [15.6, top - 4.0], [15.6, top]], 18))
    inner_src = S.join([[0.0, 0.0]], sphere, S.wall_curve(neck + [[14.0, top]], 14))
    return S.revolve(S.vessel_profile(outer, wall=2.0, floor_z=3.0, inner_from=inner_src), 64)


def _water_bottle() -> Mesh:
    body = [[33.0, 5.0], [33.0, 150.0], [31.0, 165.0], [22.0, 185.0], [15.0, 199.0], [13.5, 207.0]]
    outer = S.join(S.base_with_fillet(33.0, 5.0, n_fillet=7),
                   S.wall_curve(body + [[13.5, 216.0], [15.6, 218.0], [15.6, 225.0], [14.6, 228.0]], 40))
    inner_src = S.join(S.base_with_fillet(33.0, 5.0, n_fillet=7), S.wall_curve(body + [[13.5, 228.0]], 34))
    return S.revolve(S.vessel_profile(outer, wall=3.0, floor_z=6.0, inner_from=inner_src), 64)


def _wine_bottle() -> Mesh:
    punt = S.bezier([[0.0, 22.0], [15.0, 22.0], [24.0, 0.0], [31.0, 0.0]], 12)
    heel = S.bezier([[31.0, 0.0], [36.0, 0.0], [38.0, 3.0], [38.0, 12.0]], 8)
    body = [[38.0, 12.0], [38.0, 190.0], [36.0, 214.0], [26.0, 240.0], [17.0, 257.0], [14.5, 268.0]]
    outer = S.join(punt, heel, S.wall_curve(body + [[14.5, 287.0], [16.2, 289.0], [16.2, 296.0],
                                                    [15.2, 298.0]], 29))
    inner_src = S.join(punt, heel, S.wall_curve(body + [[14.5, 298.0]], 26))
    return S.revolve(S.vessel_profile(outer, wall=3.5, inner_from=inner_src), 64)


def _bowl() -> Mesh:
    base = S.base_with_fillet(46.0, 10.0, n_fillet=6, wall_angle_deg=45.0)
    p = base[-1]
    outer = S.join(base, S.wall_curve([[p[0], p[1]], [55.0, 11.0], [66.0, 25.0], [72.5, 45.0], [75.0, 68.0]], 18))
    return S.revolve(S.vessel_profile(outer, wall=4.0, floor_z=6.0), 64)


def _graduated_cylinder() -> Mesh:
    foot_profile = np.array([[0.0, 0.0], [34.0, 0.0], [34.0, 8.0], [32.0, 10.0], [0.0, 10.0]])
    foot = S.loft(foot_profile, S.polygon_section(6, corner_radius=0.08, corner_points=4, edge_points=2))
    outer = S.join(S.base_with_fillet(14.0, 2.0, z0=4.0, n_fillet=5),
                   S.wall_curve([[14.0, 6.0], [14.0, 228.0]], 4),
                   S.wall_curve([[14.0, 228.0], [14.0, 246.0], [15.6, 250.0]], 12, bend_weight=0.5))
    tube_v, tube_f = S.revolve(S.vessel_profile(outer, wall=1.8, floor_z=13.0), 96)
    tube_v = S.deform_radial(tube_v, S.spout_bump(8.0, 14.0, 232.0, 250.0))
    return S.union(foot, (tube_v, tube_f))


def _vase() -> Mesh:
    outer = S.join(S.base_with_fillet(38.0, 6.0, n_fillet=6),
                   S.wall_curve([[38.0, 6.0], [50.0, 28.0], [63.0, 68.0], [60.0, 108.0], [41.0, 148.0],
                                 [27.5, 172.0], [28.5, 186.0], [34.0, 200.0]], 40))
    return S.revolve(S.vessel_profile(outer, wall=3.5, floor_z=10.0), 64)


def _jar() -> Mesh:
    body = [[44.0, 6.0], [45.0, 84.0], [42.5, 93.0], [40.0, 98.0]]
    outer = S.join(S.base_with_fillet(44.0, 6.0, n_fillet=7),
                   S.wall_curve(body + [[40.0, 100.0], [42.0, 102.5], [42.0, 106.0], [40.5, 108.0],
                                        [40.0, 112.0]], 28))
    inner_src = S.join(S.base_with_fillet(44.0, 6.0, n_fillet=7), S.wall_curve(body + [[40.0, 112.0]], 20))
    return S.revolve(S.vessel_profile(outer, wall=3.0, floor_z=6.0, inner_from=inner_src), 64)


def _handle(outer: np.ndarray, wall: float, z_top: float, z_bottom: float, reach: float,
            width: float, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    path = S.handle_path(S.radius_at(outer, z_top) - wall / 2, z_top,
                         S.radius_at(outer, z_bottom) - wall / 2, z_bottom, reach, direction_deg=180.0)
    return S.tube(path, thickness / 2, 18, radius_b=width / 2, up=(0.0, 1.0, 0.0))


def _measuring_cup() -> Mesh:
    outer = S.join(S.base_with_fillet(40.0, 5.0, n_fillet=6),
                   S.wall_curve([[40.0, 5.0], [42.0, 45.0], [43.5, 75.0]], 4),
                   S.wall_curve([[43.5, 75.0], [45.0, 100.0]], 12, bend_weight=0.0))
    wall = 3.5
    v, f = S.revolve(S.vessel_profile(outer, wall=wall, floor_z=5.0), 96)
    v = S.deform_radial(v, S.spout_bump(10.0, 15.0, 76.0, 100.0))
    handle = _handle(outer, wall, 86.0, 30.0, 36.0, width=16.0, thickness=10.0)
    return S.union((v, f), handle)


def _mug() -> Mesh:
    outer = S.join(S.base_with_fillet(41.0, 5.0, n_fillet=6), S.wall_curve([[41.0, 5.0], [41.0, 98.0]], 6))
    wall = 3.5
    body = S.revolve(S.vessel_profile(outer, wall=wall, floor_z=9.0), 64)
    handle = _handle(outer, wall, 80.0, 24.0, 34.0, width=14.0, thickness=10.0)
    return S.union(body, handle)


def _pitcher() -> Mesh:
    outer = S.join(S.base_with_fillet(50.0, 8.0, n_fillet=6),
                   S.wall_curve([[50.0, 8.0], [57.5, 40.0], [60.0, 80.0], [55.5, 150.0], [50.5, 178.0]], 14),
                   S.wall_curve([[50.5, 178.0], [51.0, 195.0], [54.0, 220.0]], 14, bend_weight=0.3))
    wall = 3.5
    v, f = S.revolve(S.vessel_profile(outer, wall=wall, floor_z=8.0), 80)
    v = S.deform_radial(v, S.spout_bump(18.0, 17.0, 176.0, 220.0))
    handle = _handle(outer, wall, 196.0, 80.0, 42.0, width=20.0, thickness=12.0)
    return S.union((v, f), handle)


def _square_vase() -> Mesh:
    outer = S.join(S.base_with_fillet(35.0, 4.0, n_fillet=5),
                   S.wall_curve([[35.0, 4.0], [37.0, 100.0], [40.0, 200.0]], 10))
    section = S.polygon_section(4, corner_radius=0.15, corner_points=6, edge_points=4)
    return S.loft(S.vessel_profile(outer, wall=4.0, floor_z=12.0), section)


def _hexagonal_glass() -> Mesh:
    outer = S.join(S.base_with_fillet(33.0, 3.0, n_fillet=5),
                   S.wall_curve([[33.0, 3.0], [34.5, 50.0], [36.0, 100.0]], 8))
    section = S.polygon_section(6, corner_radius=0.08, corner_points=4, edge_points=3)
    return S.loft(S.vessel_profile(outer, wall=3.0, floor_z=12.0), section)


def _flask_flat_face() -> Mesh:
    base = S.base_with_fillet(45.0, 6.0, n_fillet=7)
    body = [[45.0, 6.0], [45.0, 118.0], [41.0, 138.0], [27.0, 154.0], [15.0, 164.0], [13.0, 172.0]]
    outer = S.join(base, S.wall_curve(body + [[13.0, 186.0], [14.8, 188.0], [14.8, 193.0],
                                              [14.0, 195.0]], 38))
    inner_src = S.join(base, S.wall_curve(body + [[13.0, 195.0]], 32))
    wall, flat_x = 3.0, 27.0
    shell = S.revolve(S.vessel_profile(outer, wall=wall, floor_z=5.0, inner_from=inner_src), 64)
    # fill the cavity beyond the inner flat face, bounded by the mid-wall surface (inside the glass)
    mid = S.closed_solid_profile(S.offset_curve(inner_src, wall / 2))
    fill = S.intersection(S.revolve(mid, 64), S.box([flat_x - wall, -100.0, -10.0], [100.0, 100.0, 300.0]))
    body_mesh = S.union(shell, fill)
    return S.intersection(body_mesh, S.box([-100.0, -100.0, -10.0], [flat_x, 100.0, 300.0]))


def _teapot() -> Mesh:
    wall = 3.5
    base = S.base_with_fillet(40.0, 6.0, n_fillet=6)
    body = S.wall_curve([[40.0, 6.0], [53.0, 22.0], [61.0, 45.0], [59.0, 75.0], [49.0, 98.0], [39.0, 110.0]], 18)
    flange = np.array([[40.5, 110.5], [41.5, 111.5], [41.5, 113.0]])
    dome_full = S.bezier([[41.5, 113.0], [36.0, 123.0], [18.0, 129.5], [0.0, 129.5]], 16)
    dome = dome_full[dome_full[:, 0] > 6.5]
    knob = S.arc((0.0, 139.0), 10.0, -53.0, 90.0, 10)
    knob[-1, 0] = 0.0
    outer_solid = S.join(base, body, flange, dome, knob)
    inner_src = S.join(base, body, S.bezier([[39.0, 110.0], [33.0, 121.0], [16.0, 127.0], [0.0, 127.0]], 14))
    cavity = S.offset_curve(inner_src, wall)
    cavity = S.truncate_from_floor(cavity, 6.0)
    cavity[-1, 0] = 0.0
    ov, of = S.revolve(outer_solid, 56)
    cv, cf = S.revolve(cavity, 56)
    hollow = (np.concatenate([ov, cv]), np.concatenate([of, cf[:, ::-1] + len(ov)]))
    # spout: a tapered tube leaving the wall at z = 40 towards +x, with a bore into the cavity
    r_mid = S.radius_at(body, 40.0) - wall / 2
    start = np.array([r_mid, 40.0])
    curve = S.bezier([[r_mid + 6.0, 40.0], [r_mid + 26.0, 40.0], [r_mid + 38.0, 80.0], [r_mid + 58.0, 112.0]], 22)
    uz = S.join([start], curve)
    path = np.stack([uz[:, 0], np.zeros(len(uz)), uz[:, 1]], axis=1)
    radii = np.interp(np.arange(len(path)), [0, len(path) - 1], [11.0, 6.0])
    spout = S.tube(path, radii, 16)
    tip_dir = path[-1] - path[-2]
    tip_dir /= np.linalg.norm(tip_dir)
    bore_path = np.concatenate([[[r_mid - 12.0, 0.0, 40.0]], path, [path[-1] + 6.0 * tip_dir]])
    bore_r = np.concatenate([[radii[0] - 2.5], radii - 2.5, [radii[-1] - 2.5]])
    bore = S.tube(bore_path, bore_r, 16)
    handle = _handle(body, wall, 100.0, 36.0, 38.0, width=18.0, thickness=11.0)
    return S.difference(S.union(hollow, spout, handle), bore)


# ------------------------------------------------------------------------------------------
# The table (ids fixed)
# ------------------------------------------------------------------------------------------
CONT = "continuous"


@dataclass(frozen=True)
class _Spec:
    name: str
    kind: str
    build: Callable[[], Mesh]
    symmetry: str | int | None  # "continuous", n (discrete n-fold about z) or None


_TABLE: dict[int, _Spec] = {
    1: _Spec("tumbler", "tumbler", _tumbler, CONT),
    2: _Spec("highball_glass", "highball glass", _highball_glass, CONT),
    3: _Spec("wine_glass", "wine glass (stem and foot)", _wine_glass, CONT),
    4: _Spec("shot_glass", "shot glass (thick base)", _shot_glass, CONT),
    5: _Spec("beaker_with_spout", "lab beaker with a pouring spout", _beaker_with_spout, None),
    6: _Spec("erlenmeyer_flask", "Erlenmeyer flask", _erlenmeyer_flask, CONT),
    7: _Spec("round_bottom_flask", "round-bottom flask (small flat base)", _round_bottom_flask, CONT),
    8: _Spec("water_bottle", "water bottle (neck and lip)", _water_bottle, CONT),
    9: _Spec("wine_bottle", "wine bottle (punt, neck, string ring)", _wine_bottle, CONT),
    10: _Spec("bowl", "bowl", _bowl, CONT),
    11: _Spec("graduated_cylinder", "graduated cylinder (spout, hexagonal foot)", _graduated_cylinder, None),
    12: _Spec("vase", "bulbous vase", _vase, CONT),
    13: _Spec("jar", "jar with a lip", _jar, CONT),
    14: _Spec("measuring_cup", "measuring cup (handle and spout)", _measuring_cup, None),
    15: _Spec("mug", "mug (handle)", _mug, None),
    16: _Spec("pitcher", "pitcher (spout and handle)", _pitcher, None),
    17: _Spec("square_vase", "square vase (square cavity)", _square_vase, 4),
    18: _Spec("hexagonal_glass", "hexagonal glass", _hexagonal_glass, 6),
    19: _Spec("flask_flat_face", "flask with one flat face (D-shaped section)", _flask_flat_face, None),
    20: _Spec("teapot", "glass teapot (spout, handle, lid knob)", _teapot, None),
}

_CONTINUOUS_Z = ({"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]},)


def _discrete_z(n: int) -> tuple:
    out = []
    for k in range(1, n):
        c, s = S.exact_cos_sin(2.0 * np.pi * k / n)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T.setflags(write=False)
        out.append(T)
    return tuple(out)


def _readonly(a: np.ndarray, dtype) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=dtype)
    a.setflags(write=False)
    return a


def _build(obj_id: int) -> ObjectModel:
    spec = _TABLE[obj_id]
    mesh = spec.build()
    if isinstance(mesh, trimesh.Trimesh):
        V, F = np.array(mesh.vertices, dtype=np.float64), np.array(mesh.faces, dtype=np.int64)
    else:
        V, F = np.array(mesh[0], dtype=np.float64), np.array(mesh[1], dtype=np.int64)
    V[:, 2] -= 0.5 * (V[:, 2].min() + V[:, 2].max())  # origin at mid-height, on the body axis
    V, F = S.orient_outward(V, F)
    keypoints = surface_keypoints(V, F)
    if spec.symmetry == CONT:
        cont, disc = _CONTINUOUS_Z, ()
    elif isinstance(spec.symmetry, int):
        cont, disc = (), _discrete_z(spec.symmetry)
    else:
        cont, disc = (), ()
    return ObjectModel(
        obj_id=obj_id, name=spec.name, kind=spec.kind,
        vertices=_readonly(V, np.float64), faces=_readonly(F, np.int64),
        diameter=mesh_diameter(V), symmetries_continuous=cont, symmetries_discrete=disc,
        keypoints=_readonly(keypoints, np.float64))


# ------------------------------------------------------------------------------------------
# Public access
# ------------------------------------------------------------------------------------------
def object_ids() -> list[int]:
    """The catalog's object ids, [1 .. 20]."""
    return sorted(_TABLE)


def _valid_range() -> str:
    ids = object_ids()
    return f"{ids[0]}-{ids[-1]}"


@functools.lru_cache(maxsize=None)
def _cached(obj_id: int) -> ObjectModel:
    return _build(obj_id)


def get_object(obj_id: int) -> ObjectModel:
    """The catalog object ``obj_id`` (built once, then cached)."""
    try:
        key = operator.index(obj_id)
    except TypeError:
        raise TdofError(f"unknown object id {obj_id!r} (valid: {_valid_range()})") from None
    if isinstance(obj_id, bool) or key not in _TABLE:
        raise TdofError(f"unknown object id {obj_id} (valid: {_valid_range()})")
    return _cached(int(key))


def all_objects() -> list[ObjectModel]:
    """All 20 objects, in id order."""
    return [get_object(i) for i in object_ids()]


def object_by_name(name: str) -> ObjectModel:
    """The object called ``name`` (snake_case, e.g. 'wine_glass')."""
    for obj_id, spec in _TABLE.items():
        if spec.name == name:
            return get_object(obj_id)
    names = ", ".join(spec.name for spec in _TABLE.values())
    raise TdofError(f"unknown object name {name!r} (valid: {names})")


def export_models(out_dir: str | Path, obj_ids=None) -> Path:
    """Write a BOP ``models`` folder: ``obj_{id:06d}.ply`` (binary PLY, mm, with vertex normals)
    and ``models_info.json``; every file is written atomically. Returns the folder."""
    out = Path(out_dir)
    ids = object_ids() if obj_ids is None else list(obj_ids)
    models = [get_object(i) for i in ids]  # unknown ids raise before anything is written
    out.mkdir(parents=True, exist_ok=True)
    info = {}
    for m in models:
        tm = m.to_trimesh()
        write_model_mesh(model_path(out, m.obj_id), tm.vertices, tm.faces)
        info[str(m.obj_id)] = m.models_info()
    write_json(out / "models_info.json", info)
    return out
