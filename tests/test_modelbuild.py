"""tdof20.annotate.modelbuild against the catalog's exact meshes (the simulator's truth): the
canonical frame and the symmetries of posed catalog meshes, models built from clusters of points
sampled on the surface a ring of cameras sees, bad clusters, and the models folder written and
read back (write_models / load_models), with its errors.

Sizes: Poisson at octree depth 8 on the visible points of the whisky tumbler (a few s per build);
a bulbous vase (not a TDoF20 class: built here from the catalog's shape builders, the one shape
whose inside no camera sees) at depth 7 on ~14,500 points (~10 s: its double wall needs points
closer than a third of the wall); the symmetry tests on asymmetric objects pass ``up`` (one
candidate axis: ~1-2 s instead of 5-30 s).
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from tdof20.annotate import modelbuild as mb
from tdof20.annotate.symmetry import canonical_frame, symmetry_kind
from tdof20.errors import TdofError
from tdof20.o3d import o3d
from tdof20.objects import get_object
from tdof20.objects import shapes as S

# juice_cup_340, whisky_cup_225 (thick base), handle_cup_280 (handle at -x), cube_136
JAR, SHOT_GLASS, MUG, HEX_GLASS = 12, 19, 7, 1      # continuous, continuous, none, 4-fold
N_FOLD = 4
VASE = "vase"                                       # continuous; a belly behind a narrow neck (see _mesh)
CONT = {"symmetries_continuous": [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]}
FAST = dataclasses.replace(mb.ModelBuildConfig(), poisson_depth=8)


def _vase() -> tuple[np.ndarray, np.ndarray]:
    """A bulbous vase, 126 x 126 x 203 mm, 3.5 mm glass, origin at mid-height (the old catalog's)."""
    outer = S.join(S.base_with_fillet(38.0, 6.0, n_fillet=6),
                   S.wall_curve([[38.0, 6.0], [50.0, 28.0], [63.0, 68.0], [60.0, 108.0], [41.0, 148.0],
                                 [27.5, 172.0], [28.5, 186.0], [34.0, 200.0]], 40))
    V, F = S.revolve(S.vessel_profile(outer, wall=3.5, floor_z=10.0), 64)
    V[:, 2] -= 0.5 * (V[:, 2].min() + V[:, 2].max())
    return S.orient_outward(V, F)


def _mesh(obj_id) -> tuple[np.ndarray, np.ndarray]:
    if obj_id == VASE:
        return _vase()
    m = get_object(obj_id).to_trimesh()
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def _pose(seed: int) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.random(random_state=seed).as_matrix(), np.array([31.0, -17.0, 420.0]) + seed


def _deg(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def _scene(V: np.ndarray, F: np.ndarray):
    s = o3d.t.geometry.RaycastingScene()
    s.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    return s


def _distance(scene, P: np.ndarray) -> np.ndarray:
    return scene.compute_distance(o3d.core.Tensor(np.asarray(P, np.float32))).numpy()


# ------------------------------------------------------------------------------------------
# canonical frame and symmetries
# ------------------------------------------------------------------------------------------
def test_a_jar_in_a_random_pose_is_continuous_about_its_true_axis():
    V, F = _mesh(JAR)
    R, t = _pose(1)
    Vi = V @ R.T + t
    T, sym = canonical_frame(Vi, F)                       # no table normal: principal axes tried
    assert sym == CONT and symmetry_kind(sym) == "continuous"
    assert min(_deg(T[2, :3], R[:, 2]), _deg(T[2, :3], -R[:, 2])) < 1.0
    # with the table normal: z along it, the origin on the axis at mid-height, the catalog's extents
    T, sym = canonical_frame(Vi, F, up=R[:, 2])
    assert sym == CONT and _deg(T[2, :3], R[:, 2]) < 1.0
    Vm = Vi @ T[:3, :3].T + T[:3, 3]
    lo, hi = Vm.min(axis=0), Vm.max(axis=0)
    assert np.allclose(0.5 * (lo + hi), 0.0, atol=0.3)
    assert np.allclose(hi - lo, get_object(JAR).size, atol=0.3)   # 77 x 77 x 93 (a 64-gon about z)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(T[:3, :3]) > 0


def test_a_jar_with_a_rough_cavity_floor_is_still_continuous():
    """A reconstructed tumbler's floor, seen by few cameras through the opening, comes out rough:
    the symmetry is judged on the open outside only (with a cone of 0 deg: found 4-fold)."""
    V, F = _mesh(JAR)
    r = np.linalg.norm(V[:, :2], axis=1)
    z_floor = V[:, 2].min() + 8.0                                # the cavity floor, 8 mm above the base
    floor = (V[:, 2] < z_floor + 0.5) & (V[:, 2] > z_floor - 0.5) & (r < 36.0)   # the floor disc
    assert floor.sum() > 60
    V[floor, 2] += np.random.default_rng(0).uniform(-2.5, 2.5, floor.sum())
    R, t = _pose(5)
    _, sym = canonical_frame(V @ R.T + t, F, up=R[:, 2])
    assert sym == CONT


def test_a_mug_with_its_handle_has_no_symmetry_and_x_points_to_the_handle():
    V, F = _mesh(MUG)
    R, t = _pose(2)
    T, sym = canonical_frame(V @ R.T + t, F, up=R[:, 2])
    assert sym == {} and symmetry_kind(sym) is None
    assert _deg(T[2, :3], R[:, 2]) < 1e-6                    # an upright object without symmetry: z = up
    assert _deg(T[0, :3], R @ [-1.0, 0.0, 0.0]) < 5.0        # the catalog's mug has its handle at -x


def test_a_cube_glass_is_four_fold_in_bop_form():
    V, F = _mesh(HEX_GLASS)
    R, t = _pose(3)
    T, sym = canonical_frame(V @ R.T + t, F, up=R[:, 2])
    assert symmetry_kind(sym) == N_FOLD and set(sym) == {"symmetries_discrete"}
    turns = np.asarray(sym["symmetries_discrete"], float)
    assert turns.shape == (N_FOLD - 1, 16)
    want = np.asarray(get_object(HEX_GLASS).models_info()["symmetries_discrete"], float)
    assert np.allclose(turns, want, atol=1e-9)               # turns by 90 deg * k about z, k = 1..3
    assert _deg(T[2, :3], R[:, 2]) < 1.0
    # each turn maps the model (in its canonical frame) onto itself
    Vm = (V @ R.T + t) @ T[:3, :3].T + T[:3, 3]
    scene = _scene(Vm, F)
    S = mb.sample_points(Vm, F, 2000)
    for M in turns.reshape(-1, 4, 4):
        assert np.percentile(_distance(scene, S @ M[:3, :3].T + M[:3, 3]), 99) < 0.5


# ------------------------------------------------------------------------------------------
# models from clusters
# ------------------------------------------------------------------------------------------
def _visible_cluster(obj_id: int, n: int, seed: int = 0, noise_mm: float = 0.2):
    """Points of the catalog object standing on the table z = 0 that a ring of 24 cameras sees
    (25 and 55 deg above the table), with noise; their true outward normals; the cameras."""
    V, F = _mesh(obj_id)
    V = V - [0.0, 0.0, V[:, 2].min()]
    scene = _scene(V, F)
    S = mb.sample_points(V, F, n, seed=seed)
    N = scene.compute_closest_points(o3d.core.Tensor(S.astype(np.float32)))["primitive_normals"].numpy()
    el, az = np.meshgrid(np.radians([25.0, 55.0]), np.radians(np.arange(0.0, 360.0, 30.0)))
    cams = 500.0 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    seen = np.zeros(len(S), bool)
    for c in cams:
        d = S - c
        L = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c, S.shape), d / L[:, None]], axis=1).astype(np.float32)
        seen |= scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() > L - 0.05
    keep = seen & (S[:, 2] > 1.0)                            # the table hides the bottom
    P = S[keep] + np.random.default_rng(seed).normal(0.0, noise_mm, (int(keep.sum()), 3))
    return P, N[keep].astype(float), cams, V, F


