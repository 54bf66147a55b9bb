"""The independent raw-session writer (tests/fixtures/raw_session.py): `tdof20 capture verify` accepts its
sessions, and its truth is self-consistent — checked against the written files with plain libraries
(json, hashlib, cv2) and a ray cast of its own (open3d), never with tdof20's readers. The annotation
comparison (slow: `tdof20 annotate` on a 2-arm session) is in tests/fixtures/README.md."""

import hashlib
import json
import time

import cv2
import numpy as np
import pytest

from cli_support import run_here
from fixtures import _geometry as g
from fixtures.raw_session import compare_labels, ur5_fk, write_raw_session

OBJ_IDS = (7, 11)
LAYOUT = ((-20.0, 60.0, 25.0), (60.0, -55.0, 0.0))
BIAS = 1.02


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    from tdof20.objects import export_models  # the only tdof20 code the fixture's tests use for input

    d = tmp_path_factory.mktemp("models")
    export_models(d, list(OBJ_IDS))
    return d


@pytest.fixture(scope="module")
def session(tmp_path_factory, models):
    g.o3d()
    root = tmp_path_factory.mktemp("raw") / "s"
    t0 = time.perf_counter()
    truth = write_raw_session(root, models_dir=models, obj_ids=OBJ_IDS, layout=LAYOUT, n_arms=2, steps=3,
                              step_deg=40.0, size=(160, 120), depth_bias=BIAS, twin_offset_mm=2.0,
                              twin_offset_deg=1.0, seed=3, clutter=True)
    truth["build_s"] = time.perf_counter() - t0
    return root, truth, models


def test_capture_verify_accepts_it(session, capfd, monkeypatch):
    root, truth, _ = session
    assert truth["build_s"] < 10.0
    r = run_here(capfd, monkeypatch, "capture", "verify", root)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ok" in r.stdout + r.stderr  # the docs do not say which stream: stderr here


def test_layout_journal_and_truth_outside(session):
    root, truth, _ = session
    assert not (root / "truth").exists()
    assert truth["truth_path"] and not str(truth["truth_path"]).startswith(str(root) + "/")
    assert json.loads(open(truth["truth_path"]).read())["depth_bias"] == BIAS
    info = json.loads((root / "session.json").read_text())
    assert info["format"] == "tdof20-raw-session" and info["camera"]["depth_scale"] == 1.0
    lines = [json.loads(x) for x in (root / "journal.jsonl").read_text().splitlines()]
    assert len(lines) == 2 * 2 * 3
    assert [ln["phase"] for ln in lines] == ["transparent"] * 6 + ["opaque"] * 6
    for ln in lines:
        for kind in ("rgb", "depth"):
            assert hashlib.sha256((root / ln[kind]).read_bytes()).hexdigest() == ln["sha256"][kind]
        rgb = cv2.imread(str(root / ln["rgb"]), cv2.IMREAD_UNCHANGED)
        d = cv2.imread(str(root / ln["depth"]), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (120, 160, 3) and rgb.dtype == np.uint8
        assert d.shape == (120, 160) and d.dtype == np.uint16
    for a, arm in zip(info["arm_positions"], truth["arms"]):  # T_base_tcp = fk(q), UR5 standard DH
        assert np.allclose(ur5_fk(a["q"]), np.reshape(a["T_base_tcp"], (4, 4)), atol=1e-6)
        T_cam = np.reshape(a["T_base_tcp"], (4, 4)) @ np.reshape(info["hand_eye"]["T_tcp_cam"], (4, 4))
        assert np.allclose(T_cam, np.reshape(arm["T_base_cam"], (4, 4)))


def _cast_alone(models, obj_id, K, size, R, t):
    """Depth (mm) of one model at a pose, rays through pixel centres (u + 0.5, v + 0.5)."""
    import trimesh

    O3 = g.o3d()
    m = trimesh.load(models / f"obj_{obj_id:06d}.ply", process=False, force="mesh")
    v = (R @ np.asarray(m.vertices).T).T + t
    sc = O3.t.geometry.RaycastingScene()
    sc.add_triangles(O3.core.Tensor(v.astype(np.float32)), O3.core.Tensor(np.asarray(m.faces, np.uint32)))
    w, h = size
    u, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))  # pixel centres at integer (u, v)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays = np.concatenate([np.zeros_like(d), d], -1).astype(np.float32)
    z = sc.cast_rays(O3.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(z), z, 0.0)


