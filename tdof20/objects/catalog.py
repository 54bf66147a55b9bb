"""TDoF20's 20 transparent object classes: procedural watertight meshes in mm.

Ids 1..20 follow the release's class list (cube_136 ... whisky_cup_270); the number at the end of
a name is the capacity in ml, and each mesh is sized so that its cavity holds that much filled to
the brim (:attr:`ObjectModel.capacity_ml`, within a few per cent).

Model frame: millimetres, z up; every object stands upright on its base (opening up). For a
symmetric object the symmetry axis is the z axis; every object's body axis is the z axis and
the origin lies on it at the mid-height of the bounding box in z. Handles point towards -x; the
long side of a cuboid's section runs along x.

Each builder below returns a closed, consistently wound mesh with walls of real glass
thickness; :func:`get_object` adds the derived data (diameter, symmetries, keypoints) and
caches the result.
"""

from __future__ import annotations

import functools
import json
import operator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop_models import model_path, write_model_mesh
from tdof20.formats.io import read_json, write_json
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
    def nominal_capacity_ml(self) -> int:
        """The capacity the name states (the number at its end, in ml)."""
        return int(self.name.rsplit("_", 1)[1])

    @functools.cached_property
    def capacity_ml(self) -> float:
        """The volume the cup holds filled to the brim, in ml, measured on the mesh
        (:func:`cavity_volume`; computed once per object, ~0.1 s)."""
        return cavity_volume(self.vertices, self.faces) / 1000.0

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
        import trimesh

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
    from scipy.spatial.distance import cdist

    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best = 0.0
    for i in range(0, len(P), chunk):
        best = max(best, float(cdist(P[i:i + chunk], P[i:]).max()))
    return best


def cavity_volume(vertices: np.ndarray, faces: np.ndarray, step: float = 1.5, seed: int = 0) -> float:
    """Volume (mm^3) of the open cavity of a vessel up to the top of its rim, sampled with one
    jittered point per cell of a grid of ``step`` mm (about 1 % accurate at 1.5 mm).

    A grid point belongs to the cavity when it lies outside the glass and the rays from it along
    +x, -x, +y, -y and -z all meet the mesh from outside (the first triangle hit faces the point):
    air walled in on every side but the top. Air around a stem, under a flaring bowl or inside a
    handle's loop escapes sideways and is not counted. Needs a closed mesh with outward normals.
    """
    from tdof20.o3d import o3d

    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    n = np.maximum(np.ceil((hi - lo) / step).astype(int), 1)
    cell = (hi - lo) / n  # cells of about ``step`` that tile the bounding box exactly
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), axis=-1).reshape(-1, 3)
    # one point per cell, jittered (fixed seed): no aliasing with walls parallel to the grid
    pts = (lo + (idx + np.random.default_rng(seed).uniform(0.0, 1.0, idx.shape)) * cell).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inside = np.ones(len(pts), dtype=bool)
    for d in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1]):
        keep = np.flatnonzero(inside)
        if len(keep) == 0:
            break
        dirs = np.broadcast_to(np.asarray(d, np.float32), (len(keep), 3))
        hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(np.concatenate([pts[keep], dirs], axis=1))))
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        ok = prim != scene.INVALID_ID
        ok[ok] = normals[prim[ok]] @ np.asarray(d, np.float64) < 0  # met from outside the glass
        inside[keep[~ok]] = False
    return float(inside.sum()) * float(np.prod(cell))


def mesh_diameter(vertices: np.ndarray) -> float:
    """Exact diameter: the farthest pair of vertices lies on the convex hull."""
    from scipy.spatial import ConvexHull

    V = np.asarray(vertices, dtype=np.float64)
    hull = ConvexHull(V)
    return max_pairwise_distance(V[hull.vertices])


# ------------------------------------------------------------------------------------------
# Builders (z0 = 0 at the bottom; the catalog re-centres the bounding box in z)
# ------------------------------------------------------------------------------------------
if TYPE_CHECKING:  # trimesh is imported where a mesh is built (importing the catalog stays light)
    import trimesh

    Mesh = tuple[np.ndarray, np.ndarray] | trimesh.Trimesh


