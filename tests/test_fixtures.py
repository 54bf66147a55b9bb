"""Self-checks of the documentation-only fixtures (tests/fixtures): files, formats and geometry agree.

These tests read the written files back with plain libraries (json, pickle, cv2, trimesh), never with
tdof20 code: the fixtures exist to test tdof20's readers against an independent reading of the docs.
"""

import json
import pickle
import time

import cv2
import numpy as np
import pytest
import trimesh

from fixtures import _geometry as g
from fixtures.bop_standard import write_bop_dataset
from fixtures.tdof20_release import HARD_TEST, write_tdof20_release

MODALITIES = {"rgb": "jpg", "depth": "png", "broken_depth": "png", "mask": "png", "labels": "txt", "pose": "pkl"}


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    g.o3d()  # import once, outside the timed build
    t0 = time.perf_counter()
    info = write_tdof20_release(tmp_path_factory.mktemp("tdof20") / "TDoF20")
    info["build_s"] = time.perf_counter() - t0
    return info


@pytest.fixture(scope="module")
def bop(tmp_path_factory):
    g.o3d()
    t0 = time.perf_counter()
    info = write_bop_dataset(tmp_path_factory.mktemp("bop") / "ds", rgb_ext={"test": "jpg"})
    info["build_s"] = time.perf_counter() - t0
    return info


def _read_list(path):
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]


# ------------------------------------------------------------------------------------------ TDoF20

