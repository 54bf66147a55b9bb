"""Issue 11 (reliability review): every finding is correct behaviour or one clear refusal naming
the file. Real captures on the simulated rig, real files, no mocks."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tdof20.capture import run_capture, sim_config, verify_session
from tdof20.capture.rig import build_rig
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_journal, read_session, sha256_file
from tdof20.formats.io import stale_temp_files
from tdof20.formats.session import depth_units_problem, frame_size_problem

W, H = 64, 48
EXE = [sys.executable, "-m", "tdof20.cli"]


def tiny(**kw):
    args = dict(steps=2, step_deg=90.0, n_arms=2, width=W, height=H)
    args.update(kw)
    return sim_config("multi/03", **args)


def fingerprint(out: Path) -> dict:
    return {str(p.relative_to(out)): sha256_file(p) for p in sorted(out.rglob("*.png")) if not p.name.startswith(".")}


def env_without_notices() -> dict:
    return {k: v for k, v in os.environ.items() if k != "TDOF20_JOURNAL_NOTICES"}


@pytest.fixture(scope="module")
def captured(tmp_path_factory) -> Path:
    """One complete tiny session (2 phases x 2 arm positions x 2 steps); tests work on copies."""
    out = tmp_path_factory.mktemp("cap") / "s"
    summary = run_capture(tiny(), out, yes=True, show_progress=False)
    assert summary.complete and verify_session(out) == []
    return out


@pytest.fixture
def session(captured, tmp_path) -> Path:
    out = tmp_path / "s"
    shutil.copytree(captured, out)
    return out


def tear_last_line(out: Path, newline: bool) -> int:
    """Replace the journal's last line by its first 35 bytes (+ newline); returns its line number."""
    jp = out / "journal.jsonl"
    lines = jp.read_bytes().split(b"\n")[:-1]
    lines[-1] = lines[-1][:35]  # '{"phase": "opaque", "arm": 1, "st'...
    jp.write_bytes(b"\n".join(lines) + (b"\n" if newline else b""))
    return len(lines)


def edit_session(out: Path, fn) -> None:
    p = out / "session.json"
    d = json.loads(p.read_text())
    fn(d)
    p.write_text(json.dumps(d))


# ---------------------------------------------------------------------------------------------
# 1 (F3): a torn last line, with or without its newline: resume, then the session verifies
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("newline", [True, False], ids=["newline", "no-newline"])
def test_resume_after_a_torn_last_line_always_verifies(session, newline):
    before = fingerprint(session)
    tear_last_line(session, newline)
    assert len(read_journal(session)) == 7  # the torn frame does not count
    summary = run_capture(tiny(), session, yes=True, show_progress=False)
    assert summary.captured == 1 and summary.complete
    assert verify_session(session) == []
    entries = read_journal(session)
    assert sorted(e.key for e in entries) == sorted(RawSession.open(session).info.planned_frames())
    assert len(entries) == 8  # the torn line is gone, not kept beside the frame taken again
    assert fingerprint(session) == before  # the frame taken again is byte-for-byte the same


# ---------------------------------------------------------------------------------------------
# 2: a torn line is said once, in one line, without a Python source line
# ---------------------------------------------------------------------------------------------
def test_torn_line_is_said_once_per_process(session, capfd):
    n = tear_last_line(session, newline=True)
    capfd.readouterr()
    for _ in range(3):
        read_journal(session)
        RawSession.open(session)
    assert verify_session(session)  # the torn frame is missing
    err = capfd.readouterr().err
    assert err.splitlines() == [f"warning: {session / 'journal.jsonl'}: line {n} is incomplete (an interrupted "
                                f"write): ignored; resuming the capture takes its frame again and cuts the line off"]
    assert "UserWarning" not in err and "warn(" not in err


def test_cli_verify_says_a_torn_line_in_one_line(session):
    n = tear_last_line(session, newline=False)
    res = subprocess.run(EXE + ["capture", "verify", str(session)], capture_output=True, text=True, timeout=120,
                         env=env_without_notices())
    assert res.returncode == 1
    warned = [ln for ln in res.stderr.splitlines() if "incomplete" in ln]
    assert warned == [f"warning: {session / 'journal.jsonl'}: line {n} is incomplete (an interrupted write): "
                      f"ignored; resuming the capture takes its frame again and cuts the line off"]
    assert "UserWarning" not in res.stderr and "Traceback" not in res.stderr
    assert "missing frame: opaque arm 1 step 1" in res.stdout