def _tumbler(r_base: float, r_top: float, height: float, wall: float, floor: float, fillet: float = 4.0,
             belly: float = 0.0) -> Mesh:
    """A round tumbler: straight or slightly tapered wall (``belly`` bulges it at mid-height)."""
    mid = 0.5 * (r_base + r_top) + belly
    outer = S.join(S.base_with_fillet(r_base, fillet, n_fillet=6),
                   S.wall_curve([[r_base, fillet], [mid, 0.5 * (fillet + height)], [r_top, height]], 10))
    return S.revolve(S.vessel_profile(outer, wall=wall, floor_z=floor), 64)


def _goblet(bowl_r: float, bowl_depth: float, stem_h: float, foot_r: float, wall: float = 2.0) -> Mesh:
    """A bowl on a stem and a round foot."""
    zb, R, D = stem_h, bowl_r, bowl_depth
    foot = S.join([[0.0, 0.0]], S.arc((foot_r, 1.5), 1.5, -90.0, 90.0, 7))
    stem = [[foot_r, 3.0], [0.55 * foot_r, 4.6], [9.0, 7.0], [5.0, 12.0], [4.5, 18.0], [4.5, zb - 10.0]]
    bowl = [[6.5, zb], [0.5 * R, zb + 0.1 * D], [0.85 * R, zb + 0.3 * D], [R, zb + 0.6 * D],
            [0.94 * R, zb + D]]
    outer = S.join(foot, S.wall_curve(stem + bowl, 50))
    inner_src = S.join([[0.0, zb]], S.wall_curve(bowl, 30))
    return S.revolve(S.vessel_profile(outer, wall=wall, floor_z=zb + 8.0, inner_from=inner_src), 64)


def _icecream_cup(rim_r: float, bowl_depth: float, stem_h: float, foot_r: float, wall: float = 2.5) -> Mesh:
    """A wide bowl flaring out to its rim, on a short stem and a round foot."""
    zb, R, D = stem_h, rim_r, bowl_depth
    foot = S.join([[0.0, 0.0]], S.arc((foot_r, 2.0), 2.0, -90.0, 90.0, 7))
    stem = [[foot_r, 4.0], [0.6 * foot_r, 5.5], [10.0, 8.0], [8.5, 12.0], [8.5, zb - 4.0]]
    bowl = [[11.0, zb], [0.55 * R, zb + 0.18 * D], [0.82 * R, zb + 0.5 * D], [R, zb + D]]
    outer = S.join(foot, S.wall_curve(stem + bowl, 40))
    inner_src = S.join([[0.0, zb]], S.wall_curve(bowl, 24))
    return S.revolve(S.vessel_profile(outer, wall=wall, floor_z=zb + 6.0, inner_from=inner_src), 64)


