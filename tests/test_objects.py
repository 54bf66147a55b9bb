"""The 20-object catalog: watertight meshes, model frame, diameters, symmetries, keypoints, export."""

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
ASYMMETRIC = ["beaker_with_spout", "graduated_cylinder", "measuring_cup", "mug", "pitcher",
              "flask_flat_face", "teapot"]
CONTINUOUS = ["tumbler", "highball_glass", "wine_glass", "shot_glass", "erlenmeyer_flask",
              "round_bottom_flask", "water_bottle", "wine_bottle", "bowl", "vase", "jar"]
DISCRETE = {"square_vase": 4, "hexagonal_glass": 6}


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
    assert len(set(names)) == 20
    assert all(re.fullmatch(r"[a-z][a-z0-9_]*", n) for n in names)
    assert names[:4] == ["tumbler", "highball_glass", "wine_glass", "shot_glass"]
    assert names[16:] == ["square_vase", "hexagonal_glass", "flask_flat_face", "teapot"]
    assert all(m.kind for m in objs)
    for m in objs:
        assert object_by_name(m.name) is m
        assert get_object(m.obj_id) is m  # cached
    assert get_object(np.int64(3)) is get_object(3)


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
        object_by_name("champagne_flute")
    msg = str(e.value)
    assert "champagne_flute" in msg and "wine_glass" in msg and "teapot" in msg and "\n" not in msg


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


def test_realistic_sizes():
    size = {m.name: m.size for m in all_objects()}
    w, _, h = size["tumbler"]
    assert 65 < w < 85 and 85 < h < 105
    w, _, h = size["wine_glass"]
    assert 70 < w < 90 and 180 < h < 220
    w, _, h = size["wine_bottle"]
    assert 70 < w < 80 and 280 < h < 310
    assert size["shot_glass"][2] < 70 and size["bowl"][0] > 130


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
    assert len(ASYMMETRIC) >= 6


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
    m = object_by_name("mug")
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
    for obj_id in (16, 20):  # boolean unions / differences included
        a, b = catalog._build(obj_id), get_object(obj_id)
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
        assert np.array_equal(a.keypoints, b.keypoints) and a.diameter == b.diameter