@pytest.fixture(scope="module")
def shot_glass_cluster():
    P, N, cams, V, F = _visible_cluster(SHOT_GLASS, 8000)
    R, t = _pose(4)                                          # the reconstruction's reference frame
    up = R[:, 2]
    return {"P": P @ R.T + t, "N": N @ R.T, "cams": cams @ R.T + t, "plane": np.r_[up, -up @ t],
            "R": R, "t": t, "V": V, "F": F}


def test_a_model_built_from_a_visible_surface_with_normals_matches_the_truth(shot_glass_cluster):
    c = shot_glass_cluster
    m = mb.build_model_from_cluster(c["P"], c["plane"], FAST, normals=c["N"])
    assert m.watertight and trimesh.Trimesh(m.vertices, m.faces, process=False).is_watertight
    assert symmetry_kind(m.symmetries) == "continuous"
    size = [m.info[k] for k in ("size_x", "size_y", "size_z")]
    assert np.allclose(size, get_object(SHOT_GLASS).size, atol=0.6)   # 83 x 83 x 63.2 mm
    assert m.info["cluster_to_model_median_mm"] < 0.3 and m.info["closed_bottom"]
    # posed into the reference frame, the model lies on the true surface, hollow like it
    T = m.T_ref_model
    V_true = (m.vertices @ T[:3, :3].T + T[:3, 3] - c["t"]) @ c["R"]
    d = _distance(_scene(c["V"], c["F"]), mb.sample_points(V_true, m.faces, 5000))
    assert d.mean() < 0.3 and np.percentile(d, 95) < 1.0
    vol = trimesh.Trimesh(V_true, m.faces, process=False).volume
    assert vol == pytest.approx(get_object(SHOT_GLASS).to_trimesh().volume, rel=0.05)
    # the model frame: z up the table normal, base at z_min, origin at mid-height on the axis
    assert _deg(T[:3, 2], c["R"][:, 2]) < 1.0
    assert m.vertices[:, 2].min() == pytest.approx(-m.vertices[:, 2].max(), abs=1e-6)


