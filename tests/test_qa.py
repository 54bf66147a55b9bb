"""Evaluation of labels against the simulator's truth, and the QA outputs (overlays, plots, report).

The oracle scene (labels = truth) measures zero; known perturbations of the labels are measured
as what they are; a change of a model's frame changes nothing; the report references only files
that exist and says why frames were flagged."""

import html
import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from tdof20.annotate.evaluate import evaluate_command, evaluate_scene, model_centre
from tdof20.annotate.qa import write_qa
from tdof20.annotate.registration import (ArmRegistration, FrameRegistration, RegistrationConfig,
                                          RegistrationResult)
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import dumps_bop_json, pose_from_bop, pose_to_bop, read_json, read_png, read_scene, write_png
from tdof20.geometry.transforms import rotation_about_axis
from tdof20.sim.truth import oracle_scene

STEPS, ARMS = 4, 2


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    root = tmp_path_factory.mktemp("qa")
    raw = root / "raw"
    run_capture(sim_config("multi/08", steps=STEPS, step_deg=10, n_arms=ARMS, width=160, height=120), raw,
                yes=True, show_progress=False)
    scene = oracle_scene(raw, root / "oracle", show_progress=False)
    return scene, raw / "truth"


def _copy(scene: Path, dst: Path) -> Path:
    shutil.copytree(scene, dst)
    return dst


def _T(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rewrite_gt(scene: Path, fn) -> None:
    """fn(im_id, gt_id, obj_id, T (4,4)) -> T: rewrite every pose of scene_gt.json."""
    raw = read_json(scene / "scene_gt.json")
    for k, lst in raw.items():
        for g, e in enumerate(lst):
            T = fn(int(k), g, e["obj_id"], _T(*pose_from_bop(e)))
            lst[g] = pose_to_bop(T[:3, :3], T[:3, 3], obj_id=e["obj_id"])
    (scene / "scene_gt.json").write_text(dumps_bop_json(raw))


def _centre(truth: Path, obj_id: int) -> np.ndarray:
    return model_centre(trimesh.load(str(truth / "models" / f"obj_{obj_id:06d}.ply"), process=False).vertices)


# ---------------------------------------------------------------------------------------------
# evaluate
# ---------------------------------------------------------------------------------------------
def test_oracle_measures_zero(oracle):
    scene, truth = oracle
    ev = json.loads(evaluate_command(scene, truth))
    assert ev["n_evaluated_frames"] == ev["n_truth_frames"] == STEPS * ARMS
    assert ev["missing_frames"] == [] and ev["extra_frames"] == [] and ev["low_visib_iou"] == []
    assert len(ev["objects"]) == 4
    for e in [*ev["objects"].values(), ev["all"]]:
        assert e["motion_rot_deg"]["max"] < 1e-5 and e["motion_trans_mm"]["max"] < 1e-5
        assert e["surface_mm"]["max"] < 1e-3
        assert e["iou_full"]["min"] == 1.0 and e["iou_visib"]["min"] == 1.0
    # 7 consecutive pairs + 7 sampled far pairs per object
    assert ev["objects"]["6"]["motion_rot_deg"]["n"] == 14
    assert all(t["ok"] for t in ev["all"]["targets"].values())
    # the sample-to-sample distance of identical meshes sampled alike is zero too
    ev2 = evaluate_scene(scene, truth, distance="samples", max_frames=3)
    assert ev2["n_evaluated_frames"] == 3 and ev2["all"]["surface_mm"]["max"] < 1e-6


def test_perturbed_labels_are_measured(oracle, tmp_path):
    scene, truth = oracle
    lab = _copy(scene, tmp_path / "perturbed")
    t0 = read_scene(truth)
    obj = t0.gt[0][0]["obj_id"]
    c = _centre(truth, obj)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shift = np.array([1.2, -1.6, 0.0])          # 2 mm

    def perturb(im, g, o, T):
        if o != obj:
            return T
        if im == 2:   # 1 deg about the object's centre
            return rotation_about_axis(axis, math.radians(1.0), T[:3, :3] @ c + T[:3, 3]) @ T
        if im == 6:   # 2 mm
            T = T.copy()
            T[:3, 3] += shift
        return T
    _rewrite_gt(lab, perturb)
    # erase the left half of one visible mask
    g_er = 1
    name = lab / "mask_visib" / f"{4:06d}_{g_er:06d}.png"
    m = read_png(name, kind="mask") > 0
    xs = np.nonzero(m)[1]
    cut = m & (np.arange(m.shape[1])[None] < np.median(xs))
    write_png(name, ((m & ~cut) * 255).astype(np.uint8))
    expected_iou = (m & ~cut).sum() / m.sum()
    assert expected_iou < 0.9

    ev = evaluate_scene(lab, truth, far_pairs=0, per_frame=True)
    o = ev["objects"][str(obj)]
    # consecutive pairs 0-1 ... 6-7: (1,2) and (2,3) carry the 1 deg rotation about the centre (no
    # translation there); (5,6) and (6,7) the 2 mm shift (no rotation)
    assert o["motion_rot_deg"]["n"] == 7
    assert o["motion_rot_deg"]["max"] == pytest.approx(1.0, abs=1e-4)
    assert o["motion_rot_deg"]["mean"] == pytest.approx(2 / 7, abs=1e-4)
    assert o["motion_trans_mm"]["max"] == pytest.approx(2.0, abs=1e-4)
    assert o["motion_trans_mm"]["mean"] == pytest.approx(4 / 7, abs=1e-4)
    for k, e in ev["objects"].items():
        if k != str(obj):
            assert e["motion_rot_deg"]["max"] < 1e-5 and e["motion_trans_mm"]["max"] < 1e-5
    surf = {(r["im_id"], r["obj_id"]): r["surface_mm"] for r in ev["frames"]}
    diam = read_json(truth / "models" / "models_info.json")[str(obj)]["diameter"]
    assert 0.05 < surf[(2, obj)] < math.radians(1.0) * diam / 2 + 1e-3   # a 1 deg turn moves no point further
    assert 0.3 < surf[(6, obj)] <= 2.0 + 1e-3                             # a 2 mm shift: between 0 and 2
    assert all(v < 1e-3 for (im, o_), v in surf.items() if (im, o_) not in {(2, obj), (6, obj)})
    # the erased mask
    obj_er = t0.gt[4][g_er]["obj_id"]
    row = next(r for r in ev["frames"] if r["im_id"] == 4 and r["obj_id"] == obj_er)
    assert row["iou_visib"] == pytest.approx(expected_iou, abs=1e-12) and row["iou_full"] == 1.0
    assert ev["low_visib_iou"] == [{"im_id": 4, "obj_id": obj_er, "iou_visib": round(expected_iou, 4), "iou_full": 1.0}]
    assert ev["objects"][str(obj_er)]["iou_visib"]["min"] == pytest.approx(expected_iou, abs=1e-6)


def test_model_frame_change_changes_nothing(oracle, tmp_path):
    scene, truth = oracle
    lab = _copy(scene, tmp_path / "reframed")
    obj = read_scene(truth).gt[0][1]["obj_id"]
    X = rotation_about_axis(np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5]), math.radians(35.0))
    X[:3, 3] = [15.0, -7.0, 22.0]              # new model frame: p_new = inv(X) p_old, T_new = T X
    ply = lab / "models" / f"obj_{obj:06d}.ply"
    mesh = trimesh.load(str(ply), process=False)
    Xi = np.linalg.inv(X)
    V = mesh.vertices @ Xi[:3, :3].T + Xi[:3, 3]
    ply.write_bytes(trimesh.exchange.ply.export_ply(trimesh.Trimesh(V, mesh.faces, process=False), encoding="binary"))
    _rewrite_gt(lab, lambda im, g, o, T: T @ X if o == obj else T)
    lt, tt = read_scene(lab), read_scene(truth)
    assert np.linalg.norm(lt.pose(0, 1)[1] - tt.pose(0, 1)[1]) > 10   # the poses do differ
    for distance, tol in (("mesh", 1e-3), ("samples", 0.05)):
        ev = evaluate_scene(lab, truth, distance=distance)
        e = ev["objects"][str(obj)]
        assert e["motion_rot_deg"]["max"] < 1e-4 and e["motion_trans_mm"]["max"] < 1e-4
        assert e["surface_mm"]["max"] < tol
        assert e["iou_visib"]["min"] == 1.0


