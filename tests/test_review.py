"""The review tool (issue 25, parts 3-5): a simulated session whose one object's fit is broken on
purpose is refused for that object (a partial scene); through the app's own HTTP API a few nudges
and a snap place it, "relabel" labels it within the accuracy targets against the simulator's
truth, every correction is a journal entry (undoable, replayed by a resumed ``tdof20 annotate``),
and ``dataset build`` refuses the scene while flags are unresolved."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.corrections import append_entry, read_journal, replay, undo_target
from tdof20.annotate.label import LabelConfig
from tdof20.annotate.pipeline import annotate
from tdof20.annotate.state import sha_file
from tdof20.capture import run_capture, sim_config
from tdof20.dataset.build import build_dataset_in_layout, unresolved_flags
from tdof20.errors import TdofError
from tdof20.formats import read_json, write_json
from tdof20.geometry import rotation_matrix
from tdof20.review import make_app

CFG = AnnotateConfig(label=LabelConfig(workers=1))


def break_fit(scene: Path, index: int, shift_mm: float = 120.0, turn_deg: float = 60.0) -> None:
    """Move object ``index``'s matching fit (work/fits.json) ``shift_mm`` across the table and turn
    it ``turn_deg`` about the table normal — what a wrong cluster or a bad match leaves — and sign
    the model stage's result again (work/state.json), as if the model stage had made it."""
    fits_file = scene / "work" / "fits.json"
    fits = read_json(fits_file)
    plane = np.asarray(read_json(scene / "work" / "reconstruction" / "reconstruction.json")["plane"], float)
    up = plane[:3] / np.linalg.norm(plane[:3])
    across = np.cross(up, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    e = fits["objects"][index]
    T = np.asarray(e["T_ref_model"], float).reshape(4, 4)
    R = rotation_matrix(up, math.radians(turn_deg))
    c = T[:3, 3].copy()
    T[:3, :3] = R @ T[:3, :3]
    T[:3, 3] = c + shift_mm * across
    e["T_ref_model"] = [float(x) for x in T.ravel()]
    write_json(fits_file, fits)
    state = read_json(scene / "work" / "state.json")
    state["stages"]["model"]["outputs"] = {"fits.json": sha_file(fits_file)}
    write_json(scene / "work" / "state.json", state)


def true_pose(raw: Path, obj_id: int) -> np.ndarray:
    """The object's true pose in the reference camera (arm 0, step 0): truth/scene_gt.json's image 0."""
    e = next(e for e in read_json(raw / "truth" / "scene_gt.json")["0"] if int(e["obj_id"]) == obj_id)
    T = np.eye(4)
    T[:3, :3] = np.asarray(e["cam_R_m2c"], float).reshape(3, 3)
    T[:3, 3] = e["cam_t_m2c"]
    return T


def build_broken_scene(base: Path, corrupt_step: int | None = None) -> dict:
    """A simulated multi/08 session (1 arm x 12 steps of 30 deg, 160x120) annotated with the true
    models, one object's matching fit broken (:func:`break_fit`), so the place stage refuses it:
    a partial scene. ``corrupt_step``: that step's transparent colour image cut short too (the
    label stage skips it: a flagged frame)."""
    raw = base / "raw"
    run_capture(sim_config("multi/08", steps=12, step_deg=30.0, n_arms=1, width=160, height=120), raw, yes=True,
                show_progress=False)
    if corrupt_step is not None:
        png = raw / "transparent" / "arm0" / "rgb" / f"{corrupt_step:06d}.png"
        png.write_bytes(png.read_bytes()[:200])
    scene = base / "scene"
    models = raw / "truth" / "models"
    annotate(raw, scene, models_dir=models, stages="register..model", cfg=CFG, progress=False)
    index = 2
    break_fit(scene, index)
    s = annotate(raw, scene, models_dir=models, cfg=CFG, progress=False)
    obj_id = int(read_json(scene / "work" / "fits.json")["objects"][index]["obj_id"])
    return {"raw": raw, "scene": scene, "models": models, "index": index, "obj_id": obj_id, "summary": s,
            "base": base}


@pytest.fixture(scope="module")
def broken(tmp_path_factory):
    return build_broken_scene(tmp_path_factory.mktemp("review"))


def _post(client: TestClient, path: str, body: dict | None = None) -> dict:
    r = client.post(path, json=body or {})
    assert r.status_code == 200, r.text
    return r.json()


def test_a_broken_object_is_placed_by_nudges_and_a_snap_and_relabelled_within_the_targets(broken):
    raw, scene, index, obj_id = broken["raw"], broken["scene"], broken["index"], broken["obj_id"]
    s = broken["summary"]
    assert s["partial"] and [f["obj_id"] for f in s["failed_objects"]] == [obj_id]
    # dataset build refuses the scene while its flags are unresolved, names the object and says what to do
    assert any(f.get("obj_id") == obj_id for f in unresolved_flags(scene))
    with pytest.raises(TdofError, match=f"unresolved flag.*object {obj_id}.*--allow-flagged"):
        build_dataset_in_layout("tdof20", [scene], broken["base"] / "ds_refused", show_progress=False)
    assert not (broken["base"] / "ds_refused").exists()

    client = TestClient(make_app(scene))
    st = client.get("/api/state").json()
    ob = next(o for o in st["objects"] if o["index"] == index)
    assert ob["status"] == "failed" and "fits its cluster badly" in ob["reason"]
    assert "Objects not labelled" in client.get("/").text
    labelled_before = st["labelled"]

    # a person's nudges: turn about the table normal in 15 deg steps, then move in 10 mm steps
    T_table_ref = np.asarray(st["T_table_ref"], float).reshape(4, 4)
    truth = T_table_ref @ true_pose(raw, obj_id)
    cur = np.asarray(ob["T_table_model"], float).reshape(4, 4)
    dR = truth[:3, :3] @ cur[:3, :3].T
    yaw = math.degrees(math.atan2(dR[1, 0], dR[0, 0]))
    nudges = 0
    for _ in range(round(abs(yaw) / 15.0)):
        st = _post(client, f"/api/objects/{index}/nudge", {"axis": "rz", "amount": math.copysign(15.0, yaw)})["state"]
        nudges += 1
    cur = np.asarray(next(o for o in st["objects"] if o["index"] == index)["T_table_model"], float).reshape(4, 4)
    for step in (25.0, 5.0):        # coarse, then fine
        for k, axis in enumerate("xyz"):
            d = truth[k, 3] - cur[k, 3]
            for _ in range(round(abs(d) / step)):
                st = _post(client, f"/api/objects/{index}/nudge", {"axis": axis, "amount": math.copysign(step, d)})["state"]
                nudges += 1
            cur = np.asarray(next(o for o in st["objects"] if o["index"] == index)["T_table_model"], float).reshape(4, 4)
    assert 5 <= nudges <= 20
    cur = np.asarray(next(o for o in st["objects"] if o["index"] == index)["T_table_model"], float).reshape(4, 4)
    assert np.linalg.norm(cur[:3, 3] - truth[:3, 3]) < 6.0         # placed by hand to within a step
    ob = next(o for o in st["objects"] if o["index"] == index)
    assert ob["status"] == "corrected" and ob["pending"]

    # snap: the place stage's ICP from there
    snap = _post(client, f"/api/objects/{index}/snap")
    assert snap["entry"]["how"] == "snap" and snap["entry"]["detail"]["fitness"] >= 0.15
    T_snap = np.asarray(next(o for o in snap["state"]["objects"] if o["index"] == index)["T_table_model"]).reshape(4, 4)
    assert np.linalg.norm(T_snap[:3, 3] - truth[:3, 3]) < 3.0

    # a frame rejected by the reviewer is not labelled again, and is no unresolved flag
    _post(client, "/api/frames", {"arm": 0, "steps": [5], "verdict": "reject"})

    r = client.post("/api/relabel", json={})
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["partial"] is False and res["unresolved_flags"] == []
    ev = read_json(scene / "work" / "evaluation.json")
    assert ev["objects"][str(obj_id)]["surface_mm"]["median"] <= 1.0          # the corrected object
    assert ev["all"]["surface_mm"]["median"] <= 1.0 and ev["wrong_labels"] == []
    gt = read_json(scene / "scene_gt.json")
    assert "5" not in gt or not gt["5"]                                   # rejected
    with_obj = [im for im, v in gt.items() if any(int(e["obj_id"]) == obj_id for e in v)]
    assert len(with_obj) >= 9 and res["labelled"] >= labelled_before - 1
    pl = read_json(scene / "work" / "placements.json")
    assert pl["failed"] == [] and any(p["index"] == index and p.get("corrected") == "snap" for p in pl["placements"])
    assert unresolved_flags(scene) == []

    # the journal: one entry per correction, in order, with a time; nothing written twice
    entries = read_journal(scene / "work")
    ops = [e["op"] for e in entries]
    assert ops == ["place"] * nudges + ["place", "frames", "relabel"]
    assert [e["id"] for e in entries] == list(range(1, len(entries) + 1)) and all(e["t"] for e in entries)

    # resume: tdof20 annotate honours the journal (everything up to date; forced, the same labels)
    s2 = annotate(raw, scene, models_dir=broken["models"], cfg=CFG, progress=False)
    assert {v["status"] for v in s2["stages"].values()} == {"up to date"}
    gt_before = (scene / "scene_gt.json").read_bytes()
    s3 = annotate(raw, scene, models_dir=broken["models"], stages="place..qa", force=True, cfg=CFG, progress=False)
    assert not s3.get("partial") and (scene / "scene_gt.json").read_bytes() == gt_before

    # undo takes back the frame verdict; replayed, the frame is labelled again after a relabel
    u = _post(client, "/api/undo")
    assert u["entry"]["undoes"] == next(e["id"] for e in entries if e["op"] == "frames")
    assert _post(client, "/api/relabel")["labelled"] == res["labelled"] + 1

    # with no flag left, the dataset builds without being told
    stats = build_dataset_in_layout("tdof20", [scene], broken["base"] / "ds", show_progress=False)
    assert stats


def test_the_pages_show_the_scene(broken):
    client = TestClient(make_app(broken["scene"]))
    index = client.get("/")
    assert index.status_code == 200 and 'id="grid"' in index.text and broken["summary"]["scene_id"] in index.text
    frame = client.get("/frame/0/3")
    assert frame.status_code == 200 and "/img/frame/0/3/opaque.png" in frame.text
    for url in ("/img/frame/0/3/rgb.png", "/img/frame/0/3/opaque.png", f"/img/object/{broken['index']}.png"):
        r = client.get(url)
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert "three.module.min.js" in client.get("/place").text
    assert client.get("/static/three.module.min.js").status_code == 200
    assert client.get("/static/three.LICENSE").text.startswith("The MIT License")
    pts = client.get("/api/scene3d").json()
    assert len(pts["points"]) == 3 * len(pts["cluster"]) and pts["clusters"] >= 4
    # refusals are one line; a POST that is not JSON is refused (no cross-site form posts)
    assert client.post("/api/undo", content="{}", headers={"content-type": "text/plain"}).status_code == 415
    r = client.post(f"/api/objects/{broken['index']}/nudge", json={"axis": "w", "amount": 1})
    assert r.status_code == 400 and "axis" in r.json()["detail"]
    assert client.post("/api/objects/99/snap", json={}).status_code == 400
    assert client.get("/qa/../work/state.json").status_code == 404
    # a drag: the pose given in the table frame comes back as given, and is one entry; undo takes it back
    ob = next(o for o in client.get("/api/state").json()["objects"] if o["index"] == 0)
    T = np.asarray(ob["T_table_model"]).reshape(4, 4)
    T[:3, 3] += [3.0, -2.0, 0.0]
    moved = _post(client, "/api/objects/0/pose", {"T_table_model": T.ravel().tolist()})
    assert moved["entry"]["how"] == "drag"
    got = next(o for o in moved["state"]["objects"] if o["index"] == 0)
    assert np.allclose(got["T_table_model"], T.ravel(), atol=1e-6) and got["pending"]
    back = _post(client, "/api/undo")["state"]
    assert np.allclose(next(o for o in back["objects"] if o["index"] == 0)["T_table_model"], ob["T_table_model"])
    bad = T.copy()
    bad[0, 0] = 2.0
    assert client.post("/api/objects/0/pose", json={"T_table_model": bad.ravel().tolist()}).status_code == 400
    assert client.get("/frame/0/99").status_code == 400


def test_the_journal_is_append_only_and_survives_a_torn_line(tmp_path):
    work = tmp_path / "work"
    T = [1.0, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1]
    a = append_entry(work, {"op": "place", "object": 0, "obj_id": 5, "T_ref_model": T, "how": "nudge"})
    append_entry(work, {"op": "frames", "arm": 0, "steps": None, "verdict": "reject"})
    append_entry(work, {"op": "frames", "arm": 0, "steps": [2], "verdict": "accept"})
    c = replay(read_journal(work))
    assert c.placed[0]["T_ref_model"] == T and c.verdict(0, 1) == "reject" and c.verdict(0, 2) == "accept"
    assert c.skip([(0, 2, "registration: residual")], 1, 3) == [(0, 0, "rejected by the reviewer (corrections.jsonl)"),
                                                               (0, 1, "rejected by the reviewer (corrections.jsonl)")]
    u = append_entry(work, {"op": "undo", "undoes": undo_target(read_journal(work))["id"]})
    assert u["undoes"] == 3 and replay(read_journal(work)).verdict(0, 2) == "reject"
    # a write cut short leaves a torn last line: left out, and the next entry is whole after it
    path = work / "corrections.jsonl"
    with open(path, "ab") as f:
        f.write(b'{"op": "place", "obj')
    assert len(read_journal(work)) == 4
    e = append_entry(work, {"op": "relabel"})
    assert e["id"] == 5 and [x["id"] for x in read_journal(work)][-1] == 5
    # a damaged line before the last is an error naming the file and the line
    lines = path.read_bytes().split(b"\n")
    lines[1] = b"not json"
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(TdofError, match="corrections.jsonl.*line 2"):
        read_journal(work)
    with pytest.raises(TdofError, match="not a rigid pose"):
        append_entry(tmp_path / "w2", {"op": "place", "object": 0, "obj_id": 5, "how": "drag",
                                       "T_ref_model": [2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]})
    assert a["id"] == 1 and json.loads(path.read_bytes().split(b"\n")[0])["op"] == "place"
