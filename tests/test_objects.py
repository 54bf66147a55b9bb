"""The catalog of TDoF20's 20 classes: names, capacities, watertight meshes, model frame, diameters,
symmetries, keypoints, export."""

from __future__ import annotations

import functools
import json
import re

import numpy as np
import pytest

from tdof20.objects.keypoints import KEYPOINT_SAMPLES, KEYPOINT_SEED
import trimesh
from scipy.spatial import ConvexHull, cKDTree

from tdof20.errors import TdofError
from tdof20.geometry import farthest_point_sampling, invert, rotation_about_axis, transform_points
from tdof20.o3d import o3d
from tdof20.objects import (
    ObjectModel,
    all_objects,
    export_models,
    get_object,
    object_by_name,
    object_ids,
)
from tdof20.objects import catalog, shapes

IDS = list(range(1, 21))
TDOF20_CLASSES = ["cube_136", "cube_166", "cube_216", "cuboid_210", "cuboid_330", "goblet_180", "handle_cup_280",
                  "handle_cup_440", "handle_cup_480", "icecream_cup_175", "juice_cup_250", "juice_cup_340",
                  "juice_cup_350", "quartet_cup_80", "quartet_cup_90", "short_cup_220", "water_cup_270",
                  "water_cup_300", "whisky_cup_225", "whisky_cup_270"]  # the release's classes.txt order
ASYMMETRIC = ["handle_cup_280", "handle_cup_440", "handle_cup_480"]
CONTINUOUS = ["goblet_180", "icecream_cup_175", "juice_cup_250", "juice_cup_340", "juice_cup_350", "short_cup_220",
              "water_cup_270", "water_cup_300", "whisky_cup_225", "whisky_cup_270"]
DISCRETE = {"cube_136": 4, "cube_166": 4, "cube_216": 4, "cuboid_210": 2, "cuboid_330": 2,
            "quartet_cup_80": 4, "quartet_cup_90": 4}


@functools.lru_cache(maxsize=None)
def _scene(obj_id: int):
    m = get_object(obj_id)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                        o3d.core.Tensor(m.faces.astype(np.uint32)))
    return scene


def _dist_to_mesh(obj_id: int, pts: np.ndarray) -> np.ndarray:
    """Exact unsigned distance (mm) of points to the object's surface."""
    return _scene(obj_id).compute_distance(o3d.core.Tensor(np.asarray(pts, np.float32))).numpy()


def _surface_gap(m: ObjectModel, T: np.ndarray, n: int = 3000) -> float:
    """Symmetric gap between the surface and its image under T: the largest distance of a sample
    of one surface (Monte-Carlo samples and the vertices) to the other mesh, both ways (a
    sampled Hausdorff distance), in mm."""
    q = np.concatenate([m.sample_surface(n, seed=7), m.vertices])
    a = _dist_to_mesh(m.obj_id, transform_points(T, q))  # moved samples vs original mesh
    b = _dist_to_mesh(m.obj_id, transform_points(invert(T), q))  # original samples vs moved mesh
    return float(max(a.max(), b.max()))


def _adds(m: ObjectModel, T: np.ndarray) -> float:
    """ADD-S-style symmetric closest-point distance (mm) between moved and original surface
    samples (cKDTree): the mean, both ways, of each sample's distance to the nearest other one."""
    ref = m.sample_surface(20000, seed=11)
    q = m.sample_surface(2000, seed=12)
    d1, _ = cKDTree(ref).query(transform_points(T, q))
    d2, _ = cKDTree(transform_points(T, ref)).query(q)
    return float(max(d1.mean(), d2.mean()))


def _rot_z(deg: float) -> np.ndarray:
    return rotation_about_axis([0.0, 0.0, 1.0], np.radians(deg))


# ------------------------------------------------------------------------------------------
# Catalog and access
# ------------------------------------------------------------------------------------------
def test_ids_names_and_access():
    assert object_ids() == IDS
    objs = all_objects()
    assert [m.obj_id for m in objs] == IDS
    names = [m.name for m in objs]
    assert names == TDOF20_CLASSES
    assert all(re.fullmatch(r"[a-z][a-z0-9_]*_\d+", n) for n in names)
    assert catalog.object_names() == dict(zip(IDS, TDOF20_CLASSES))
    assert all(m.kind for m in objs)
    for m in objs:
        assert object_by_name(m.name) is m
        assert catalog.object_id_by_name(m.name) == m.obj_id
        assert get_object(m.obj_id) is m  # cached
    assert get_object(np.int64(3)) is get_object(3)
    assert set(ASYMMETRIC) | set(CONTINUOUS) | set(DISCRETE) == set(TDOF20_CLASSES)


