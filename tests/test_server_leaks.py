"""The benchmark server's two leaks (issue 32, parts 1-2), tried as an attacker would.

1. The public release: a rig dataset like the real one (objects static on the turntable, the camera
   at 2 arm positions x 20 steps, extrinsics in every scene_camera.json) is published; every chain
   that rebuilds a test pose from PUBLIC is tried (the extrinsics chain, the rig's repeated arm
   positions and steps, the turntable motion of the train poses). The extrinsics chain rebuilds
   every test pose from ROOT (what the old release held) and nothing from PUBLIC; on the hard
   protocol (test scenes with no labelled image) every chain misses by far more than the ADD
   threshold, and a results file built from PUBLIC scores 0 where the old release's scored 100 %;
   on the simple protocol (test arcs of labelled scenes) the turntable chain still works, which is
   what publish.json says ("test labels derivable from public images": true).
2. The scores: the probe attack (one estimate of one target, all others left empty, perturbed
   across submissions) through the server's real path (API upload, worker, scorer, API read).
   From the stored full result it recovers the target's error and its position exactly; from what
   the server shows, nothing (every recovered error is off by more than 50 mm).
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from functools import lru_cache

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation
from sqlalchemy import select

from tdof20.dataset.build import write_splits
from tdof20.dataset.results import format_results_csv
from tdof20.formats import BopSceneWriter, read_json, write_json
from tdof20.objects import export_models, get_object
from tdof20.server.db import submissions
from tdof20.server.disclosure import K, MIN_TARGETS, disclose, step_for
from tdof20.server.figures import SHOWN_FIGURE, shown_figures
from tdof20.server.publish import CAMERA_FIELDS, DERIVABLE, publish
from tdof20.server.worker import run_worker
from tests.test_server_support import Server

KM = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
N_ARMS, STEPS, STEP_DEG = 2, 20, 18.0
SCENES = {7: ("single/handle_cup_280", (7,)), 21: ("multi/00", (1, 7, 17)), 23: ("multi/02", (1, 7, 17))}


def _T(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rig(arm: int, step: int) -> np.ndarray:
    """T_w2c of arm position ``arm`` at turntable step ``step`` (world = the turntable's frame): the
    same in every scene, as a rig's is."""
    elev = np.deg2rad(35.0 + 20.0 * arm)
    look = Rotation.from_euler("x", np.pi / 2 + elev).as_matrix()  # camera looking down at the table
    T_arm = _T(look, np.array([0.0, 0.0, 700.0]))
    return T_arm @ _T(Rotation.from_euler("z", np.deg2rad(STEP_DEG * step)).as_matrix(), np.zeros(3))


def _png_with_text(img: np.ndarray) -> bytes:
    """A real PNG (PIL) with a tEXt chunk and a tIME chunk, as a camera tool would write."""
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    data = buf.getvalue()

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    return data[:33] + chunk(b"tEXt", b"Creation Time\x002026-01-02 03:04:05") + \
        chunk(b"tIME", bytes([7, 234, 1, 2, 3, 4, 5])) + data[33:]


def build_rig_dataset(root) -> dict:
    """A tdof20-layout dataset of three scenes on one rig; returns {(scene, im, obj): T_m2c}."""
    export_models(root / "models", (1, 7, 17))
    rng = np.random.default_rng(32)
    truth = {}
    for sid, (_, objs) in SCENES.items():
        placed = {o: _T(Rotation.random(random_state=int(rng.integers(2**31))).as_matrix(),
                        np.array([*rng.uniform(-90, 90, 2), 0.0])) for o in objs}  # on the table, static
        with BopSceneWriter(root / "scenes" / f"{sid:06d}") as w:
            for arm in range(N_ARMS):
                for step in range(STEPS):
                    im = arm * STEPS + step
                    T_w2c = _rig(arm, step)
                    poses = []
                    for o in objs:
                        T = T_w2c @ placed[o]
                        poses.append((o, T[:3, :3], T[:3, 3]))
                        truth[(sid, im, o)] = T
                    mask = np.zeros((4, 6), bool)
                    mask[1:3, (im % 4):(im % 4) + 2] = True
                    w.add_frame(im, KM, 1.0, poses, [mask] * len(objs), [mask] * len(objs),
                                rgb=np.full((4, 6, 3), im % 250, np.uint8), depth=np.full((4, 6), 700, np.uint16),
                                T_w2c=T_w2c, extra={"depth_restored": np.full((4, 6), 690, np.uint16)})
    info = {"name": "tdof20", "format": "bop", "scenes": {str(s): n for s, (n, _) in SCENES.items()},
            "layout": {str(s): {"n_arms": N_ARMS, "steps": STEPS} for s in SCENES}}
    write_json(root / "dataset_info.json", info)
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_splits(root, info)  # the real build's splits and targets (simple: arcs of scene 7; hard: scene 23)
    (root / "scenes" / "000007" / "scene_info.json").write_text('{"scene_id": "single/handle_cup_280", "step_deg": 18}')
    (root / "shards").mkdir()
    (root / "shards" / "hard_test.h5").write_bytes(b"packed labels")
    rgb = root / "scenes" / "000007" / "rgb" / "000001.png"  # a test image written by a tool with metadata
    rgb.write_bytes(_png_with_text(np.full((4, 6, 3), 1, np.uint8)))
    os.utime(rgb, (1e9, 1e9))
    return truth


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    root = tmp_path_factory.mktemp("rig")
    truth = build_rig_dataset(root)
    public = tmp_path_factory.mktemp("pub") / "public"
    return root, truth, public, publish(root, public)


def _cams(root, sid) -> dict[int, dict]:
    return {int(k): v for k, v in read_json(root / "scenes" / f"{sid:06d}" / "scene_camera.json").items()}


def _gts(root, sid) -> dict[tuple[int, int], np.ndarray]:
    out = {}
    for im, gts in read_json(root / "scenes" / f"{sid:06d}" / "scene_gt.json").items():
        for g in gts:
            out[(int(im), g["obj_id"])] = _T(np.reshape(g["cam_R_m2c"], (3, 3)), g["cam_t_m2c"])
    return out


def _w2c(cam: dict) -> np.ndarray | None:
    if "cam_R_w2c" not in cam:
        return None
    return _T(np.reshape(cam["cam_R_w2c"], (3, 3)), cam["cam_t_w2c"])


@lru_cache(maxsize=8)
def _points(models: str, obj: int) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.load(f"{models}/obj_{obj:06d}.ply").vertices)