def _handle(outer: np.ndarray, wall: float, z_top: float, z_bottom: float, reach: float,
            width: float, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    path = S.handle_path(S.radius_at(outer, z_top) - wall / 2, z_top,
                         S.radius_at(outer, z_bottom) - wall / 2, z_bottom, reach, direction_deg=180.0)
    return S.tube(path, thickness / 2, 18, radius_b=width / 2, up=(0.0, 1.0, 0.0))


def _handle_cup(r_base: float, r_top: float, height: float, wall: float = 3.5, floor: float = 8.0,
                reach: float = 32.0, belly: float = 0.0) -> Mesh:
    """A mug: a round body with a C-shaped handle towards -x."""
    mid = 0.5 * (r_base + r_top) + belly
    outer = S.join(S.base_with_fillet(r_base, 5.0, n_fillet=6),
                   S.wall_curve([[r_base, 5.0], [mid, 0.5 * (5.0 + height)], [r_top, height]], 8))
    body = S.revolve(S.vessel_profile(outer, wall=wall, floor_z=floor), 64)
    handle = _handle(outer, wall, height - 0.2 * height, 0.25 * height, reach, width=14.0, thickness=10.0)
    return S.union(body, handle)


def _box_glass(half_x: float, half_y: float, height: float, wall: float = 3.0, floor: float = 8.0,
               corner: float = 7.0) -> Mesh:
    """A glass with a rounded-rectangle (or rounded-square) section, straight walls, flat rim."""
    outer = S.rounded_rect_section(half_x, half_y, corner, corner_points=7, edge_points=2)
    inner = S.rounded_rect_section(half_x - wall, half_y - wall, corner - wall, corner_points=7, edge_points=2)
    return S.prism_vessel(outer, inner, height, floor, fillet=4.0, inner_fillet=3.0)


def _quartet_cup(r_base: float, r_top: float, height: float, wall: float = 2.5, floor: float = 7.0,
                 lobes: float = 0.1) -> Mesh:
    """A small cup of four-lobed (quatrefoil) section, slightly flaring."""
    outer = S.join(S.base_with_fillet(r_base, 3.5, n_fillet=6),
                   S.wall_curve([[r_base, 3.5], [0.5 * (r_base + r_top), 0.5 * (3.5 + height)], [r_top, height]], 8))
    return S.loft(S.vessel_profile(outer, wall=wall, floor_z=floor), S.lobed_section(4, lobes, 16))


# ------------------------------------------------------------------------------------------
# The table (ids fixed: TDoF20's classes in its order; the number in a name is the capacity in ml)
# ------------------------------------------------------------------------------------------
CONT = "continuous"


@dataclass(frozen=True)
class _Spec:
    name: str
    kind: str
    build: Callable[[], Mesh]
    symmetry: str | int | None  # "continuous", n (discrete n-fold about z) or None


def _spec(name: str, kind: str, builder: Callable[..., Mesh], symmetry, **dims) -> _Spec:
    return _Spec(name, kind, functools.partial(builder, **dims), symmetry)


_TABLE: dict[int, _Spec] = {
    1: _spec("cube_136", "cube glass (square section, rounded edges)", _box_glass, 4,
             half_x=29.0, half_y=29.0, height=58.6),
    2: _spec("cube_166", "cube glass (square section, rounded edges)", _box_glass, 4,
             half_x=31.0, half_y=31.0, height=61.2),
    3: _spec("cube_216", "cube glass (square section, rounded edges)", _box_glass, 4,
             half_x=33.5, half_y=33.5, height=66.3),
    4: _spec("cuboid_210", "cuboid glass (rectangular section)", _box_glass, 2,
             half_x=36.0, half_y=25.0, height=80.8),
    5: _spec("cuboid_330", "cuboid glass (rectangular section)", _box_glass, 2,
             half_x=38.0, half_y=27.0, height=106.7),
    6: _spec("goblet_180", "goblet (bowl on a stem and foot)", _goblet, CONT,
             bowl_r=35.0, bowl_depth=71.0, stem_h=45.0, foot_r=34.0),
    7: _spec("handle_cup_280", "mug with a handle", _handle_cup, None,
             r_base=40.0, r_top=41.0, height=71.3),
    8: _spec("handle_cup_440", "tall mug with a handle (tapered)", _handle_cup, None,
             r_base=40.0, r_top=45.0, height=97.8),
    9: _spec("handle_cup_480", "wide mug with a handle (barrel)", _handle_cup, None,
             r_base=44.0, r_top=46.0, height=87.0, belly=3.0),
    10: _spec("icecream_cup_175", "ice-cream cup (flaring bowl on a short foot)", _icecream_cup, CONT,
              rim_r=50.0, bowl_depth=41.0, stem_h=18.0, foot_r=32.0),
    11: _spec("juice_cup_250", "juice tumbler", _tumbler, CONT,
              r_base=33.0, r_top=36.0, height=85.0, wall=2.5, floor=8.0),
    12: _spec("juice_cup_340", "juice tumbler (straight)", _tumbler, CONT,
              r_base=38.0, r_top=38.5, height=91.7, wall=2.5, floor=8.0),
    13: _spec("juice_cup_350", "juice tumbler (tapered)", _tumbler, CONT,
              r_base=32.0, r_top=39.0, height=107.9, wall=2.5, floor=8.0),
    14: _spec("quartet_cup_80", "quartet cup (small, four-lobed section)", _quartet_cup, 4,
              r_base=24.0, r_top=27.0, height=52.9),
    15: _spec("quartet_cup_90", "quartet cup (small, four-lobed section)", _quartet_cup, 4,
              r_base=25.0, r_top=28.0, height=54.6),
    16: _spec("short_cup_220", "short cup (low, wide)", _tumbler, CONT,
              r_base=40.0, r_top=45.0, height=45.9, wall=2.5, floor=6.0, belly=1.5),
    17: _spec("water_cup_270", "water glass (tall)", _tumbler, CONT,
              r_base=30.0, r_top=33.0, height=106.7, wall=2.2, floor=8.0),
    18: _spec("water_cup_300", "water glass (tall)", _tumbler, CONT,
              r_base=30.5, r_top=34.0, height=112.0, wall=2.2, floor=8.0),
    19: _spec("whisky_cup_225", "whisky tumbler (short, wide, thick base)", _tumbler, CONT,
              r_base=41.0, r_top=41.5, height=61.7, wall=3.0, floor=14.0, fillet=3.0),
    20: _spec("whisky_cup_270", "whisky tumbler (short, wide, thick base)", _tumbler, CONT,
              r_base=42.5, r_top=43.0, height=67.2, wall=3.0, floor=15.0, fillet=3.0),
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
    import trimesh

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


def object_names() -> dict[int, str]:
    """{object id: name} of the catalog, in id order, without building any mesh."""
    return {obj_id: spec.name for obj_id, spec in sorted(_TABLE.items())}


def object_id_by_name(name: str) -> int:
    """The id of the object called ``name`` (e.g. 'goblet_180' -> 6), without building its mesh."""
    for obj_id, spec in _TABLE.items():
        if spec.name == name:
            return obj_id
    names = ", ".join(spec.name for spec in _TABLE.values())
    raise TdofError(f"unknown object name {name!r} (valid: {names})")


def object_by_name(name: str) -> ObjectModel:
    """The object called ``name`` (TDoF20's class name, e.g. 'goblet_180')."""
    return get_object(object_id_by_name(name))


def export_models(out_dir: str | Path, obj_ids=None) -> Path:
    """Write a BOP ``models`` folder: ``obj_{id:06d}.ply`` (binary PLY, mm, with vertex normals)
    and ``models_info.json``; every file is written atomically. Returns the folder.

    A folder holding an earlier export keeps the objects it has (their entries join the new ones);
    a models_info.json of other models (an entry the catalog does not write) is refused before
    anything is written, since its models would be overwritten."""
    out = Path(out_dir)
    ids = object_ids() if obj_ids is None else list(obj_ids)
    models = [get_object(i) for i in ids]  # unknown ids raise before anything is written
    info = {}
    old = out / "models_info.json"
    if old.exists():
        data = read_json(old)
        if not isinstance(data, dict):
            raise TdofError("holds models_info.json of other models (not a JSON object): export into another "
                            "folder", old)
        catalog = {str(i): json.loads(json.dumps(get_object(i).models_info())) for i in object_ids()}
        foreign = [k for k, e in data.items() if catalog.get(k) != e]
        if foreign:
            raise TdofError(f"holds models_info.json of other models (object {foreign[0]}'s entry is not the "
                            "catalog's): export into another folder", old)
        info.update(data)
    out.mkdir(parents=True, exist_ok=True)
    for m in models:
        tm = m.to_trimesh()
        write_model_mesh(model_path(out, m.obj_id), tm.vertices, tm.faces)
        info[str(m.obj_id)] = m.models_info()
    write_json(out / "models_info.json", dict(sorted(info.items(), key=lambda kv: int(kv[0]))))
    return out