@pytest.mark.parametrize("bad", [0, 21, 25, -1])
def test_unknown_id_raises(bad):
    with pytest.raises(TdofError, match=rf"unknown object id {bad}\b"):
        get_object(bad)


def test_unknown_id_message_and_name():
    with pytest.raises(TdofError) as e:
        get_object(25)
    assert str(e.value) == "unknown object id 25 (valid: 1-20)"
    with pytest.raises(TdofError, match="unknown object id"):
        get_object("3")
    with pytest.raises(TdofError) as e:
        object_by_name("wine_glass")  # an old name
    msg = str(e.value)
    assert "wine_glass" in msg and "cube_136" in msg and "whisky_cup_270" in msg and "\n" not in msg


# ------------------------------------------------------------------------------------------
# Meshes
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("obj_id", IDS)
def test_mesh_is_watertight_solid(obj_id):
    m = get_object(obj_id)
    assert m.vertices.dtype == np.float64 and m.vertices.ndim == 2 and m.vertices.shape[1] == 3
    assert m.faces.dtype == np.int64 and m.faces.shape[1] == 3
    assert not m.vertices.flags.writeable and not m.faces.flags.writeable
    tm = m.to_trimesh()
    assert tm.is_watertight
    assert tm.is_winding_consistent
    assert tm.volume > 0
    assert len(m.faces) <= 12500  # ray casting stays fast
    assert len(np.unique(m.vertices, axis=0)) == len(m.vertices)  # no duplicate vertices
    assert np.all(tm.area_faces > 0)


@pytest.mark.parametrize("obj_id", IDS)
def test_vessels_have_real_walls(obj_id):
    """Every object is hollow: a ray along y through the mid-height crosses glass twice, each
    wall 1.5-5 mm thick, and the glass fills well under half of the convex hull."""
    m = get_object(obj_id)
    ray = np.array([[0.3, -1000.0, 0.0, 0.0, 1.0, 0.0]], np.float32)
    t = np.sort(_scene(obj_id).list_intersections(o3d.core.Tensor(ray))["t_hit"].numpy())
    assert len(t) == 4
    walls = t[1::2] - t[0::2]
    assert np.all((walls > 1.5) & (walls < 5.0)), walls
    tm = m.to_trimesh()
    assert tm.volume < 0.5 * tm.convex_hull.volume


@pytest.mark.parametrize("obj_id", IDS)
def test_model_frame_and_sizes(obj_id):
    m = get_object(obj_id)
    lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
    assert abs(lo[2] + hi[2]) < 1e-9  # origin at mid-height
    assert m.z_min == pytest.approx(lo[2]) and m.z_min < 0
    assert np.allclose(m.centre, (lo + hi) / 2)
    assert m.footprint_radius == pytest.approx(np.sqrt((m.vertices[:, :2] ** 2).sum(axis=1)).max())
    assert 50.0 < m.diameter < 320.0
    assert np.all(hi - lo > 40.0)
    if m.symmetric:
        assert np.allclose(m.centre, 0.0, atol=1e-9)  # symmetry axis = z axis through the origin
    # the body axis (z) runs through the object: through its base and up its cavity
    ray = np.array([[0.0, 0.0, m.z_min - 10.0, 0.0, 0.0, 1.0]], np.float32)
    assert len(_scene(obj_id).list_intersections(o3d.core.Tensor(ray))["t_hit"].numpy()) >= 2


def _cavity_by_lid(m: ObjectModel) -> float:
    """The cavity's volume (ml) from the meshes alone: a lid slab laid on the rim (0.2 mm into it) and
    united with the glass (manifold3d) encloses the cavity as an inner shell of negative volume."""
    lo, hi = m.bbox_min, m.bbox_max
    lid = shapes.box([lo[0] - 1, lo[1] - 1, hi[2] - 0.2], [hi[0] + 1, hi[1] + 1, hi[2] + 2])
    parts = shapes.union(m.to_trimesh(), lid).split(only_watertight=False)
    vols = sorted(shapes.signed_volume(p.vertices, p.faces) for p in parts)
    assert len(vols) == 2 and vols[0] < 0 < vols[1]  # the outer shell and the cavity
    return -vols[0] / 1000.0