def _add_mm(models, obj: int, T: np.ndarray, T_gt: np.ndarray) -> float:
    """ADD (mm): the mean distance between the model's points at the two poses."""
    pts = _points(str(models), obj)
    return float(np.linalg.norm((pts @ T[:3, :3].T + T[:3, 3]) - (pts @ T_gt[:3, :3].T + T_gt[:3, 3]), axis=1).mean())


def _test_images(root, split) -> list[tuple[int, int]]:
    return [(int(s), int(i)) for s, ims in read_json(root / "splits" / f"{split}_test.json").items() for i in ims]


def _extrinsics_chain(release, split) -> dict:
    """T_w2c(test) T_w2c(train)^-1 T_m2c(train), the train image from the same scene where the
    release has one with a label, else (the rig repeats itself) from any scene at the same arm
    position and step with a label: {(scene, im, obj): T} for what the release lets it compute."""
    out = {}
    labelled = {s: _gts(release, s) for s in SCENES}
    cams = {s: _cams(release, s) for s in SCENES}
    for s, im in _test_images(release, split):
        T_test = _w2c(cams[s][im])
        if T_test is None:  # not published: the same arm position and step in another scene instead
            T_test = next((_w2c(cams[o][im]) for o in SCENES if o != s and _w2c(cams[o].get(im, {})) is not None),
                          None)
        for obj in SCENES[s][1]:
            src = [(o, j) for o in ([s] + [x for x in SCENES if x != s]) for (j, ob) in labelled[o] if ob == obj
                   and _w2c(cams[o][j]) is not None]
            if T_test is None or not src:
                continue
            o, j = src[0]
            out[(s, im, obj)] = T_test @ np.linalg.inv(_w2c(cams[o][j])) @ labelled[o][(j, obj)]
    return out


