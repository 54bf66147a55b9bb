"""What annotate refuses, and what it never damages: options out of range named with their file
(once), a scene folder that holds another session's annotation, a colour file that is not the
PNG its name says, the folder lock under concurrent runs, temporary files of a killed run."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import cv2
import pytest

from tdof20.annotate.config import AnnotateConfig, load_annotate_config
from tdof20.annotate.evaluate import truth_label_inputs
from tdof20.annotate.label import LabelConfig, label_scene
from tdof20.annotate.pipeline import annotate
from tdof20.annotate.state import FolderLock as _Lock
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json

CFG = AnnotateConfig(label=LabelConfig(workers=1))


def _capture(path: Path, scene: str, steps: int = 6) -> Path:
    run_capture(sim_config(scene, steps=steps, step_deg=30.0, n_arms=1, width=160, height=120), path, yes=True,
                show_progress=False)
    return path


# ------------------------------------------------------------------------------------- options
@pytest.mark.parametrize("toml, option", [
    ("[reconstruct]\nvoxel_mm = -2.0\n", "reconstruct.voxel_mm must be > 0"),
    ("[register]\nvoxel_sizes_mm = [8.0, 0.0]\n", "register.voxel_sizes_mm must be > 0"),
    ("[register]\nmin_fitness = 1.5\n", "register.min_fitness must be in [0, 1]"),
    ("[fit]\nicp_mm = []\n", "fit.icp_mm must not be empty"),
    ("[build]\npoisson_depth = 0\n", "build.poisson_depth must be > 0"),
    ("fuse_max_frames = -1\n", "fuse_max_frames must be >= 0"),
    ("[label]\nchunk = 0\n", "chunk must be >= 1"),
    ("[place]\nmatch_candidates = 0\n", "match_candidates must be >= 1"),
])
def test_out_of_range_options_are_refused_naming_the_file_once(tmp_path, toml, option):
    p = tmp_path / "bad.toml"
    p.write_text(toml)
    with pytest.raises(TdofError) as e:
        load_annotate_config(p)
    msg = str(e.value)
    assert option in msg
    assert msg.count(str(p)) == 1 and msg.startswith(f"{p}: ")
    assert ": :" not in msg and "\n" not in msg


# ------------------------------------------------------------------------------------- another session
def test_out_holding_another_sessions_annotation_is_refused_unless_force(tmp_path):
    a = _capture(tmp_path / "raw_a", "multi/08")
    b = _capture(tmp_path / "raw_b", "single/juice_cup_340")
    out = tmp_path / "scene"
    annotate(a, out, stages="register", cfg=CFG, progress=False)
    reg_a = (out / "work" / "registration.json").read_bytes()
    with pytest.raises(TdofError, match="another session .*multi/08.*--force") as e:
        annotate(b, out, stages="register", cfg=CFG, progress=False)
    assert str(out) in str(e.value)
    # nothing of the first annotation was touched
    assert (out / "work" / "registration.json").read_bytes() == reg_a
    assert read_json(out / "work" / "state.json")["session"]["scene_id"] == "multi/08"
    # the same session (here: moved to another folder) is still this annotation: it resumes
    moved = tmp_path / "moved_a"
    a.rename(moved)
    again = annotate(moved, out, stages="register", cfg=CFG, progress=False)
    assert again["stages"]["register"]["status"] == "up to date"
    # --force replaces it, and nothing of the old one is left
    annotate(b, out, stages="register", cfg=CFG, force=True, progress=False)
    assert read_json(out / "work" / "state.json")["session"]["scene_id"] == "single/juice_cup_340"
    assert (out / "work" / "registration.json").read_bytes() != reg_a
    assert read_json(out / "work" / "registration.json")["scene_id"] == "single/juice_cup_340"


# ------------------------------------------------------------------------------------- not a PNG
def test_a_jpeg_named_png_is_skipped_not_copied(tmp_path):
    raw = _capture(tmp_path / "raw", "multi/08", steps=3)
    s = RawSession.open(raw)
    e = s.entry("transparent", 0, 1)
    p = raw / e.rgb
    ok, jpg = cv2.imencode(".jpg", cv2.imread(str(p)))
    assert ok
    p.write_bytes(jpg.tobytes())
    # the journal's checksum matches the JPEG: only the file's content gives it away
    import hashlib

    lines = (raw / "journal.jsonl").read_text().splitlines()
    for i, line in enumerate(lines):
        d = json.loads(line)
        if (d["phase"], d["arm"], d["step"]) == ("transparent", 0, 1):
            d["sha256"]["rgb"] = hashlib.sha256(jpg.tobytes()).hexdigest()
            lines[i] = json.dumps(d)
    (raw / "journal.jsonl").write_text("\n".join(lines) + "\n")

    frames, places, models = _truth_labels(raw)
    out = tmp_path / "scene"
    summary = label_scene(raw, out, frames, places, models, LabelConfig(workers=1), progress=False)
    skipped = {sk["im_id"]: sk["reason"] for sk in summary["skipped"]}
    assert 1 in skipped and "not a PNG" in skipped[1] and e.rgb in skipped[1]
    assert not (out / "rgb" / "000001.png").exists()
    assert (out / "rgb" / "000000.png").exists() and (out / "rgb" / "000002.png").exists()
    assert "1" not in read_json(out / "scene_gt.json")


_truth_labels = truth_label_inputs


# ------------------------------------------------------------------------------------- the label gate
def test_the_label_gate_writes_true_labels_and_refuses_wrong_ones(tmp_path):
    raw = _capture(tmp_path / "raw", "multi/08", steps=4)
    frames, places, models = _truth_labels(raw)
    good = label_scene(raw, tmp_path / "good", frames, places, models, LabelConfig(workers=1), progress=False)
    assert good["labelled"] == 4 and not good["skipped"]
    assert good["gate"]["instances_failed"] == 0 and good["gate"]["agree"]["min"] > 0.9
    # one object placed 20 mm off (about a sixth of its diameter): no frame gets that label
    wrong = [(o, M.copy()) for o, M in places]
    wrong[1][1][:3, 3] += [20.0, 0.0, 0.0]
    out = tmp_path / "wrong"
    bad = label_scene(raw, out, frames, wrong, models, LabelConfig(workers=1), progress=False)
    assert bad["labelled"] == 0 and len(bad["skipped"]) == 4
    assert all(sk["reason"].startswith(f"label gate: object {wrong[1][0]} (gt 1) disagrees with the opaque depth")
               for sk in bad["skipped"])
    assert bad["gate"]["frames_refused"] == 4
    assert not list((out / "rgb").glob("*.png")) and not (out / "scene_gt.json").exists()
    # the gate off writes them (what the gate prevents)
    off = label_scene(raw, tmp_path / "off", frames, wrong, models, LabelConfig(workers=1, gate=False),
                      progress=False)
    assert off["labelled"] == 4
    # with the gate on again, without reuse every frame is judged again: the wrong labels go
    again = label_scene(raw, tmp_path / "off", frames, wrong, models, LabelConfig(workers=1), progress=False,
                        reuse=False)
    assert again["labelled"] == 0 and again["gate"]["frames_refused"] == 4 and sorted(again["removed"]) == [0, 1, 2, 3]
    assert not list((tmp_path / "off" / "rgb").glob("*.png")) and read_json(tmp_path / "off" / "scene_gt.json") == {}


# ------------------------------------------------------------------------------------- the lock
def _hold(work: str, barrier, log: str) -> None:
    barrier.wait()
    try:
        with _Lock(Path(work)):
            t0 = time.monotonic()
            time.sleep(0.15)
            t1 = time.monotonic()
        with open(log, "a") as f:
            f.write(f"{t0} {t1}\n")
    except TdofError as e:
        with open(log + ".refused", "a") as f:
            f.write(str(e) + "\n")


def test_the_folder_lock_has_one_holder_at_a_time(tmp_path):
    ctx = mp.get_context("fork")
    log = str(tmp_path / "held.txt")
    for trial in range(5):
        work = tmp_path / f"work{trial}"
        work.mkdir()
        barrier = ctx.Barrier(4)
        procs = [ctx.Process(target=_hold, args=(str(work), barrier, log)) for _ in range(4)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(30)
            assert p.exitcode == 0
    spans = sorted(tuple(map(float, line.split())) for line in Path(log).read_text().splitlines())
    assert len(spans) >= 5   # every trial had a holder
    for (a0, a1), (b0, b1) in zip(spans, spans[1:]):
        assert b0 >= a1 or b1 <= a0 or a1 <= b0, "two runs held the lock at once"
    refusals = Path(log + ".refused").read_text().splitlines()
    assert refusals and all("another annotate run" in r and "wait for it" in r for r in refusals)


def test_a_lock_of_a_dead_run_is_taken_over(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / ".lock").write_text("999999")   # left by a run killed with -9: no process holds it
    with _Lock(work):
        assert (work / ".lock").read_text() == str(os.getpid())
    with pytest.raises(TdofError, match="another annotate run"):
        with _Lock(work):
            with _Lock(work):
                pass


# ------------------------------------------------------------------------------------- temp files
def test_temporary_files_of_a_killed_run_are_removed_on_resume(tmp_path):
    raw = _capture(tmp_path / "raw", "multi/08", steps=4)
    out = tmp_path / "scene"
    annotate(raw, out, stages="register", cfg=CFG, progress=False)
    (out / "mask").mkdir()
    stale = [out / "mask" / ".000000_000000.png.k2j3ab9_.tmp", out / "work" / ".registration.json.x1yz0q8w.tmp",
             out / "work" / "reconstruction" / "scene_mesh.tmp.ply"]
    stale[-1].parent.mkdir(parents=True)
    for p in stale:
        p.write_bytes(b"half")
    keep = out / "mask" / "notes.tmp.txt"
    keep.write_text("mine")
    summary = annotate(raw, out, stages="register", cfg=CFG, progress=False)
    assert not any(p.exists() for p in stale)
    assert keep.exists()
    assert any("removed 3 temporary file" in w for w in summary["warnings"])