def test_evaluate_errors(oracle, tmp_path):
    scene, truth = oracle
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hello")
    with pytest.raises(TdofError, match="not an annotated scene") as e:
        evaluate_scene(tmp_path / "junk", truth)
    assert "\n" not in str(e.value)
    with pytest.raises(TdofError, match="no such scene folder"):
        evaluate_scene(tmp_path / "nowhere", truth)
    bad_truth = _copy(truth, tmp_path / "truth_no_gt")
    (bad_truth / "scene_gt.json").unlink()
    with pytest.raises(TdofError, match="truth has no scene_gt.json"):
        evaluate_scene(scene, bad_truth)
    shifted = _copy(scene, tmp_path / "shifted")
    for f in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
        d = read_json(shifted / f)
        (shifted / f).write_text(dumps_bop_json({str(int(k) + 100): v for k, v in d.items()}))
    with pytest.raises(TdofError, match="no image in common"):
        evaluate_scene(shifted, truth)
    # a raw session folder is accepted for the truth; frames missing from the labels are listed
    part = _copy(scene, tmp_path / "part")
    gt = read_json(part / "scene_gt.json")
    del gt["3"]
    (part / "scene_gt.json").write_text(dumps_bop_json(gt))
    ev = evaluate_scene(part, truth.parent)
    assert ev["missing_frames"] == [3] and ev["n_evaluated_frames"] == STEPS * ARMS - 1