def test_worker_processes_started_afterwards_do_not_repeat_it(session):
    tear_last_line(session, newline=True)
    code = ("import subprocess, sys; from tdof20.formats import read_journal; read_journal(sys.argv[1]); "
            "subprocess.run([sys.executable, '-c', 'import sys; from tdof20.formats import read_journal; "
            "read_journal(sys.argv[1])', sys.argv[1]], check=True)")
    res = subprocess.run([sys.executable, "-c", code, str(session)], capture_output=True, text=True, timeout=120,
                         env=env_without_notices())
    assert res.returncode == 0, res.stderr
    assert len(res.stderr.splitlines()) == 1 and "line 8 is incomplete" in res.stderr


# ---------------------------------------------------------------------------------------------
# 3: an --out that cannot hold a session: one line naming it, before any device moves
# ---------------------------------------------------------------------------------------------
def test_out_is_an_existing_file(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("x")
    rig = build_rig(tiny())
    with pytest.raises(TdofError) as ei:
        run_capture(tiny(), f, yes=True, show_progress=False, rig=rig)
    assert str(ei.value) == f"{f}: --out is a file, not a folder: choose a folder for the session"
    assert rig.world.moves == 0 and f.read_text() == "x"
    with pytest.raises(TdofError, match=f"{tmp_path / 'notes.txt' / 'sub'}: cannot create the session folder: "
                                        f"{f} is a file, not a folder"):
        run_capture(tiny(), f / "sub", yes=True, show_progress=False, rig=rig)
    assert rig.world.moves == 0


def test_cli_out_is_a_file_is_one_line(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("x")
    res = subprocess.run(EXE + ["capture", "run", "--sim", "--scene", "multi/03", "--steps", "2", "--arm-positions",
                                "1", "--width", str(W), "--height", str(H), "--yes", "--out", str(f)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"error: {f}: --out is a file, not a folder: choose a folder for "
                                               f"the session"]


def test_out_under_a_folder_that_refuses_writes(tmp_path):
    """/sys refuses new entries even to root (the tests run as root, where chmod does not stop writes)."""
    target = Path("/sys/tdof20-capture-test")
    if not Path("/sys").is_dir() or os.access("/sys", os.W_OK) and _can_mkdir(target):
        pytest.skip("no folder here that refuses writes to this user")
    rig = build_rig(tiny())
    with pytest.raises(TdofError, match=r"^/sys/tdof20-capture-test: cannot write the session folder \(.+\): "
                                        r"choose a folder you can write to$"):
        run_capture(tiny(), target, yes=True, show_progress=False, rig=rig)
    assert rig.world.moves == 0


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a 0555 folder: chmod cannot make it read-only")
def test_out_is_a_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(TdofError, match="ro: cannot write the session folder"):
            run_capture(tiny(), ro, yes=True, show_progress=False)
        with pytest.raises(TdofError, match="cannot write the session folder"):
            run_capture(tiny(), ro / "s", yes=True, show_progress=False)
    finally:
        ro.chmod(0o755)


def _can_mkdir(p: Path) -> bool:
    try:
        p.mkdir()
    except OSError:
        return False
    p.rmdir()
    return True


def test_a_write_failing_mid_run_stops_cleanly(session):
    """A folder of the session replaced by a file (any OSError while writing): one line, resumable."""
    lines = (session / "journal.jsonl").read_text().splitlines()
    (session / "journal.jsonl").write_text("\n".join(lines[:6]) + "\n")  # opaque arm 1 still to take
    shutil.rmtree(session / "opaque" / "arm1")
    (session / "opaque" / "arm1").write_text("in the way")
    with pytest.raises(TdofError) as ei:
        run_capture(tiny(), session, yes=True, show_progress=False, resume_command="tdof20 capture run X")
    msg = str(ei.value)
    assert msg.startswith("capture stopped: cannot write ") and "opaque/arm1" in msg
    assert msg.endswith("0 new frames kept; resume with: tdof20 capture run X") and "\n" not in msg
    (session / "opaque" / "arm1").unlink()
    assert run_capture(tiny(), session, yes=True, show_progress=False).captured == 2
    assert verify_session(session) == []


# ---------------------------------------------------------------------------------------------
# 4: a hand-eye translation in metres is refused by the session reader
# ---------------------------------------------------------------------------------------------
def test_hand_eye_in_metres_is_refused_naming_session_json(session):
    def to_metres(d):
        T = d["hand_eye"]["T_tcp_cam"]
        T[3], T[7], T[11] = T[3] / 1000, T[7] / 1000, T[11] / 1000

    edit_session(session, to_metres)
    with pytest.raises(TdofError) as ei:
        read_session(session)
    assert str(ei.value).startswith(f"{session / 'session.json'}: hand_eye.T_tcp_cam translation has length 0.075")
    assert "looks like metres, millimetres expected" in str(ei.value)
    res = subprocess.run(EXE + ["capture", "verify", str(session)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and res.stderr.startswith("error: ") and "hand_eye.T_tcp_cam" in res.stderr
    assert "Traceback" not in res.stderr


# ---------------------------------------------------------------------------------------------
# 5: frames of another size than session.json's camera: one line naming the file and both sizes
# ---------------------------------------------------------------------------------------------
def test_frame_size_against_session_json(session):
    def double(d):
        d["camera"]["width"], d["camera"]["height"] = 2 * W, 2 * H

    edit_session(session, double)
    s = RawSession.open(session)
    for load, kind, rel in ((s.load_rgb, "colour", "rgb"), (s.load_depth_mm, "depth", "depth")):
        with pytest.raises(TdofError) as ei:
            load("opaque", 0, 1)
        msg = str(ei.value)
        assert msg == (f"{session / 'opaque/arm0' / rel / '000001.png'}: {kind} image is {W}x{H} pixels but "
                       f"session.json's camera is {2 * W}x{2 * H} (camera.width x camera.height)")
        problems = verify_session(session)
        assert msg in problems  # capture verify says the very same line (one check function)
    assert len(verify_session(session)) == 16  # every file of the 8 frames
    assert frame_size_problem(np.zeros((H, W, 3), np.uint8), s.info.camera, "rgb").startswith("colour image is 64x48")
    assert frame_size_problem(np.zeros((2 * H, 2 * W), np.uint16), s.info.camera, "depth") is None


# ---------------------------------------------------------------------------------------------
# 6: depth units
# ---------------------------------------------------------------------------------------------
def test_depth_scale_off_by_1000_is_caught_by_verify(session):
    edit_session(session, lambda d: d["camera"].__setitem__("depth_scale", 0.001))
    problems = verify_session(session)
    assert len(problems) == 1, problems
    p = problems[0]
    assert p.startswith(f"{session / 'session.json'}: the valid depths have a median of 0.")
    assert "implausible for a tabletop rig (100..5000 mm): camera.depth_scale in session.json is 0.001 mm per unit; " \
           "depth_scale = 1 would give" in p
    assert p.endswith("(sampled: opaque arm 0 step 0, opaque arm 1 step 0)")


def test_depth_units_problem_in_words(captured):
    s = RawSession.open(captured)
    z = s.load_depth_mm("opaque", 0, 0)
    assert depth_units_problem(s.info, z) is None
    too_far = depth_units_problem(s.info, z * 1000)
    assert "camera.depth_scale in session.json is 1 mm per unit; depth_scale = 0.001 would give" in too_far
    assert depth_units_problem(s.info, np.zeros_like(z)) == \
        "holds no depth at all (every pixel is 0): the camera delivered no depth"
    zoomed = depth_units_problem(s.info, z / 10)  # a 0.1 mm/unit camera read as 1 mm/unit
    assert zoomed is None or "depth_scale = 10 would give" in zoomed


# ---------------------------------------------------------------------------------------------
# 7: missing frames of a phase: one deterministic line naming journal.jsonl
# ---------------------------------------------------------------------------------------------
def test_empty_journal_is_one_line_naming_the_journal(session):
    jp = session / "journal.jsonl"
    jp.write_bytes(b"")
    s = RawSession.open(session)
    for _ in range(2):
        with pytest.raises(TdofError) as ei:
            s.require_frames("opaque")
        assert str(ei.value) == f"{jp}: no opaque frames (the journal is empty: was the capture run?)"
    assert verify_session(session) == [f"{jp}: no transparent frames (the journal is empty: was the capture run?)"]
    jp.unlink()
    with pytest.raises(TdofError, match=r"journal\.jsonl: no opaque frames \(there is no journal: was the capture run\?\)"):
        RawSession.open(session).require_frames("opaque")


def test_a_phase_or_an_arm_without_frames(session):
    jp = session / "journal.jsonl"
    lines = jp.read_text().splitlines()
    jp.write_text("\n".join(lines[:4]) + "\n")  # the transparent phase only
    s = RawSession.open(session)
    assert len(s.require_frames("transparent")) == 4
    msg = f"{jp}: no opaque frames (the journal lists 4 transparent frames only: was the opaque phase captured?)"
    with pytest.raises(TdofError) as ei:
        s.require_frames("opaque")
    assert str(ei.value) == msg
    problems = verify_session(session)
    assert problems[-1] == msg and problems[0] == "missing frame: opaque arm 0 step 0"
    jp.write_text("\n".join(lines[:6]) + "\n")  # opaque arm 0 only
    with pytest.raises(TdofError) as ei:
        RawSession.open(session).require_frames("opaque")
    assert str(ei.value) == f"{jp}: no opaque frames for arm position 1 (of 2 in session.json): " \
                            f"was the capture stopped early?"
    edit_session(session, lambda d: d.__setitem__("phases", ["transparent"]))
    jp.write_text("\n".join(lines[:4]) + "\n")
    with pytest.raises(TdofError, match=r"session\.json: phases \['transparent'\] do not include 'opaque'"):
        RawSession.open(session).require_frames("opaque")


# ---------------------------------------------------------------------------------------------
# 8: stale temporary files of a kill -9 are removed on resume (only those)
# ---------------------------------------------------------------------------------------------
STALE = [".session.json.k3j_9x2q.tmp", "transparent/arm0/rgb/.000001.png.ab12cd34.tmp",
         "opaque/arm1/depth/.000000.png.zz_zz_zz.tmp", "truth/.scene_gt.json.q1w2e3r4.tmp",
         ".journal.jsonl.abcdefgh.tmp"]
KEPT = ["notes.tmp", ".hidden.tmp", "transparent/arm0/rgb/.x.abc.tmp", "truth/.scene_gt.json.ABCDEFGH.tmp",
        "operator-notes.txt"]


def test_resume_removes_only_stale_temp_files(session):
    for rel in STALE + KEPT:
        (session / rel).write_bytes(b"half")
    assert sorted(str(p.relative_to(session)) for p in stale_temp_files(session)) == sorted(STALE)
    summary = run_capture(tiny(), session, yes=True, show_progress=False)
    assert summary.captured == 0
    for rel in STALE:
        assert not (session / rel).exists(), rel
    for rel in KEPT:
        assert (session / rel).read_bytes() == b"half", rel
    assert "removed the unfinished write" in (session / "capture.log").read_text()


def test_kill_during_the_first_session_json_write(tmp_path):
    """A kill -9 while session.json was first written leaves only its temporary file: that folder
    is still this run's, not 'not empty'."""
    out = tmp_path / "s"
    out.mkdir()
    (out / ".session.json.a1b2c3d4.tmp").write_text('{"format": "tdof')
    (out / ".write-check.9z8y7x6w.tmp").write_bytes(b"")
    summary = run_capture(tiny(), out, yes=True, show_progress=False)
    assert summary.complete and verify_session(out) == [] and stale_temp_files(out) == []
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / ".notes.txt.a1b2c3d4.tmp").write_text("someone else's")
    with pytest.raises(TdofError, match="not empty and holds no session.json"):
        run_capture(tiny(), tmp_path / "t", yes=True, show_progress=False)
    assert (tmp_path / "t" / ".notes.txt.a1b2c3d4.tmp").exists()