def _turntable_chain(release, split) -> dict:
    """No extrinsics at all: a labelled image's pose turned by the turntable steps between it and
    the test image (the same arm position of the same scene; im_id = arm * steps + step): the
    motion of one turntable step is T(k)^-1 T(k+1) between two labelled neighbours."""
    out = {}
    info = read_json(release / "dataset_info.json")["layout"]
    for s, im in _test_images(release, split):
        steps = info[str(s)]["steps"]
        arm, step = divmod(im, steps)
        gts = _gts(release, s)
        for obj in SCENES[s][1]:
            ks = sorted(j % steps for (j, ob) in gts if ob == obj and j // steps == arm)
            pair = next(((k, k + 1) for k in ks if k + 1 in ks), None)
            if pair is None:
                continue  # no labelled image of this scene: nothing to turn
            T0, T1 = gts[(arm * steps + pair[0], obj)], gts[(arm * steps + pair[1], obj)]
            M = np.linalg.inv(T0) @ T1
            out[(s, im, obj)] = T0 @ np.linalg.matrix_power(M if step >= pair[0] else np.linalg.inv(M),
                                                            abs(step - pair[0]))
    return out


def _errors(root, chain: dict, truth: dict) -> dict:
    return {k: _add_mm(root / "models", k[2], T, truth[k]) for k, T in chain.items()}


def test_publish_hides_test_extrinsics_and_says_what_it_dropped(rig):
    root, truth, public, info = rig
    hidden = {(s, i) for split in ("simple", "hard") for s, i in _test_images(root, split)}
    assert len(hidden) == 6 + 40 and info["hidden_test_images"] == 46
    for s in SCENES:
        src, dst = _cams(root, s), _cams(public, s)
        for im, cam in src.items():
            assert "cam_R_w2c" in cam
            if (s, im) in hidden:
                assert set(dst[im]) == set(CAMERA_FIELDS) and dst[im]["cam_K"] == cam["cam_K"]
            else:
                assert dst[im] == cam  # a train image keeps its extrinsics
    # no hidden pose appears in any public JSON file (a hidden image's extrinsics do: the rig
    # repeats its arm positions and steps, so another scene's image at the same ones has them;
    # they place the camera, not the objects: test_no_chain_rebuilds_a_hidden_hard_pose_from_public)
    secret = set()
    for s, im in hidden:
        for g in read_json(root / "scenes" / f"{s:06d}" / "scene_gt.json")[str(im)]:
            secret |= {json.dumps(g["cam_t_m2c"]), json.dumps(g["cam_R_m2c"])}
    for f in public.rglob("*.json"):
        text = json.dumps(read_json(f))
        assert not any(x in text for x in secret), f
    # left out: the scene's rig registration, the packed shard; images without their metadata or times
    assert "shards/" in info["not_published"] and "scene_info.json" in info["not_published"]
    assert not (public / "shards").exists() and not (public / "scenes" / "000007" / "scene_info.json").exists()
    src_png, pub_png = (d / "scenes" / "000007" / "rgb" / "000001.png" for d in (root, public))
    assert b"tEXt" in src_png.read_bytes() and b"tEXt" not in pub_png.read_bytes() and b"tIME" not in pub_png.read_bytes()
    assert np.array_equal(np.asarray(Image.open(src_png)), np.asarray(Image.open(pub_png)))
    assert pub_png.stat().st_mtime > 1e9 + 86400
    # the rule is written down, per protocol whether its test labels can still be derived
    written = read_json(public / "publish.json")
    assert written["rule"]["dropped for test images"] and written["splits"] == info["splits"]
    assert info["splits"]["simple"][DERIVABLE] is True and "static scene" in info["splits"]["simple"]["why"]
    assert info["splits"]["hard"][DERIVABLE] is False


def test_no_chain_rebuilds_a_hidden_hard_pose_from_public(rig):
    """Every chain on PUBLIC misses every hard test pose by far more than the ADD threshold; the
    extrinsics chain on ROOT (the old release) rebuilt them all exactly."""
    root, truth, public, _ = rig
    before = _errors(root, _extrinsics_chain(root, "hard"), truth)
    assert len(before) == 40 * 3 and max(before.values()) < 1e-6  # the old leak, exactly
    thr = {o: 0.1 * get_object(o).diameter for o in (1, 7, 17)}
    after = {**_errors(root, _extrinsics_chain(public, "hard"), truth)}
    turned = _errors(root, _turntable_chain(public, "hard"), truth)
    assert len(after) == 120 and not turned  # the rig's other scenes chain; the turntable has nothing to turn
    ratio = min(e / thr[k[2]] for k, e in after.items())
    assert ratio > 5, ratio  # the nearest a public chain gets: > 5x the threshold (measured: printed)
    print(f"hard: extrinsics chain on ROOT max {max(before.values()):.1e} mm; on PUBLIC min "
          f"{min(after.values()):.0f} mm = {ratio:.1f}x the ADD threshold")


def test_simple_is_derivable_as_publish_json_says(rig):
    """simple's test arcs lie in labelled scenes: its own extrinsics are gone, and still the rig's
    repeated extrinsics and the turntable chain rebuild them (what publish.json states): nothing
    left out of a release can hide them."""
    root, truth, public, info = rig
    assert max(_errors(root, _extrinsics_chain(root, "simple"), truth).values()) < 1e-6
    # the rig repeats its arm positions and steps: another scene's image at the same ones has the
    # test image's extrinsics, and its own scene's train labels do the rest
    via_other_scenes = _errors(root, _extrinsics_chain(public, "simple"), truth)
    assert len(via_other_scenes) == 6 and max(via_other_scenes.values()) < 1e-6
    turned = _errors(root, _turntable_chain(public, "simple"), truth)
    assert len(turned) == 6 and max(turned.values()) < 1e-6
    assert info["splits"]["simple"][DERIVABLE] is True


def test_a_results_file_from_public_no_longer_scores(rig, tmp_path):
    """Through the server: a file from the old release's extrinsics chain scores 100 % ADD(S) (the
    worker's stored result), one from PUBLIC's best chain 0 %."""
    root, truth, public, _ = rig
    server = Server(root, tmp_path / "data")
    uids = []
    for release in (root, public):
        chain = _extrinsics_chain(release, "hard")
        rows = [(s, im, o, 1.0, T[:3, :3], T[:3, 3], 0.02) for (s, im, o), T in sorted(chain.items())]
        r = server.submit("alice", format_results_csv(rows).encode(), split="hard", method="chain")
        assert r.status_code == 201, r.text
        uids.append(r.json()["uid"])
    assert run_worker(server.cfg, once=True) == 2
    with server.engine.begin() as c:
        stored = {u: json.loads(res) for u, res in c.execute(select(submissions.c.uid, submissions.c.result))}
    old, new = (stored[u]["summary"]["mean"]["add_s"] for u in uids)
    assert old == 1.0 and new == 0.0
    # the leaderboard of the protocol whose test labels cannot be hidden says so
    assert 'id="derivable"' in server.client.get("/", params={"split": "simple"}).text
    assert 'id="derivable"' not in server.client.get("/", params={"split": "hard"}).text
    print(f"ADD(S) of a results file from the release: old release {100 * old:.0f} %, PUBLIC {100 * new:.0f} %")


# ---------------------------------------------------------------------------------------- part 2
N_PROBE = 200  # targets of the probe dataset's one object: the smallest cell the rule shows
PROBE_SCENE = 23


def build_probe_dataset(root) -> dict:
    """One hard test scene of N_PROBE images of object 7 (asymmetric: ADD(S) = ADD) and a train scene."""
    export_models(root / "models", (7,))
    rng = np.random.default_rng(5)
    truth = {}
    for sid, n in ((21, 2), (PROBE_SCENE, N_PROBE)):
        with BopSceneWriter(root / "scenes" / f"{sid:06d}") as w:
            for im in range(n):
                R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
                t = np.array([rng.uniform(-50, 50), rng.uniform(-40, 40), rng.uniform(600, 800)])
                mask = np.zeros((4, 6), bool)
                mask[1:3, 1:4] = True
                w.add_frame(im, KM, 1.0, [(7, R, t)], [mask], [mask], rgb=np.full((4, 6, 3), 9, np.uint8),
                            depth=np.full((4, 6), 700, np.uint16))
                truth[(sid, im)] = (R, t)
    info = {"name": "tdof20", "format": "bop", "scenes": {"21": "multi/00", str(PROBE_SCENE): "multi/02"},
            "layout": {"21": {"n_arms": 1, "steps": 2}, str(PROBE_SCENE): {"n_arms": 1, "steps": N_PROBE}}}
    write_json(root / "dataset_info.json", info)
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_splits(root, info)
    return truth


def test_the_probe_attack_recovers_nothing(tmp_path):
    """One estimate of one target (every other target without one), moved 20 mm along each axis and
    repeated, 6 submissions through the API and the worker. From the stored result the classic
    recovery e = 100 (1 - n auc) gives each probe's error and, by trilateration, the hidden position
    to 1e-3 mm; from what the API shows, every recovered error is off by > 50 mm, also when the
    repeats are averaged, and the position by more than twice the ADD threshold."""
    root = tmp_path / "ds"
    truth = build_probe_dataset(root)
    server = Server(root, tmp_path / "data", daily_limit=50)
    R, t = truth[(PROBE_SCENE, 17)]
    base = np.array([7.0, -11.0, 13.0])  # the attacker's first guess is this far off (unknown to it)
    moves = [np.zeros(3), np.array([20.0, 0, 0]), np.array([0, 20.0, 0]), np.array([0, 0, 20.0]),
             np.zeros(3), np.zeros(3)]
    uids = []
    for d in moves:
        csv = format_results_csv([(PROBE_SCENE, 17, 7, 1.0, R, t + base + d, 0.02)]).encode()
        r = server.submit("alice", csv, split="hard", method="probe")
        assert r.status_code == 201, r.text
        uids.append(r.json()["uid"])
    assert run_worker(server.cfg, once=True) == len(moves)
    true_e = [float(np.linalg.norm(base + d)) for d in moves]

    def recover(auc: list[float]) -> tuple[list[float], np.ndarray]:
        e = [100.0 * (1.0 - N_PROBE * a) for a in auc]
        b = np.array([(e[i] ** 2 - e[0] ** 2 - 400.0) / 40.0 for i in (1, 2, 3)])  # |b + d|^2 = e^2
        return e, b

    with server.engine.begin() as c:
        stored = {u: json.loads(res) for u, res in c.execute(select(submissions.c.uid, submissions.c.result))}
    e_old, b_old = recover([stored[u]["summary"]["objects"]["7"]["auc_add_s"] for u in uids])
    assert np.allclose(e_old, true_e, atol=1e-4) and np.allclose(b_old, base, atol=1e-3)  # the leak, as it was

    shown = [server.client.get(f"/api/submissions/{u}", headers=server.headers("alice")).json()["result"]
             for u in uids]
    cells = [s["summary"]["objects"]["7"] for s in shown]
    assert all(c["n"] == N_PROBE and c["step"] == step_for(N_PROBE) == 0.05 for c in cells)
    assert N_PROBE * cells[0]["step"] >= K and N_PROBE >= MIN_TARGETS
    e_new, b_new = recover([c["auc_add_s"] for c in cells])
    assert min(abs(a - b) for a, b in zip(e_new, true_e)) > 50, (e_new, true_e)
    # trilateration from the shown values lands where it lands whatever the hidden position is (all
    # shown 0: at (-10, -10, -10) mm from the estimate; an upper step: metres off), here > 2x the threshold
    assert np.linalg.norm(b_new - base) > 2 * 0.1 * get_object(7).diameter
    pooled = 100.0 * (1.0 - N_PROBE * float(np.mean([cells[i]["auc_add_s"] for i in (0, 4, 5)])))
    assert abs(pooled - true_e[0]) > 50  # averaging the repeats does not help either
    for s in shown:  # no cell anywhere is finer than its step; the tiny train scene's absence changes nothing
        for cell in [*s["summary"]["objects"].values(), *s["summary"]["scenes"].values(), s["summary"]["all"],
                     s["summary"]["mean"]]:
            for k, v in cell.items():
                if k not in ("n", "step", "withheld") and v is not None:
                    assert abs(v / cell["step"] - round(v / cell["step"])) < 1e-6
    # the results page's figure is drawn from the shown values alone: the same PNG from them in a fresh folder
    alice = server.sign_in("alice")
    page = alice.get(f"/s/{uids[0]}").text
    assert f"/s/{uids[0]}/plots/{SHOWN_FIGURE}" in page and "accuracy_add_s.png" not in page
    assert 'id="disclosure"' in page and "AUC ADD(S)" in page
    png = alice.get(f"/s/{uids[0]}/plots/{SHOWN_FIGURE}").content
    (tmp_path / "fresh").mkdir()
    assert shown_figures(tmp_path / "fresh", "probe", shown[0]) == [SHOWN_FIGURE]
    assert (tmp_path / "fresh" / SHOWN_FIGURE).read_bytes() == png
    print(f"probe: stored result recovers errors {np.round(e_old, 4).tolist()} mm (true "
          f"{np.round(true_e, 4).tolist()}), position off {np.linalg.norm(b_old - base):.1e} mm; shown result "
          f"recovers {np.round(e_new, 1).tolist()} mm, position off {np.linalg.norm(b_new - base):.0f} mm")


def test_the_rule_on_stored_results():
    """The pure rule: counts decide the step, small cells are withheld, the mean counts as N x its
    smallest object, exact 0 and 1 stay, the same uid shows the same values, validation is whole."""
    cell = lambda n, v: {"n": n, "add_s": v, "auc_add_s": v}  # noqa: E731
    stored = {"summary": {"objects": {"1": cell(5000, 0.12345), "2": cell(150, 0.5), "3": cell(1000, 1.0)},
                          "scenes": {"21": cell(6150, 0.3)}, "all": cell(6150, 0.3), "mean": cell(3, 0.54)},
              "warnings": [], "per_image": [{"im_id": 1}]}
    a = disclose(stored, "test", b"k" * 32, "u1")
    o = a["summary"]["objects"]
    assert o["1"]["step"] == 0.002 and abs(o["1"]["add_s"] - 0.12345) <= 0.002 and "per_image" not in a
    assert o["2"]["add_s"] is None and "fewer than 200" in o["2"]["withheld"]
    assert o["3"]["step"] == 0.01 and o["3"]["add_s"] == 1.0
    assert a["summary"]["mean"]["step"] == step_for(3 * 150) == 0.05
    assert disclose(stored, "test", b"k" * 32, "u1") == a
    assert disclose(stored, "val", b"k" * 32, "u1")["per_image"] == [{"im_id": 1}]
    # the dither is unbiased: over many submissions (uids) the shown value averages to the exact one
    vals = [disclose(stored, "test", b"k" * 32, f"u{i}")["summary"]["objects"]["1"]["add_s"] for i in range(4000)]
    assert set(np.round(np.array(vals) / 0.002).astype(int)) == {61, 62}
    assert abs(np.mean(vals) - 0.12345) < 1e-4