def test_capacities_match_the_names():
    """The number in a class name is its capacity in ml: every cavity holds that, filled to the brim,
    within 5 % (the ray-cast measure of the catalog); and that measure agrees within 2 % with an
    exact one (a lid on the rim) on one object of each shape family."""
    for m in all_objects():
        assert m.nominal_capacity_ml == int(m.name.rsplit("_", 1)[1])
        assert abs(m.capacity_ml / m.nominal_capacity_ml - 1.0) < 0.05, (m.name, m.capacity_ml)
    for name in ("cube_136", "cuboid_330", "goblet_180", "handle_cup_480", "icecream_cup_175", "quartet_cup_80",
                 "whisky_cup_225"):
        m = object_by_name(name)
        exact = _cavity_by_lid(m)
        assert abs(m.capacity_ml / exact - 1.0) < 0.02, (name, m.capacity_ml, exact)


def test_cavity_volume_of_a_known_cup():
    """A plain cylinder cup (inner radius 30, inner depth 60 above a 10 mm floor, flat top): 169.6 ml."""
    outer = shapes.rounded_rect_section(32.0, 32.0, 31.9, corner_points=64, edge_points=0)
    inner = shapes.rounded_rect_section(30.0, 30.0, 29.9, corner_points=64, edge_points=0)
    tm = shapes.prism_vessel(outer, inner, height=70.0, floor=10.0, fillet=0.5, inner_fillet=0.5)
    want = shapes.section_area(inner) * 60.0  # the tiny fillet at the floor aside
    got = catalog.cavity_volume(tm.vertices, tm.faces)
    assert abs(got / want - 1.0) < 0.015, (got, want)


def test_shapes_fit_their_names():
    size = {m.name: m.size for m in all_objects()}
    for name in ("cube_136", "cube_166", "cube_216"):  # as wide as deep as tall, within 10 %
        x, y, z = size[name]
        assert x == pytest.approx(y) and abs(z / x - 1.0) < 0.1
    for name in ("cuboid_210", "cuboid_330"):  # a rectangle, long side along x
        x, y, _ = size[name]
        assert x > 1.2 * y
    ratio = {n: size[n][2] / size[n][0] for n in size if not n.startswith("handle")}  # height / width
    assert min(ratio[n] for n in ("water_cup_270", "water_cup_300")) > max(
        ratio[n] for n in ("juice_cup_250", "juice_cup_340", "juice_cup_350", "whisky_cup_225", "whisky_cup_270",
                           "short_cup_220"))  # water glasses are the tallest tumblers
    assert max(ratio[n] for n in ("whisky_cup_225", "whisky_cup_270", "short_cup_220")) < 0.85  # short, wide
    assert ratio["short_cup_220"] < 0.6 and ratio["icecream_cup_175"] < 0.7
    for name in ("handle_cup_280", "handle_cup_440", "handle_cup_480"):  # the handle reaches out towards -x
        m = object_by_name(name)
        assert m.bbox_min[0] < -m.bbox_max[0] - 25.0
    # the whisky tumblers' base is the thickest: the first glass the z axis meets from below
    def base(name):
        m = object_by_name(name)
        ray = np.array([[0.3, 0.2, m.z_min - 10.0, 0.0, 0.0, 1.0]], np.float32)  # off the pole vertex
        t = np.sort(_scene(m.obj_id).list_intersections(o3d.core.Tensor(ray))["t_hit"].numpy())
        return t[1] - t[0]
    assert min(base("whisky_cup_225"), base("whisky_cup_270")) > 12.0 > max(base("water_cup_270"), base("juice_cup_250"))
    # the goblet's bowl sits on a stem: a ray along y at a quarter of the height meets only the stem
    g = object_by_name("goblet_180")
    ray = np.array([[0.0, -1000.0, g.z_min + 0.25 * g.size[2], 0.0, 1.0, 0.0]], np.float32)
    t = np.sort(_scene(g.obj_id).list_intersections(o3d.core.Tensor(ray))["t_hit"].numpy())
    assert len(t) == 2 and t[1] - t[0] < 12.0


# ------------------------------------------------------------------------------------------
# Diameter
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("obj_id", IDS)
def test_diameter_exact(obj_id):
    m = get_object(obj_id)
    hv = m.vertices[ConvexHull(m.vertices).vertices]
    brute = max(np.sqrt(((hv[i:i + 256, None, :] - hv[None, :, :]) ** 2).sum(-1).max())
                for i in range(0, len(hv), 256))
    assert abs(m.diameter - brute) < 1e-6
    # a separate computation over all vertices (Gram-matrix form, chunked)
    V = m.vertices
    sq = (V * V).sum(1)
    best = max(float((sq[i:i + 2000, None] + sq[None, :] - 2.0 * V[i:i + 2000] @ V.T).max())
               for i in range(0, len(V), 2000))
    assert abs(m.diameter - np.sqrt(best)) < 1e-6
    assert m.diameter >= (m.size.max() - 1e-9)
    assert m.diameter <= np.linalg.norm(m.size) + 1e-9