def test_a_model_built_with_estimated_normals_is_watertight_and_the_right_size(shot_glass_cluster):
    c = shot_glass_cluster
    m = mb.build_model_from_cluster(c["P"], c["plane"], FAST, viewpoints=c["cams"])
    assert m.watertight
    size = [m.info[k] for k in ("size_x", "size_y", "size_z")]
    assert np.allclose(size, get_object(SHOT_GLASS).size, atol=1.5)
    assert m.info["cluster_to_model_median_mm"] < 0.6


def test_a_vase_whose_belly_no_camera_sees_is_built_hollow():
    """Issue 12: the cameras see the vase's belly only from outside (the neck hides its inside),
    its neck from both sides. The model gets the inner wall at the thickness measured on the
    neck, and is hollow like the truth (before: the belly solid under a ragged cap — 1.1 mm
    from the truth here, 2.1-2.7 mm in the 640x480 pipeline, 4.5 times the volume)."""
    P, N, _, V, F = _visible_cluster(VASE, 25000)            # ~14,500 points, 1.1 mm apart
    R, t = _pose(6)
    cfg = dataclasses.replace(mb.ModelBuildConfig(), poisson_depth=7)
    m = mb.build_model_from_cluster(P @ R.T + t, np.r_[R[:, 2], -R[:, 2] @ t], cfg, normals=N @ R.T)
    T = m.T_ref_model
    V_true = (m.vertices @ T[:3, :3].T + T[:3, 3] - t) @ R
    d_model = _distance(_scene(V, F), mb.sample_points(V_true, m.faces, 5000))    # model -> truth
    d_truth = _distance(_scene(V_true, m.faces), mb.sample_points(V, F, 5000))    # truth -> model
    assert 0.5 * (d_model.mean() + d_truth.mean()) < 0.5    # the evaluation's surface distance
    assert np.percentile(d_truth, 95) < 1.5                 # the inside of the belly is there
    vol = trimesh.Trimesh(V_true, m.faces, process=False).volume
    assert vol == pytest.approx(trimesh.Trimesh(V, F, process=False).volume, rel=0.15)
    assert m.watertight and symmetry_kind(m.symmetries) == "continuous"
    assert 3.0 < m.info["wall_mm"] < 4.0 and m.info["inner_wall_points"] > 5000   # 3.5 mm glass


def test_bad_clusters_raise_clear_errors():
    rng = np.random.default_rng(0)
    plane = np.array([0.0, 0.0, 1.0, 0.0])                   # the table z = 0, objects above
    ball = rng.normal(size=(3000, 3))
    ball = 30.0 * ball / np.linalg.norm(ball, axis=1, keepdims=True) + [0.0, 0.0, 40.0]
    cases = [
        (ball[:100], plane, r"too small.*100 points"),
        (np.c_[rng.uniform(-40, 40, (3000, 2)), np.full(3000, 30.0)], plane, r"degenerate"),      # a flat sheet
        (np.c_[np.zeros((3000, 2)), rng.uniform(10, 90, 3000)], plane, r"degenerate"),            # a line
        (ball - [0.0, 0.0, 100.0], plane, r"below the table plane"),
        (ball[:, :2], plane, r"\(N,3\)"),
        (ball, np.array([0.0, 0.0, 0.0, 1.0]), r"table plane"),
        (np.full((3000, 3), np.nan), plane, r"too small"),
    ]
    for points, pl, pattern in cases:
        with pytest.raises(TdofError, match=pattern) as e:
            mb.build_model_from_cluster(points, pl, FAST)
        assert "\n" not in str(e.value)
    with pytest.raises(TdofError, match="normals must match"):
        mb.build_model_from_cluster(ball, plane, FAST, normals=np.ones((10, 3)))


