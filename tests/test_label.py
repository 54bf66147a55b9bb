"""The label stage against the simulator's exact truth: poses, masks, restored depth, gt_info and
the BOP layout; resume after an interruption; skipped, missing and corrupt frames; the paper's
far-to-near labels compared; 2 local workers and a Ray cluster give the same bytes as 1 worker."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from tdof20.annotate.executors import run_chunks
from tdof20.annotate.label import LabelConfig, _LabelJob, label_scene
from tdof20.annotate.labels import mask_iou
from tdof20.annotate.evaluate import truth_label_inputs
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import RawSession, dumps_bop_json, read_json, read_scene

ARMS, STEPS = 2, 4


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("label") / "session"
    run_capture(sim_config("multi/08", steps=STEPS, step_deg=30.0, n_arms=ARMS, width=160, height=120),
                out, yes=True, show_progress=False)
    return out


def truth_inputs(session: Path):
    """T_ref_frames, placements and models from the simulator's truth."""
    return truth_label_inputs(session)


@pytest.fixture(scope="module")
def labelled(session, tmp_path_factory):
    """One in-process run over the whole session (the reference the other tests compare with)."""
    out = tmp_path_factory.mktemp("label") / "scene"
    T, P, M = truth_inputs(session)
    summary = label_scene(session, out, T, P, M, LabelConfig(workers=1, compare_every=3), progress=False)
    return out, summary


