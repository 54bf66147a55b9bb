"""The annotation pipeline end to end on small simulated sessions, measured against the simulator's
exact truth: a multi-object scene with the truth's models (--models), a single-object scene with a
model built from its reconstruction, resume after finished and interrupted stages, and bad input.

Sizes: 240x180 images, 2 arm positions x 12 steps of 30 deg. At this size a depth pixel covers
~3 mm on the objects (4x the real rig's), so the thresholds here are looser than the targets the
benchmark measures at 640x480 (benchmarks/annotate_accuracy.py): measured here, the multi scene's
frame-to-frame motions are within ~0.05 deg / 0.3 mm (median), the surface distance ~0.3 mm
(median) and the visible-mask IoU ~0.985 (median).
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import trimesh

from tdof20.annotate.config import AnnotateConfig, load_annotate_config
from tdof20.annotate.label import LabelConfig
from tdof20.annotate.pipeline import annotate
from tdof20.annotate.stages import STAGES, parse_stages
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, read_scene, write_frame
from tdof20.sim.scenes import get_scene

STEPS, STEP_DEG, ARMS = 12, 30.0, 2
SIZE = dict(width=240, height=180)
CFG = AnnotateConfig(label=LabelConfig(workers=1))
BAD_RGB = (1, 5)      # a transparent colour PNG cut short after capture
ZERO_DEPTH = (0, 7)   # an opaque frame whose depth came back all zero


def _capture(path, scene, **kw):
    run_capture(sim_config(scene, steps=STEPS, step_deg=STEP_DEG, n_arms=ARMS, **(SIZE | kw)), path, yes=True,
                show_progress=False)
    return path


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    """multi/11 (whisky_cup_270, juice_cup_340, quartet_cup_80: a round, a tall and a 4-fold cup) with
    one corrupt colour PNG and one all-zero opaque depth, annotated in two runs: register..model,
    then the rest."""
    base = tmp_path_factory.mktemp("annotate")
    raw = _capture(base / "raw", "multi/11")
    s = RawSession.open(raw)
    p = raw / s.entry("transparent", *BAD_RGB).rgb
    p.write_bytes(p.read_bytes()[:200])
    a, k = ZERO_DEPTH
    write_frame(raw, s.info, "opaque", a, k, s.load_rgb("opaque", a, k),
                np.zeros((s.info.camera.height, s.info.camera.width), np.uint16))
    out = base / "scene"
    first = annotate(raw, out, models_dir=raw / "truth" / "models", stages="register..model", cfg=CFG, progress=False)
    state1 = read_json(out / "work" / "state.json")
    mtime = (out / "work" / "registration.json").stat().st_mtime_ns
    second = annotate(raw, out, models_dir=raw / "truth" / "models", cfg=CFG, progress=False)
    return {"raw": raw, "out": out, "first": first, "second": second, "state1": state1, "reg_mtime": mtime}


def test_multi_object_scene_matches_the_truth(multi):
    s = multi["second"]
    ev = s["evaluation"]["all"]
    assert ev["motion_rot_deg"]["median"] <= 0.15 and ev["motion_rot_deg"]["p95"] <= 0.5
    assert ev["motion_trans_mm"]["median"] <= 1.0 and ev["motion_trans_mm"]["p95"] <= 2.5
    assert ev["surface_mm"]["median"] <= 1.0 and ev["surface_mm"]["p95"] <= 2.0
    assert ev["iou_visib"]["median"] >= 0.95 and ev["iou_full"]["median"] >= 0.95
    for obj_id, e in s["evaluation"]["objects"].items():
        assert e["surface_mm"]["median"] <= 1.5, obj_id
        assert e["iou_visib"]["median"] >= 0.93, obj_id
    # one placement per object of session.json, each fitted well, upright on the table
    out = multi["out"]
    ids = sorted(p["obj_id"] for p in s["objects"])
    assert ids == sorted(RawSession.open(multi["raw"]).info.obj_ids) == sorted(get_scene("multi/11").obj_ids)
    for p in s["objects"]:
        assert p["fitness"] > 0.3 and p["score_mm"] < 2.5 and p["upright_correction_deg"] < 3.0
    # a BOP scene: its models are the user's files byte for byte, the QA report is there
    scene = read_scene(out)
    assert len(scene.im_ids()) == STEPS * ARMS - 2
    for o in ids:
        name = f"obj_{o:06d}.ply"
        assert (out / "models" / name).read_bytes() == (multi["raw"] / "truth" / "models" / name).read_bytes()
    assert (out / "qa" / "report.html").exists() and (out / "work" / "evaluation.json").exists()
    assert json.loads((out / "work" / "summary.json").read_text())["scene_id"] == "multi/11"
    for f in ("registration.json", "fits.json", "placements.json", "reconstruction/reconstruction.json",
              "reconstruction/scene_points.ply", "reconstruction/cluster_000.ply", "label.json"):
        assert (out / "work" / f).exists(), f


def test_every_label_carries_its_bounds_and_objects_stand_on_the_table(multi):
    """scene_gt_uncertainty.json: keyed like scene_gt.json, an entry per label in its order with
    its object's id, positive finite bounds that cover the truth's error for most labels and stay
    informative (median within 3x the median true error + 1 mm); the QA report's table; every
    upright object set down on the table (its lowest point on the plane)."""
    out, raw = multi["out"], multi["raw"]
    gt, tru = read_json(out / "scene_gt.json"), read_json(raw / "truth" / "scene_gt.json")
    unc = read_json(out / "scene_gt_uncertainty.json")
    info = read_json(out / "models" / "models_info.json")
    assert unc.keys() == gt.keys()
    err, bnd = [], []
    for k, entries in gt.items():
        assert [e["obj_id"] for e in unc[k]] == [e["obj_id"] for e in entries]
        for e, b in zip(entries, unc[k]):
            assert set(b) == {"obj_id", "rot_deg", "trans_mm", "surface_mm"}
            assert all(np.isfinite(b[q]) and b[q] > 0 for q in ("rot_deg", "trans_mm", "surface_mm"))
            t = next(x for x in tru[k] if x["obj_id"] == e["obj_id"])
            mi = info[str(e["obj_id"])]
            c = np.array([mi[f"min_{a}"] + mi[f"size_{a}"] / 2 for a in "xyz"])
            pl, pt = (np.reshape(x["cam_R_m2c"], (3, 3)) @ c + np.reshape(x["cam_t_m2c"], 3) for x in (e, t))
            err.append(float(np.linalg.norm(pl - pt)))
            bnd.append(b["trans_mm"])
    err, bnd = np.array(err), np.array(bnd)
    assert np.mean(err <= bnd) >= 0.9, (np.median(err), np.median(bnd))
    assert np.median(bnd) <= 3 * np.median(err) + 1.0
    qa = read_json(out / "qa" / "qa.json")["label_bounds"]
    assert sorted(int(o) for o in qa) == sorted({e["obj_id"] for v in gt.values() for e in v})
    assert "Label error bounds (95 %)" in (out / "qa" / "report.html").read_text()
    # set down onto the table: each upright placement's lowest model point on the plane
    from tdof20.formats.bop_models import model_path, read_model_mesh

    pl = read_json(out / "work" / "placements.json")
    n, d = np.asarray(pl["plane"][:3]), pl["plane"][3]
    for p in pl["placements"]:
        assert p["contact_mm"] is not None
        V, _ = read_model_mesh(model_path(out / "models", p["obj_id"]))
        T = np.reshape(p["T_ref_model"], (4, 4))
        assert abs(float(np.min((V @ T[:3, :3].T + T[:3, 3]) @ n + d)) / np.linalg.norm(n)) < 0.01


def test_a_rerun_resumes_after_the_finished_stages(multi):
    first, second = multi["first"], multi["second"]
    assert [first["stages"][st]["status"] for st in STAGES] == ["ran"] * 3 + ["not requested"] * 3
    assert [second["stages"][st]["status"] for st in STAGES] == ["up to date"] * 3 + ["ran"] * 3
    state = read_json(multi["out"] / "work" / "state.json")
    for st in ("register", "reconstruct", "model"):
        assert state["stages"][st] == multi["state1"]["stages"][st]
    assert (multi["out"] / "work" / "registration.json").stat().st_mtime_ns == multi["reg_mtime"]
    assert all(state["stages"][st]["seconds"] > 0 for st in STAGES)
    # nothing left to do
    third = annotate(multi["raw"], multi["out"], models_dir=multi["raw"] / "truth" / "models", cfg=CFG,
                     progress=False)
    assert {third["stages"][st]["status"] for st in STAGES} == {"up to date"}
    # a changed label option reruns label and qa only
    cfg = dataclasses.replace(CFG, qa=dataclasses.replace(CFG.qa, sample=4))
    fourth = annotate(multi["raw"], multi["out"], models_dir=multi["raw"] / "truth" / "models", cfg=cfg,
                      progress=False)
    assert [fourth["stages"][st]["status"] for st in STAGES] == ["up to date"] * 5 + ["ran"]


def test_bad_frames_are_listed_and_skipped_never_labelled(multi):
    s = multi["second"]
    skipped = {(e["arm"], e["step"]): e["reason"] for e in s["label"]["skipped"]}
    assert set(skipped) == {BAD_RGB, ZERO_DEPTH}
    assert "checksum" in skipped[BAD_RGB] or "PNG" in skipped[BAD_RGB]
    assert {(f["arm"], f["step"]) for f in s["registration"]["flagged"]} == {ZERO_DEPTH}
    assert s["label"]["labelled"] == STEPS * ARMS - 2
    scene = read_scene(multi["out"])
    for a, k in (BAD_RGB, ZERO_DEPTH):
        im = a * STEPS + k
        assert im not in scene.gt and not (multi["out"] / "rgb" / f"{im:06d}.png").exists()
    qa = {(f["arm"], f["step"]) for f in read_json(multi["out"] / "qa" / "qa.json")["flagged"]}
    assert ZERO_DEPTH in qa
    # the report lists the corrupt frame, or (its colour image unreadable) the summary says why not
    assert BAD_RGB in qa or any(f"arm {BAD_RGB[0]} step {BAD_RGB[1]} not drawn" in p for p in s["problems"])


def test_an_interrupted_label_stage_resumes_without_redoing_the_others(multi, tmp_path, monkeypatch):
    from tdof20.annotate import label as label_mod

    out = tmp_path / "scene"
    shutil.copytree(multi["out"], out)
    for sub in ("rgb", "depth", "depth_opaque", "depth_restored", "mask", "mask_visib"):
        shutil.rmtree(out / sub)
    for f in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        (out / f).unlink()
    before = read_json(out / "work" / "state.json")["stages"]
    real = label_mod._LabelJob.__call__
    calls = []

    def dies_on_the_third_chunk(self, chunk):
        calls.append(len(chunk))
        if len(calls) == 3:
            raise RuntimeError("power cut")
        return real(self, chunk)

    monkeypatch.setattr(label_mod._LabelJob, "__call__", dies_on_the_third_chunk)
    cfg = dataclasses.replace(CFG, label=dataclasses.replace(CFG.label, chunk=4))
    models = multi["raw"] / "truth" / "models"
    with pytest.raises(RuntimeError, match="power cut"):
        annotate(multi["raw"], out, models_dir=models, cfg=cfg, progress=False)
    state = read_json(out / "work" / "state.json")["stages"]
    assert "finished" not in state["label"]
    monkeypatch.setattr(label_mod._LabelJob, "__call__", real)
    s = annotate(multi["raw"], out, models_dir=models, cfg=cfg, progress=False)
    assert [s["stages"][st]["status"] for st in STAGES] == ["up to date"] * 4 + ["ran"] * 2
    after = read_json(out / "work" / "state.json")["stages"]
    for st in ("register", "reconstruct", "model", "place"):
        assert after[st] == before[st]
    assert s["label"]["already_done"] == 8 and s["label"]["labelled"] == STEPS * ARMS - 2 - 8
    # the resumed labels are the uninterrupted run's labels
    a, b = read_scene(out), read_scene(multi["out"])
    assert a.im_ids() == b.im_ids()
    for im in a.im_ids():
        for g in range(len(a.gt[im])):
            assert np.allclose(a.pose(im, g)[1], b.pose(im, g)[1])
            assert np.array_equal(a.mask(im, g, visib=True), b.mask(im, g, visib=True))


def test_models_in_metres_are_refused_naming_the_file(multi, tmp_path):
    out = tmp_path / "scene"
    shutil.copytree(multi["out"], out)
    metres = tmp_path / "models_m"
    shutil.copytree(multi["raw"] / "truth" / "models", metres)
    for ply in metres.glob("obj_*.ply"):
        m = trimesh.load(ply, process=False)
        m.apply_scale(0.001)
        m.export(ply)
    with pytest.raises(TdofError, match=r"obj_0000\d\d\.ply|models_info\.json") as e:
        annotate(multi["raw"], out, models_dir=metres, stages=["model"], cfg=CFG, progress=False)
    assert "metre" in str(e.value) and "\n" not in str(e.value)


def test_a_stage_without_its_inputs_says_which_stage_to_run_first(multi, tmp_path):
    with pytest.raises(TdofError, match="run stage 'register' first"):
        annotate(multi["raw"], tmp_path / "fresh", stages=["label"], cfg=CFG, progress=False)
    with pytest.raises(TdofError, match="not empty"):
        annotate(multi["raw"], multi["raw"] / "truth", cfg=CFG, progress=False)


def test_single_object_scene_builds_a_watertight_model(tmp_path):
    raw = _capture(tmp_path / "raw", "single/juice_cup_350")  # a tapered tumbler, 2.5 mm glass walls
    s = annotate(raw, tmp_path / "scene", cfg=CFG, progress=False)
    assert [p["source"] for p in s["objects"]] == ["built"]
    mesh = trimesh.load(tmp_path / "scene" / "models" / "obj_000013.ply", process=False)
    assert mesh.is_watertight
    ev = s["evaluation"]["all"]
    # a built model of a hollow tumbler (2.5 mm walls, built with the TSDF's normals): measured
    # 0.55 mm here (visible IoU 0.977, motion 0.13 deg / 0.33 mm); the former catalog's jar 0.65 mm
    assert ev["surface_mm"]["median"] <= 1.2
    assert ev["iou_visib"]["median"] >= 0.9
    assert ev["motion_rot_deg"]["median"] <= 0.2 and ev["motion_trans_mm"]["median"] <= 1.0


def test_a_session_without_its_opaque_phase_is_refused(tmp_path):
    raw = tmp_path / "raw"
    run_capture(sim_config("single/01", steps=2, step_deg=30.0, n_arms=1, width=160, height=120,
                           phases=("transparent",)), raw, yes=True, show_progress=False)
    with pytest.raises(TdofError, match="opaque") as e:
        annotate(raw, tmp_path / "scene", cfg=CFG, progress=False)
    assert "session.json" in str(e.value)
    assert read_json(tmp_path / "scene" / "work" / "summary.json")["stages"]["register"]["status"] == "failed"


def test_all_zero_opaque_depth_is_a_clear_error(tmp_path):
    raw = tmp_path / "raw"
    run_capture(sim_config("single/01", steps=3, step_deg=30.0, n_arms=1, width=160, height=120), raw, yes=True,
                show_progress=False)
    s = RawSession.open(raw)
    for k in range(3):
        write_frame(raw, s.info, "opaque", 0, k, s.load_rgb("opaque", 0, k), np.zeros((120, 160), np.uint16))
    with pytest.raises(TdofError, match=r"session\.json: holds no depth at all .*sampled opaque frames: arm 0 step 0"):
        annotate(raw, tmp_path / "scene", cfg=CFG, progress=False)
    assert not (tmp_path / "scene" / "scene_gt.json").exists()


def test_config_from_toml_is_strict(tmp_path):
    p = tmp_path / "annotate.toml"
    p.write_text('fuse_max_frames = 60\n[label]\nmethod = "far_to_near"\nworkers = 2\n'
                 '[place]\nupright = false\nmatch_icp_mm = [6, 3]\n[register]\ncrop_radius_mm = 200\n'
                 '[fit]\nicp_mm = [6.0, 3.0]\n')
    cfg = load_annotate_config(p)
    assert cfg.fuse_max_frames == 60 and cfg.label.method == "far_to_near" and cfg.label.workers == 2
    assert cfg.place.upright is False and cfg.place.match_icp_mm == (6.0, 3.0)
    assert cfg.register.crop_radius_mm == 200.0 and cfg.fit.icp_mm == (6.0, 3.0)
    for text, what in (('[label]\nmethdo = "raycast"\n', "label.methdo"), ("[qa]\nsample = 'x'\n", "qa.sample"),
                       ("colour = 1\n", "colour"), ('[label]\nmethod = "paint"\n', "method"),
                       ("[build\n", "malformed")):
        p.write_text(text)
        with pytest.raises(TdofError, match=what) as e:
            load_annotate_config(p)
        assert str(p) in str(e.value)
    assert cfg.with_label_options(executor="ray", ray_address="auto").label.executor == "ray"


def test_parse_stages():
    assert parse_stages(None) == STAGES
    assert parse_stages("register..model") == ("register", "reconstruct", "model")
    assert parse_stages(["qa", "label"]) == ("label", "qa")
    assert parse_stages("place..") == ("place", "label", "qa")
    for bad in ("labels", "qa..register", ""):
        with pytest.raises(TdofError):
            parse_stages(bad)