# ------------------------------------------------------------------------------------------
# the models folder
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The catalog's jar and mug written as built models (catalog frame, catalog symmetries)."""
    models = {}
    for o in (JAR, MUG):
        V, F = _mesh(o)
        sym = {k: v for k, v in get_object(o).models_info().items() if k.startswith("symmetries")}
        models[o] = mb.BuiltModel(vertices=V, faces=F, T_ref_model=np.eye(4), symmetries=sym, watertight=True,
                                  info={"source": "test", "watertight": True})
    out = mb.write_models(models, tmp_path_factory.mktemp("models") / "models", n_samples=3000)
    return out, models


def test_write_models_writes_a_bop_models_folder(written):
    from tdof20.methods.data import model_keypoints

    d, models = written
    names = sorted(p.name for p in d.iterdir())
    assert names == ["keypoints.json", "models_info.json", "obj_000007.ply", "obj_000007_samples.npy",
                     "obj_000012.ply", "obj_000012_samples.npy"]
    header = (d / "obj_000012.ply").read_bytes()[:400].split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header
    for prop in ("float x", "float y", "float z", "float nx", "float ny", "float nz", "list uchar int vertex_indices"):
        assert f"property {prop}" in header
    info = json.loads((d / "models_info.json").read_text())
    kps = json.loads((d / mb.KEYPOINTS_FILE).read_text())
    assert sorted(info) == sorted(kps) == ["12", "7"]
    for o, m in models.items():
        mesh = trimesh.load(d / f"obj_{o:06d}.ply", process=False)
        assert np.allclose(mesh.vertices, m.vertices, atol=1e-4) and np.array_equal(mesh.faces, m.faces)
        truth = get_object(o).models_info()
        e = info[str(o)]
        for k in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"):
            assert e[k] == pytest.approx(truth[k], abs=1e-3), k
        assert e["source"] == "test"
        assert {k: v for k, v in e.items() if k.startswith("symmetries")} == m.symmetries
        S = np.load(d / f"obj_{o:06d}_samples.npy")
        assert S.shape == (3000, 3) and S.dtype == np.float32
        assert _distance(_scene(m.vertices, m.faces), S).max() < 1e-3
        assert np.asarray(kps[str(o)]).shape == (9, 3)
    # the keypoints are those the network's loader computes from the PLY files
    loaded = model_keypoints(d)
    for o in models:
        assert np.allclose(kps[str(o)], loaded[o], atol=1e-5)
    assert symmetry_kind(info["12"]) == "continuous" and symmetry_kind(info["7"]) is None


def test_load_models_reads_back_what_write_models_wrote(written):
    d, models = written
    got = mb.load_models(d)
    assert sorted(got) == sorted([JAR, MUG])
    info = json.loads((d / "models_info.json").read_text())
    for o, (V, F, e) in got.items():
        assert np.allclose(V, models[o].vertices, atol=1e-4) and np.array_equal(F, models[o].faces)
        assert e == info[str(o)]
    assert sorted(mb.load_models(d, obj_ids=[MUG])) == [MUG]


def test_load_models_errors_name_the_file(written, tmp_path):
    src, _ = written

    def copy(name):
        d = tmp_path / name
        shutil.copytree(src, d)
        return d

    def fails(d, pattern, path, obj_ids=None):
        with pytest.raises(TdofError, match=pattern) as e:
            mb.load_models(d, obj_ids=obj_ids)
        assert str(e.value).startswith(str(path)) and "\n" not in str(e.value)

    fails(tmp_path / "nowhere", "models folder not found", tmp_path / "nowhere")
    d = copy("no_info")
    (d / "models_info.json").unlink()
    fails(d, r"no models_info\.json", d)
    fails(src, r"no entry for object\(s\) \[99\]", src / "models_info.json", obj_ids=[JAR, 99])
    d = copy("no_mesh")
    (d / "obj_000007.ply").unlink()
    fails(d, "model file not found", d / "obj_000007.ply")
    d = copy("metres")
    m = trimesh.load(d / "obj_000012.ply", process=False)
    m.apply_scale(0.001)
    m.export(d / "obj_000012.ply")
    fails(d, "metres", d / "obj_000012.ply")
    d = copy("other")
    m = trimesh.load(d / "obj_000012.ply", process=False)
    m.apply_scale(1.2)                                       # another model: 20 % larger than models_info says
    m.export(d / "obj_000012.ply")
    fails(d, r"across but models_info\.json says", d / "obj_000012.ply")
    d = copy("info_metres")
    info = json.loads((d / "models_info.json").read_text())
    info["7"]["diameter"] = 0.1300  # handle_cup_280: 130.0 mm
    (d / "models_info.json").write_text(json.dumps(info))
    fails(d, "looks like metres", d / "models_info.json")