def test_opaque_depth_is_the_twin_times_the_bias(session):
    """On the opaque frames the measured depth over an object is its twin's ray-cast depth x depth_bias
    (within the stereo noise), and clearly not the bias-free depth; the twin stands where the truth says,
    `twin_offset_mm` from the transparent pose; transparent glass pixels mostly have no depth."""
    root, truth, models = session
    K = np.reshape(truth["K"], (3, 3))
    size = tuple(truth["size"])
    ratios, holes = [], []
    for f in truth["frames"]:
        d = cv2.imread(str(root / f["phase"] / f"arm{f['arm']}" / "depth" / f"{f['step']:06d}.png"),
                       cv2.IMREAD_UNCHANGED).astype(np.float64)
        for lab, tw in zip(f["gt"], f["twins"]):
            assert lab["obj_id"] == tw["obj_id"]
            Rl, tl = np.reshape(lab["R"], (3, 3)), np.asarray(lab["t"])
            Rw, tw_ = np.reshape(tw["R"], (3, 3)), np.asarray(tw["t"])
            assert np.linalg.norm(tw_ - tl) == pytest.approx(2.0, abs=1e-6)
            ang = np.degrees(np.arccos(np.clip((np.trace(Rl.T @ Rw) - 1) / 2, -1, 1)))
            assert ang == pytest.approx(1.0, abs=1e-4)
            pose = (Rw, tw_) if f["phase"] == "opaque" else (Rl, tl)
            z = _cast_alone(models, lab["obj_id"], K, size, *pose)
            m = (z > 0) & (d > 0)
            if f["phase"] == "opaque":
                m &= cv2.erode((z > 0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
                m &= np.abs(d - z * BIAS) < 30  # the object's own pixels (not an occluder in front)
                if m.sum() > 20:
                    ratios.append(np.median(d[m] / z[m]))
            else:
                holes.append(np.mean(d[z > 0] == 0))
    assert len(ratios) >= 8
    assert np.median(ratios) == pytest.approx(BIAS, abs=0.002)
    assert np.median(holes) > 0.45


def test_compare_labels_of_the_truth_is_zero(session, tmp_path):
    """compare_labels on a scene whose labels are the truth itself (scene_gt/scene_camera as BOP writes
    them) gives zero errors and every frame."""
    _, truth, _ = session
    gt, cam = {}, {}
    for f in truth["frames"]:
        if f["phase"] != "transparent":
            continue
        T = np.reshape(f["T_cam_table"], (4, 4))
        gt[str(f["im_id"])] = [{"obj_id": e["obj_id"], "cam_R_m2c": e["R"], "cam_t_m2c": e["t"]} for e in f["gt"]]
        cam[str(f["im_id"])] = {"cam_K": truth["K"], "depth_scale": 1.0,
                                "cam_R_w2c": T[:3, :3].ravel().tolist(), "cam_t_w2c": T[:3, 3].tolist()}
    (tmp_path / "scene_gt.json").write_text(json.dumps(gt))
    (tmp_path / "scene_camera.json").write_text(json.dumps(cam))
    c = compare_labels(tmp_path, truth)
    assert c["frames_labelled"] == c["frames_planned"] == 6
    assert c["instances"] == 12 and c["missing_instances"] == 0
    assert c["t_err_mm"]["max"] < 1e-6 and c["r_err_deg"]["max"] < 1e-3
    assert c["camera_motion"]["r_deg"]["max"] < 1e-3 and c["cam_K_matches"]