# ------------------------------------------------------------------------------------------
# Symmetries
# ------------------------------------------------------------------------------------------
def test_symmetry_records():
    for m in all_objects():
        if m.name in CONTINUOUS:
            assert m.symmetries_continuous == ({"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]},)
            assert m.symmetries_discrete == ()
        elif m.name in DISCRETE:
            n = DISCRETE[m.name]
            assert m.symmetries_continuous == ()
            assert len(m.symmetries_discrete) == n - 1
            for k, T in enumerate(m.symmetries_discrete, start=1):
                assert T.shape == (4, 4)
                assert np.allclose(T, _rot_z(360.0 * k / n), atol=1e-12)
                assert not np.allclose(T, np.eye(4))
        else:
            assert m.name in ASYMMETRIC
            assert not m.symmetric
            assert m.symmetries_continuous == () and m.symmetries_discrete == ()
    assert len(ASYMMETRIC) == 3 and len(CONTINUOUS) == 10


@pytest.mark.parametrize("name", CONTINUOUS)
def test_continuous_symmetry_holds(name):
    m = object_by_name(name)
    assert m.symmetric
    for deg in (23.0, 131.0, 250.0):
        T = _rot_z(deg)
        assert _surface_gap(m, T) < 0.01 * m.diameter
        assert _adds(m, T) < 0.01 * m.diameter


@pytest.mark.parametrize("name", sorted(DISCRETE))
def test_discrete_symmetry_holds(name):
    m = object_by_name(name)
    for T in m.symmetries_discrete:
        assert _surface_gap(m, T) < 1e-3 * m.diameter
        assert _adds(m, T) < 0.01 * m.diameter
    half_step = 180.0 / DISCRETE[name]  # not continuously symmetric
    assert _surface_gap(m, _rot_z(half_step)) > 0.02 * m.diameter


@pytest.mark.parametrize("name", ASYMMETRIC)
def test_asymmetric_objects_are_not_invariant(name):
    m = object_by_name(name)
    gaps = [_surface_gap(m, _rot_z(deg)) for deg in (60.0, 90.0, 180.0)]
    assert max(gaps) > 0.02 * m.diameter, gaps


# ------------------------------------------------------------------------------------------
# Keypoints and sampling
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("obj_id", IDS)
def test_keypoints(obj_id):
    m = get_object(obj_id)
    kp = m.keypoints
    assert kp.shape == (9, 3)
    assert np.array_equal(kp[0], m.centre)
    assert np.all(_dist_to_mesh(obj_id, kp[1:]) < 1e-2)  # on the surface
    d = np.linalg.norm(kp[:, None] - kp[None], axis=-1)[np.triu_indices(9, 1)]
    assert d.min() > 0.1 * m.diameter  # spread out
    again = farthest_point_sampling(m.sample_surface(KEYPOINT_SAMPLES, KEYPOINT_SEED), 9, first=m.centre)
    assert np.allclose(again, kp)  # reproducible


def test_sample_surface_deterministic_and_on_surface():
    m = object_by_name("handle_cup_280")
    a, b, c = m.sample_surface(500, seed=3), m.sample_surface(500, seed=3), m.sample_surface(500, seed=4)
    assert a.shape == (500, 3)
    assert np.array_equal(a, b) and not np.allclose(a, c)
    assert np.all(_dist_to_mesh(m.obj_id, a) < 1e-2)
    # area-uniform: the share of samples on the handle side matches the share of area there
    tm = m.to_trimesh()
    s = m.sample_surface(20000, seed=0)
    frac_area = tm.area_faces[tm.triangles_center[:, 0] < -45.0].sum() / tm.area
    assert abs((s[:, 0] < -45.0).mean() - frac_area) < 0.02


# ------------------------------------------------------------------------------------------
# models_info and export
# ------------------------------------------------------------------------------------------
def test_models_info_entries():
    for m in all_objects():
        info = m.models_info()
        json.dumps(info)  # plain JSON types
        assert info["diameter"] == pytest.approx(m.diameter)
        for k, axis in (("x", 0), ("y", 1), ("z", 2)):
            assert info[f"min_{k}"] == pytest.approx(m.vertices[:, axis].min())
            assert info[f"size_{k}"] == pytest.approx(np.ptp(m.vertices[:, axis]))
        assert ("symmetries_continuous" in info) == bool(m.symmetries_continuous)
        assert ("symmetries_discrete" in info) == bool(m.symmetries_discrete)
        if m.symmetries_continuous:
            assert info["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
        if m.symmetries_discrete:
            for flat, T in zip(info["symmetries_discrete"], m.symmetries_discrete):
                assert len(flat) == 16 and np.allclose(np.reshape(flat, (4, 4)), T)


def test_export_models(tmp_path):
    out = export_models(tmp_path / "models")
    assert out == tmp_path / "models"
    plys = sorted(out.glob("obj_*.ply"))
    assert [p.name for p in plys] == [f"obj_{i:06d}.ply" for i in IDS]
    info = json.loads((out / "models_info.json").read_text())
    assert sorted(info, key=int) == [str(i) for i in IDS]
    for i, p in zip(IDS, plys):
        m = get_object(i)
        head = p.read_bytes()[:400]
        assert b"format binary_little_endian" in head and b"property float nx" in head
        tm = trimesh.load(p, process=False)
        assert len(tm.vertices) == len(m.vertices) and len(tm.faces) == len(m.faces)
        assert np.allclose(tm.vertices, m.vertices, atol=1e-3)
        assert abs(info[str(i)]["diameter"] - m.diameter) < 1e-9
    assert not list(out.glob("*.tmp")) and not list(out.glob(".*"))


def test_export_subset_and_bad_id(tmp_path):
    out = export_models(tmp_path, obj_ids=[3, 17])
    assert sorted(p.name for p in out.glob("*.ply")) == ["obj_000003.ply", "obj_000017.ply"]
    assert sorted(json.loads((out / "models_info.json").read_text())) == ["17", "3"]
    with pytest.raises(TdofError, match="unknown object id 21"):
        export_models(tmp_path / "bad", obj_ids=[1, 21])
    assert not (tmp_path / "bad").exists()



def test_export_keeps_an_earlier_export_and_refuses_a_users_models(tmp_path):
    out = export_models(tmp_path / "m", obj_ids=[3, 17])
    export_models(out, obj_ids=[5])  # an earlier export's objects stay listed
    assert list(json.loads((out / "models_info.json").read_text())) == ["3", "5", "17"]
    export_models(out, obj_ids=[5])  # again: the same
    assert list(json.loads((out / "models_info.json").read_text())) == ["3", "5", "17"]
    user = tmp_path / "user"
    user.mkdir()
    (user / "models_info.json").write_text('{"1": {"diameter": 172.0}}')
    (user / "obj_000001.ply").write_bytes(b"the user's model")
    with pytest.raises(TdofError, match="models_info.json of other models .object 1's entry is not the catalog's"):
        export_models(user, obj_ids=[1])
    assert (user / "obj_000001.ply").read_bytes() == b"the user's model"
    assert (user / "models_info.json").read_text() == '{"1": {"diameter": 172.0}}'

# ------------------------------------------------------------------------------------------
# Builders
# ------------------------------------------------------------------------------------------
def test_revolve_and_loft_are_closed():
    outer = shapes.join(shapes.base_with_fillet(30.0, 4.0), shapes.wall_curve([[30.0, 4.0], [32.0, 80.0]], 6))
    prof = shapes.vessel_profile(outer, wall=2.0, floor_z=6.0)
    for v, f in (shapes.revolve(prof, 48), shapes.revolve(prof[::-1], 48),
                 shapes.loft(prof, shapes.polygon_section(5, 0.1))):
        tm = trimesh.Trimesh(v, f, process=False)
        assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    v, f = shapes.tube(shapes.bezier([[0, 0, 0], [30, 0, 0], [30, 0, 50], [0, 0, 50]], 20), 4.0, 12, radius_b=6.0)
    tm = trimesh.Trimesh(v, f, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0


def test_bad_profiles_rejected():
    with pytest.raises(ValueError, match="axis"):
        shapes.revolve(np.array([[1.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]))
    bow_tie = np.array([[0.0, 0.0], [2.0, 2.0], [2.0, 0.0], [0.0, 2.0]])
    with pytest.raises(ValueError, match="self-intersects"):
        shapes.revolve(bow_tie)


def test_builds_are_deterministic():
    for obj_id in (1, 7):  # boolean differences / unions included
        a, b = catalog._build(obj_id), get_object(obj_id)
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
        assert np.array_equal(a.keypoints, b.keypoints) and a.diameter == b.diameter