# ---------------------------------------------------------------------------------------------
# write_qa
# ---------------------------------------------------------------------------------------------
def _registration() -> RegistrationResult:
    frames = []
    for a in range(ARMS):
        for k in range(STEPS):
            bad = (a, k) == (1, 2)
            frames.append(FrameRegistration(a, k, np.eye(4), fitness=0.9 - 0.05 * k, rmse=1.0 + 0.1 * k,
                                            residual_deg=3.2 if bad else 0.05 * k, residual_mm=0.4 * k,
                                            flagged=bad, reason="residual 3.2 deg > 1.0 <&>" if bad else ""))
    arms = [ArmRegistration(a, np.array([0, 0, 1.0]), np.zeros(3), np.array([0, 0, 1.0]), 0.0, 300.0, np.eye(4), np.eye(4))
            for a in range(ARMS)]
    return RegistrationResult("multi/08", STEPS, 10.0, ARMS, frames, arms, RegistrationConfig().to_dict())


def _srcs(report: Path) -> list[str]:
    return re.findall(r"""(?:src|href)=["']([^"']+)["']""", report.read_text())


def test_write_qa_report(oracle, tmp_path):
    scene, truth = oracle
    lab = _copy(scene, tmp_path / "scene")
    # frame 5 lost its labels (say ICP diverged); it keeps its colour image
    for f in ("scene_gt.json", "scene_gt_info.json"):
        d = read_json(lab / f)
        del d["5"]
        (lab / f).write_text(dumps_bop_json(d))
    reg = _registration()
    reg_path = reg.save(tmp_path / "registration.json")
    ev = evaluate_scene(lab, truth)
    report = write_qa(lab, registration=reg_path, flagged=[(5, "no labels: ICP diverged"), (0, 3, "operator: smudge")],
                      sample=3, progress=False, evaluation=ev)
    out = lab / "qa"
    assert report == out / "report.html" and report.exists()
    text = report.read_text()
    refs = _srcs(report)
    assert "registration.png" in refs and any(r.startswith("overlays/") for r in refs)
    for r in refs:
        assert (out / r).is_file(), r
    for reason in ("no labels: ICP diverged", "operator: smudge", "residual 3.2 deg > 1.0 <&>"):
        assert html.escape(reason) in text
    assert "<&>" not in text
    assert "Evaluation against the truth" in text
    qa = read_json(out / "qa.json")
    assert {f["im_id"] for f in qa["flagged"]} == {3, 5, 6}
    assert {o["im_id"] for o in qa["overlays"]} >= {3, 5, 6} and len(qa["overlays"]) <= 6
    assert (out / "contact_sheet.png").exists()
    plot = read_png(out / "registration.png", kind="rgb")
    assert plot.shape[0] > 300 and plot.shape[1] > 300 and plot.std() > 10

    # a labelled overlay differs from the colour image inside the masks, not far from them
    s = read_scene(lab)
    im = next(o["im_id"] for o in qa["overlays"] if o["labelled"] and not o["flagged"])
    rgb = cv2.resize(s.rgb(im), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    ov = read_png(out / "overlays" / f"{im:06d}.png", kind="rgb")
    assert ov.shape == rgb.shape
    up = lambda m: cv2.resize(m.astype(np.uint8), (ov.shape[1], ov.shape[0]), interpolation=cv2.INTER_NEAREST) > 0  # noqa: E731
    n = len(s.gt[im])
    vis = np.any([up(s.mask(im, g, visib=True)) for g in range(n)], axis=0)
    full = np.any([up(s.mask(im, g)) for g in range(n)], axis=0)
    near = cv2.dilate(full.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    diff = np.abs(ov.astype(int) - rgb.astype(int)).sum(2)
    body = np.zeros(full.shape, bool)
    body[30:] = True                                   # below the caption band
    assert np.mean(diff[vis & body] > 0) > 0.9
    assert np.all(diff[~near & body] == 0)

    # the flagged frame without labels: the colour image with the reason written on it, nothing else
    ov5 = read_png(out / "overlays" / f"{5:06d}.png", kind="rgb")
    rgb5 = cv2.resize(s.rgb(5), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    d5 = np.abs(ov5.astype(int) - rgb5.astype(int)).sum(2)
    assert np.all(d5[30:-40] == 0)
    assert d5[-40:].any() and d5[:30].any()


def test_write_qa_without_registration(oracle, tmp_path):
    scene, _ = oracle
    out = tmp_path / "qa_out"
    report = write_qa(scene, sample=2, out_dir=out, progress=False)
    assert report == out / "report.html"
    refs = _srcs(report)
    assert "registration.png" not in refs and not (out / "registration.png").exists()
    assert sorted(p.name for p in (out / "overlays").iterdir()) == ["000000.png", "000007.png"]
    for r in refs:
        assert (out / r).is_file(), r
    with pytest.raises(TdofError, match="no such scene folder"):
        write_qa(tmp_path / "nowhere", progress=False)
    with pytest.raises(TdofError, match="cannot read the flagged frame"):
        write_qa(scene, flagged=[(1, 2, 3, 4)], out_dir=tmp_path / "x", progress=False)