def files_of(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def frame_files(d: Path, im_id: int) -> list[Path]:
    return sorted(p for p in d.rglob(f"{im_id:06d}*.png"))


def test_labels_equal_the_truth(session, labelled):
    out, s = labelled
    n = ARMS * STEPS
    assert (s["frames"], s["labelled"], s["already_done"], s["skipped"]) == (n, n, 0, [])
    assert s["frames_per_s"] > 0 and s["no_opaque"] == [] and s["removed"] == []
    scene = read_scene(out)  # the BOP loaders read it unchanged
    truth = read_scene(session / "truth")
    raw = RawSession.open(session)
    T, _, _ = truth_inputs(session)
    assert scene.im_ids() == truth.im_ids() == list(range(n))
    for im in scene.im_ids():
        arm, step = divmod(im, STEPS)
        # camera: K, depth scale, and the reference camera as the world
        Tw2c = np.linalg.inv(T[(arm, step)])
        cam = scene.camera[im]
        assert np.allclose(cam["cam_K"], raw.info.camera.K) and cam["depth_scale"] == raw.info.camera.depth_scale
        assert np.allclose(cam["cam_R_w2c"], Tw2c[:3, :3], atol=1e-9) and np.allclose(cam["cam_t_w2c"], Tw2c[:3, 3])
        # copied, not re-encoded
        e_t, e_o = raw.entry("transparent", arm, step), raw.entry("opaque", arm, step)
        assert (out / "rgb" / f"{im:06d}.png").read_bytes() == (session / e_t.rgb).read_bytes()
        assert (out / "depth" / f"{im:06d}.png").read_bytes() == (session / e_t.depth).read_bytes()
        assert (out / "depth_opaque" / f"{im:06d}.png").read_bytes() == (session / e_o.depth).read_bytes()
        depth_t = raw.load_depth("transparent", arm, step)
        seen = np.zeros(depth_t.shape, bool)
        for g, e in enumerate(truth.gt[im]):
            assert scene.gt[im][g]["obj_id"] == e["obj_id"]
            R, t = scene.pose(im, g)
            Rt, tt = truth.pose(im, g)
            assert np.abs(R - Rt).max() < 1e-6 and np.abs(t - tt).max() < 1e-4
            full, vis = scene.mask(im, g), scene.mask(im, g, visib=True)
            assert mask_iou(full, truth.mask(im, g)) >= 0.99
            assert mask_iou(vis, truth.mask(im, g, visib=True)) >= 0.99
            seen |= vis
            info, tinfo = scene.gt_info[im][g], truth.gt_info[im][g]
            for k in ("bbox_obj", "bbox_visib", "px_count_all", "px_count_visib"):
                assert info[k] == tinfo[k], (im, g, k)
            assert info["visib_fract"] == pytest.approx(tinfo["visib_fract"])
            # px_count_valid: silhouette pixels with a *transparent* depth measurement
            assert info["px_count_valid"] == int(np.count_nonzero(full & (depth_t > 0)))
            assert info["px_count_valid"] < info["px_count_all"]  # glass loses depth
        # restored depth: the models where an object is seen, the opaque twin's elsewhere
        restored = scene.image("depth_restored", im).astype(np.int64)
        assert seen.any()
        assert np.abs(restored[seen] - truth.depth(im).astype(np.int64)[seen]).max() <= 1
        assert np.array_equal(restored[~seen], raw.load_depth("opaque", arm, step)[~seen])
    # the JSON files are in the BOP toolkit's layout
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        text = (out / name).read_text()
        assert text == dumps_bop_json(json.loads(text))


def test_far_to_near_comparison_is_reported(labelled, session, tmp_path):
    _, s = labelled
    c = s["comparison"]
    assert c["methods"] == ["raycast", "far_to_near"] and c["frames"] == 3  # im_id 0, 3, 6
    assert c["instances"] >= 9
    assert 0.8 < c["visible_iou"]["median"] < 1.0 and c["visible_iou"]["min"] > 0.7
    assert len(c["per_instance"]) == c["instances"]
    # the paper's labels as the method: a valid scene close to the truth
    T, P, M = truth_inputs(session)
    out = tmp_path / "ftn"
    s2 = label_scene(session, out, {k: T[k] for k in [(0, 1), (1, 2)]}, P, M,
                     LabelConfig(method="far_to_near", workers=1), progress=False)
    assert s2["labelled"] == 2 and len(s2["skipped"]) == ARMS * STEPS - 2
    scene, truth = read_scene(out), read_scene(session / "truth")
    ious = [mask_iou(scene.mask(im, g, True), truth.mask(im, g, True)) for im in scene.im_ids()
            for g in range(len(truth.gt[im])) if truth.gt_info[im][g]["px_count_visib"] > 100]
    assert ious and np.median(ious) > 0.8


def test_resume_redoes_only_what_is_missing(session, labelled, tmp_path):
    ref, _ = labelled
    out = tmp_path / "scene"
    shutil.copytree(ref, out)
    # lose a mask of frame 3 and the colour image of frame 5, and frame 6's entry in scene_gt.json
    (out / "mask_visib" / "000003_000001.png").unlink()
    (out / "rgb" / "000005.png").unlink()
    gt = read_json(out / "scene_gt.json")
    del gt["6"]
    (out / "scene_gt.json").write_text(dumps_bop_json(gt))
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    time.sleep(0.01)
    T, P, M = truth_inputs(session)
    s = label_scene(session, out, T, P, M, LabelConfig(workers=1), progress=False)
    assert (s["labelled"], s["already_done"]) == (3, 5)
    for p, t in before.items():
        im = int(p.name[:6])
        if im in (3, 5, 6):
            assert p.stat().st_mtime_ns != t  # rewritten
        else:
            assert p.stat().st_mtime_ns == t, p  # untouched
    assert files_of(out) == files_of(ref)
    # a rerun with nothing missing does nothing; changed poses redo the frames they change
    s = label_scene(session, out, T, P, M, LabelConfig(workers=1), progress=False)
    assert (s["labelled"], s["already_done"]) == (0, 8)
    T2 = dict(T)
    T2[(1, 1)] = T[(1, 1)] @ np.diag([1.0, 1.0, 1.0, 1.0])
    T2[(1, 1)][0, 3] += 0.5
    s = label_scene(session, out, T2, P, M, LabelConfig(workers=1), progress=False)
    assert (s["labelled"], s["already_done"]) == (1, 7)


def test_each_process_builds_its_ray_caster_once(session, tmp_path, monkeypatch):
    import tdof20.annotate.label as label

    built = []
    original = label.ModelRaycaster

    class Counting(original):
        def __init__(self, *a, **k):
            built.append(1)
            super().__init__(*a, **k)

    monkeypatch.setattr(label, "ModelRaycaster", Counting)
    T, P, M = truth_inputs(session)
    s = label_scene(session, tmp_path / "scene", T, P, M, LabelConfig(workers=1, chunk=1), progress=False)
    assert s["labelled"] == ARMS * STEPS and len(built) == 1  # 8 chunks, one ray caster


def test_interrupted_run_keeps_finished_chunks(session, tmp_path, monkeypatch):
    T, P, M = truth_inputs(session)
    out = tmp_path / "scene"
    calls = {"n": 0}
    original = _LabelJob.label_frame

    def flaky(self, st, spec):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return original(self, st, spec)

    monkeypatch.setattr(_LabelJob, "label_frame", flaky)
    with pytest.raises(KeyboardInterrupt):
        label_scene(session, out, T, P, M, LabelConfig(workers=1, chunk=2), progress=False)
    monkeypatch.setattr(_LabelJob, "label_frame", original)
    scene = read_scene(out)  # the JSON files are whole: the finished chunk (frames 0, 1) is in
    assert scene.im_ids() == [0, 1]
    s = label_scene(session, out, T, P, M, LabelConfig(workers=1, chunk=2), progress=False)
    assert (s["labelled"], s["already_done"]) == (6, 2)
    assert read_scene(out).im_ids() == list(range(ARMS * STEPS))


def test_skipped_frames_get_no_labels(session, labelled, tmp_path):
    ref, _ = labelled
    out = tmp_path / "scene"
    shutil.copytree(ref, out)  # frame 1 was labelled before: its labels must go
    T, P, M = truth_inputs(session)
    T = dict(T)
    del T[(1, 2)]  # registration gave nothing for arm 1 step 2 (im_id 6)
    s = label_scene(session, out, T, P, M, LabelConfig(workers=1), skip=[(0, 1, "ICP diverged")],
                    progress=False)
    reasons = {e["im_id"]: e["reason"] for e in s["skipped"]}
    assert reasons == {1: "ICP diverged", 6: "no registration for this frame (no T_ref_frame)"}
    assert s["removed"] == [1, 6] and s["already_done"] == 6
    assert read_scene(out).im_ids() == [0, 2, 3, 4, 5, 7]
    assert frame_files(out, 1) == [] and frame_files(out, 6) == []


def test_bad_frames_are_reported_and_the_rest_labelled(session, tmp_path):
    sess = tmp_path / "session"
    shutil.copytree(session, sess, ignore=shutil.ignore_patterns("truth"))
    raw = RawSession.open(sess)
    rgb = sess / raw.entry("transparent", 0, 2).rgb
    rgb.write_bytes(rgb.read_bytes()[:500])                       # truncated colour image
    (sess / raw.entry("opaque", 1, 0).depth).unlink()             # lost opaque depth
    dep = sess / raw.entry("transparent", 1, 3).depth
    data = bytearray(dep.read_bytes())
    data[200:260] = b"\0" * 60                                    # damaged depth
    dep.write_bytes(bytes(data))
    T, P, M = truth_inputs(session)
    for verify in (True, False):
        out = tmp_path / f"scene{verify}"
        s = label_scene(sess, out, T, P, M, LabelConfig(workers=1, verify=verify), progress=False)
        reasons = {e["im_id"]: e["reason"] for e in s["skipped"]}
        assert sorted(reasons) == [2, 4, 7] and s["labelled"] == 5
        assert str(rgb) in reasons[2] and "missing depth file" in reasons[4] and str(dep) in reasons[7]
        if verify:
            assert "checksum mismatch" in reasons[2] and "checksum mismatch" in reasons[7]
        else:
            assert "corrupt PNG" in reasons[2] or "cannot be decoded" in reasons[2]
        assert read_scene(out).im_ids() == [0, 1, 3, 5, 6]
        for im in (2, 4, 7):
            assert frame_files(out, im) == []


def test_two_local_workers_give_the_same_bytes(session, labelled, tmp_path):
    ref, _ = labelled
    T, P, M = truth_inputs(session)
    out = tmp_path / "scene"
    s = label_scene(session, out, T, P, M, LabelConfig(workers=2, chunk=2), progress=False)
    assert s["labelled"] == ARMS * STEPS and s["workers"] == 2
    assert files_of(out) == files_of(ref)


def _square(chunk):
    if chunk == "boom":
        raise ValueError("boom")
    return [x * x for x in chunk]


def test_run_chunks_local():
    chunks = [[i, i + 1] for i in range(0, 10, 2)]
    for workers in (1, 2):
        got = list(run_chunks(_square, chunks, workers=workers))
        assert sorted(sum(got, [])) == [x * x for x in range(10)]
    with pytest.raises(ValueError, match="boom"):
        list(run_chunks(_square, [[1], "boom", [2]], workers=2))
    with pytest.raises(TdofError, match="executor must be one of"):
        list(run_chunks(_square, chunks, executor="spark"))


def test_bad_inputs(session, tmp_path):
    T, P, M = truth_inputs(session)
    with pytest.raises(TdofError, match="label method"):
        LabelConfig(method="paint")
    with pytest.raises(TdofError, match="no model for object"):
        label_scene(session, tmp_path / "o", T, P, {P[0][0]: M[P[0][0]]}, progress=False)
    with pytest.raises(TdofError, match="must be a .4,4. transform"):
        label_scene(session, tmp_path / "o", {(0, 0): np.eye(3)}, P, M, progress=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(120)
def test_ray_cluster(session, labelled, tmp_path, monkeypatch):
    """A local Ray head started here (`ray start --head --block`, about 4 s on this machine;
    ray.init(num_cpus=1) would take as long and not exercise connecting to an address)."""
    pytest.importorskip("ray")
    ref, _ = labelled
    T, P, M = truth_inputs(session)
    few = {k: T[k] for k in [(0, 0), (0, 3), (1, 1)]}
    # nothing listens there: a clear one-line error, fast
    cfg = LabelConfig(executor="ray", ray_address=f"127.0.0.1:{_free_port()}")
    with pytest.raises(TdofError, match="cannot reach the Ray cluster at 127.0.0.1:"):
        label_scene(session, tmp_path / "none", few, P, M, cfg, progress=False)

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")  # the head and this driver share no token
    port = _free_port()
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths must fit 107 chars
    ray_bin = Path(sys.executable).with_name("ray")
    head = subprocess.Popen([str(ray_bin), "start", "--head", "--block", "--num-cpus", "1", "--port", str(port),
                             "--temp-dir", temp, "--include-dashboard=false", "--disable-usage-stats"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    try:
        deadline = time.time() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert head.poll() is None and time.time() < deadline, "the Ray head did not start"
                time.sleep(0.2)
        out = tmp_path / "scene"
        s = label_scene(session, out, few, P, M,
                        LabelConfig(executor="ray", ray_address=f"127.0.0.1:{port}", chunk=1), progress=False)
        assert s["labelled"] == 3 and s["executor"] == "ray"
        got = files_of(out)
        want = files_of(ref)
        for name, data in got.items():
            if name.endswith(".png"):
                assert data == want[name], name
        assert sorted(int(Path(n).name[:6]) for n in got if n.startswith("rgb/")) == [0, 3, 5]
    finally:
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(timeout=40)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        shutil.rmtree(temp, ignore_errors=True)