def test_release_layout_and_lists(release):
    root = release["root"]
    assert release["build_s"] < 2.0
    cfg = root / "dataset_config"
    assert _read_list(cfg / "classes.txt") == release["classes"]
    intr = json.loads((cfg / "intrinsics.json").read_text())
    assert set(intr) == {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"}
    lists = {n: _read_list(cfg / n) for n in ("train_data_list.txt", "test_data_list.txt",
                                               "hard_train_data_list.txt", "hard_test_data_list.txt",
                                               "visual_data_list.txt")}
    for name, rows in lists.items():
        assert rows == release["lists"][name] and len(rows) == release["counts"][name]
        for row in rows:  # every line indexes a frame stem whose modalities all exist
            top, scene, stem = row.split("/")
            for mod, ext in MODALITIES.items():
                assert (root / top / scene / mod / f"{stem}.{ext}").is_file()
    single = {k for k, f in release["frames"].items() if f["kind"] == "single"}
    train, test = set(lists["train_data_list.txt"]), set(lists["test_data_list.txt"])
    assert not train & test and train | test == single
    assert set(lists["visual_data_list.txt"]) <= test
    hard_tr, hard_te = set(lists["hard_train_data_list.txt"]), set(lists["hard_test_data_list.txt"])
    assert single <= hard_tr and not hard_tr & hard_te
    assert {r.split("/")[1] for r in hard_te} == {"02"} and {r.split("/")[1] for r in hard_tr - single} == {"00"}
    assert all(r.split("/")[1] in HARD_TEST for r in hard_te)
    assert hard_tr | hard_te == set(release["frames"])


def test_release_models_diameters_keypoints(release):
    root = release["root"]
    for c in release["classes"]:
        mesh = trimesh.load(root / "models" / f"{c}.ply", process=False)
        d = float((root / "diameters" / f"{c}_diameter.txt").read_text())
        assert d == pytest.approx(g.diameter(mesh.vertices), rel=1e-5)  # same units as the mesh (m)
        assert 0.04 < d < 0.2
        kp = np.loadtxt(root / "farthest" / f"{c}_farthest.txt")
        assert kp.shape == (8, 3)
        O3 = g.o3d()
        scene = O3.t.geometry.RaycastingScene()
        scene.add_triangles(O3.t.geometry.TriangleMesh.from_legacy(
            O3.geometry.TriangleMesh(O3.utility.Vector3dVector(mesh.vertices),
                                     O3.utility.Vector3iVector(mesh.faces))))
        dist = scene.compute_distance(O3.core.Tensor(kp.astype(np.float32))).numpy()
        assert dist.max() < 1e-5  # on the surface
        assert np.linalg.norm(kp, axis=1).min() > 0.3 * d  # far from the centre, spread out
        assert np.linalg.norm(kp[:, None] - kp[None], axis=2)[np.triu_indices(8, 1)].min() > 0.1 * d


def test_release_pose_mask_depth_agree(release):
    root, K = release["root"], release["K"]
    seen_occluded = False
    for key, f in release["frames"].items():
        d = root / f["kind"].replace("single", "single_data").replace("multi", "multi_data") / f["scene"]
        with open(d / "pose" / f"{f['stem']}.pkl", "rb") as fh:
            rec = pickle.load(fh)
        P, ids = rec["poses"], rec["cls_ids"]
        n = len(f["instances"])
        assert P.shape == (3, 4, n) and ids.shape == (n,) and rec["center_3ds"].shape == (n, 3)
        mask = cv2.imread(str(d / "mask" / f"{f['stem']}.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(d / "depth" / f"{f['stem']}.png"), cv2.IMREAD_UNCHANGED)
        broken = cv2.imread(str(d / "broken_depth" / f"{f['stem']}.png"), cv2.IMREAD_UNCHANGED)
        rgb = cv2.imread(str(d / "rgb" / f"{f['stem']}.jpg"))
        assert mask.dtype == np.uint8 and depth.dtype == np.uint16 and broken.dtype == np.uint16
        assert mask.shape == depth.shape == rgb.shape[:2] == (48, 64)
        assert (depth > 0).all() and (broken[mask > 0] == 0).any()
        assert set(np.unique(mask)) - {0} <= set(range(1, len(release["classes"]) + 1))
        labels = [ln.split() for ln in (d / "labels" / f"{f['stem']}.txt").read_text().splitlines()]
        for k, inst in enumerate(f["instances"]):
            R, t_m = P[:, :3, k], P[:, 3, k]
            assert ids[k] == inst["cls_id"]
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
            assert np.allclose(t_m * 1000.0, inst["t_mm"]) and np.allclose(rec["center_3ds"][k], t_m)
            assert 300 < inst["t_mm"][2] < 600
            u, v = np.round(g.project(K, t_m)[0]).astype(int)  # the model centre reprojects on its pixels
            cover = mask[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2]
            if inst["px_visib"] == inst["px_all"]:
                assert (cover == ids[k]).any(), key
                # stabilized depth at the centre pixel: the object's front surface, in front of the centre
                assert 0 < inst["t_mm"][2] - depth[v, u] < 60 or mask[v, u] != ids[k]
            else:
                seen_occluded = True
            assert (mask == ids[k]).sum() == inst["px_visib"]
            assert int(labels[k][0]) == ids[k]
            if inst["px_visib"]:
                x, y, bw, bh = inst["bbox_xywh"]
                assert [int(s) for s in labels[k][1:]] == [x, y, x + bw, y + bh]
    assert seen_occluded  # multi scenes have occlusions


def test_release_units_and_forms(tmp_path):
    info = write_tdof20_release(tmp_path / "a", classes=("cube_136", "juice_cup_250"), multi=("09",),
                                frames_per_scene=2, pose_units="mm", model_units="mm", intrinsics_form="K",
                                list_form="short", visual_name="visual_data.txt", depth_scale=0.5,
                                cls_ids_shape="column", extra_pkl_keys=True)
    root = info["root"]
    cfg = root / "dataset_config"
    intr = json.loads((cfg / "intrinsics.json").read_text())
    assert np.allclose(intr["K"], info["K"]) and intr["depth_scale"] == 0.5
    assert (cfg / "visual_data.txt").is_file() and not (cfg / "visual_data_list.txt").exists()
    assert _read_list(cfg / "hard_test_data_list.txt") == ["09/000000", "09/000001"]
    assert all(r.startswith("cube_136/") or r.startswith("juice_cup_250/") for r in _read_list(cfg / "test_data_list.txt"))
    assert float((root / "diameters" / "cube_136_diameter.txt").read_text()) == pytest.approx(
        info["diameters_mm"]["cube_136"], rel=1e-5)
    f = info["frames"]["multi_data/09/000000"]
    with open(root / "multi_data/09/pose/000000.pkl", "rb") as fh:
        rec = pickle.load(fh)
    assert rec["cls_ids"].shape == (2, 1) and rec["kp_3ds"].shape == (2, 8, 3)
    assert np.allclose(rec["poses"][:, 3, 0], f["instances"][0]["t_mm"])
    depth = cv2.imread(str(root / "multi_data/09/depth/000000.png"), cv2.IMREAD_UNCHANGED)
    assert np.allclose(depth * 0.5, f["depth_mm"], atol=0.3)
    j = np.loadtxt(root / "farthest" / "juice_cup_250_farthest.txt")
    assert np.abs(j).max() > 20  # mm


def test_release_broken_variants(tmp_path):
    info = write_tdof20_release(tmp_path / "b", classes=("cube_136",), multi=(), frames_per_scene=2,
                                missing_list="test_data_list.txt", pkl_drop_keys=("poses",), bad_cls_id=True,
                                pose_units="mm", drop_file=("depth", 1), classes_txt=["cube_136", "cube_166"])
    root = info["root"]
    assert not (root / "dataset_config" / "test_data_list.txt").exists()
    assert "test_data_list.txt" not in info["counts"]
    assert _read_list(root / "dataset_config" / "classes.txt") == ["cube_136", "cube_166"]
    with open(root / "single_data/cube_136/pose/000000.pkl", "rb") as fh:
        rec = pickle.load(fh)
    assert "poses" not in rec and rec["cls_ids"].tolist() == [2]
    mask = cv2.imread(str(root / "single_data/cube_136/mask/000000.png"), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(mask)) == {0, 2}
    assert not (root / "single_data/cube_136/depth/000001.png").exists()
    assert (root / "single_data/cube_136/depth/000000.png").exists()
    with pytest.raises(TypeError):
        write_tdof20_release(tmp_path / "c", no_such_variant=1)


# ------------------------------------------------------------------------------------------ BOP

def test_bop_layout(bop):
    root = bop["root"]
    assert bop["build_s"] < 2.0
    cam = json.loads((root / "camera.json").read_text())
    assert set(cam) == {"cx", "cy", "depth_scale", "fx", "fy", "height", "width"}
    for folder in ("models", "models_eval"):
        info = json.loads((root / folder / "models_info.json").read_text())
        assert sorted(int(k) for k in info) == [1, 5, 30]
        for oid in (1, 5, 30):
            mesh = trimesh.load(root / folder / f"obj_{oid:06d}.ply", process=False)
            e = info[str(oid)]
            assert e["diameter"] == pytest.approx(g.diameter(mesh.vertices), rel=1e-6)
            assert np.allclose([e["min_x"], e["min_y"], e["min_z"]], mesh.bounds[0], atol=1e-5)
            assert np.allclose([e["size_x"], e["size_y"], e["size_z"]], np.ptp(mesh.bounds, axis=0), atol=1e-5)
        assert "symmetries_discrete" in info["1"] and "symmetries_continuous" in info["5"]
        assert not {"symmetries_discrete", "symmetries_continuous"} & set(info["30"])
        for s in info["1"]["symmetries_discrete"]:
            T = np.reshape(s, (4, 4))
            assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.allclose(T[3], [0, 0, 0, 1])
    assert sorted(p.name for p in root.iterdir()) == ["camera.json", "models", "models_eval", "test",
                                                     "test_targets_bop19.json", "train_pbr"]
    assert [p.name for p in (root / "train_pbr").iterdir()] == ["000000"]
    assert [p.name for p in (root / "test").iterdir()] == ["000001"]
    targets = json.loads((root / "test_targets_bop19.json").read_text())
    assert targets == bop["targets"] and targets
    assert all(set(t) == {"im_id", "inst_count", "obj_id", "scene_id"} and t["scene_id"] == 1 for t in targets)


def test_bop_scenes_consistent(bop):
    K = bop["K"]
    partly = False
    for split, scenes in bop["splits"].items():
        for sc, s in scenes.items():
            d = s["dir"]
            cams = json.loads((d / "scene_camera.json").read_text())
            gts = json.loads((d / "scene_gt.json").read_text())
            infos = json.loads((d / "scene_gt_info.json").read_text())
            assert sorted(cams, key=int) == sorted(gts, key=int) == sorted(infos, key=int) == ["0", "1", "2", "3"]
            for im, im_gt in gts.items():
                assert np.allclose(np.reshape(cams[im]["cam_K"], (3, 3)), K)
                scale = cams[im]["depth_scale"]
                assert scale == (0.1 if split == "train_pbr" else 1.0)
                depth = cv2.imread(str(d / "depth" / f"{int(im):06d}.png"), cv2.IMREAD_UNCHANGED)
                assert depth.dtype == np.uint16
                rgb = cv2.imread(str(d / s["images"][int(im)]["rgb"]))
                assert rgb.shape == (48, 64, 3) and s["images"][int(im)]["rgb"].endswith(s["rgb_ext"])
                for gt_id, (gt, gi) in enumerate(zip(im_gt, infos[im])):
                    R = np.reshape(gt["cam_R_m2c"], (3, 3))
                    t = np.asarray(gt["cam_t_m2c"])
                    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
                    full = cv2.imread(str(d / "mask" / f"{int(im):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED)
                    vis = cv2.imread(str(d / "mask_visib" / f"{int(im):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED)
                    assert set(np.unique(full)) <= {0, 255} and not (vis & ~full).any()
                    assert gi["px_count_all"] == (full > 0).sum() and gi["px_count_visib"] == (vis > 0).sum()
                    assert gi["px_count_valid"] == ((full > 0) & (depth > 0)).sum()
                    assert gi["visib_fract"] == pytest.approx(gi["px_count_visib"] / gi["px_count_all"])
                    if gi["px_count_visib"]:
                        ys, xs = np.nonzero(vis)
                        assert gi["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
                    u, v = np.round(g.project(K, t)[0]).astype(int)
                    assert full[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2].any()  # centre on the silhouette
                    partly |= 0 < gi["visib_fract"] < 1
                    zs = depth[vis > 0] * scale
                    zs = zs[zs > 0]
                    if len(zs):  # the visible surface lies within the bbox half-diagonal of the centre depth
                        e = bop["models_info"][str(gt["obj_id"])]
                        half = np.linalg.norm([e["size_x"], e["size_y"], e["size_z"]]) / 2
                        assert np.abs(zs - t[2]).max() < half + 1
    assert partly
