"""The capture sequencer on the simulated rig: plan, run, resume after any interruption, faults."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tdof20.capture import config_from_dict, load_config, run_capture, sim_config, verify_session
from tdof20.capture.plan import describe, workspace_problems
from tdof20.capture.rig import build_rig
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_journal, read_png, sha256_file
from tests.cli_support import run_here

SIM_ARGS = ["--sim", "--scene", "multi/03", "--steps", "30", "--step-deg", "12", "--arm-positions", "2",
            "--width", "96", "--height", "72"]


def small(**kw):
    args = dict(steps=4, step_deg=90.0, n_arms=2, width=96, height=72)
    args.update(kw)
    return sim_config("multi/03", **args)


def fingerprint(out: Path) -> dict:
    """Every frame file and its checksum, plus the truth files."""
    return {str(p.relative_to(out)): sha256_file(p) for p in sorted(out.rglob("*.png")) if not p.name.startswith(".")}


def differences(out: Path, ref: Path) -> list[str]:
    """The PNGs of ``out`` that differ from ``ref``'s (or that only one has), with the number of
    pixels that differ: what a failed comparison of two runs shows."""
    a, b = fingerprint(out), fingerprint(ref)
    lines = []
    for name in sorted(set(a) | set(b)):
        if a.get(name) == b.get(name):
            continue
        if name in a and name in b:
            x, y = read_png(out / name), read_png(ref / name)
            n = int(np.any(x != y, axis=-1).sum()) if x.ndim == 3 else int((x != y).sum())
            lines.append(f"{name}: {n} pixels differ")
        else:
            lines.append(f"{name}: only in {'the resumed run' if name in a else 'the reference'}")
    return lines


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run of the session the interruption tests use (SIM_ARGS), made in this
    process: the frames are deterministic for the config, so the CLI's runs must give these bytes."""
    out = tmp_path_factory.mktemp("ref") / "s"
    run_capture(sim_config("multi/03", steps=30, step_deg=12.0, n_arms=2, width=96, height=72), out, yes=True,
                show_progress=False)
    return out



def test_sequence_end_to_end(tmp_path):
    cfg = small()
    summary = run_capture(cfg, tmp_path / "s", yes=True, show_progress=False)
    assert summary.complete and summary.captured == 2 * 2 * 4 and summary.retries == 0
    s = RawSession.open(tmp_path / "s")
    assert s.missing_frames() == [] and verify_session(tmp_path / "s") == []
    # the journal is in capture order and records the read-back metadata
    keys = [e.key for e in s.entries]
    assert keys == [(ph, a, k) for ph in ("transparent", "opaque") for a in range(2) for k in range(4)]
    e = s.entry("opaque", 1, 3)
    assert e.angle_deg == pytest.approx(270.0)
    assert np.allclose(e.extra["q_actual"], s.info.arm_positions[1].q)
    assert e.extra["table_angle_reported_deg"] == pytest.approx(270.0)
    assert (tmp_path / "s" / "capture.log").read_text().count("moving to arm position") == 4
    # a second run finds nothing to do and changes nothing
    before = fingerprint(tmp_path / "s")
    again = run_capture(cfg, tmp_path / "s", yes=True, show_progress=False)
    assert again.captured == 0 and again.present_before == 16
    assert fingerprint(tmp_path / "s") == before


def test_bad_files_are_taken_again(tmp_path):
    cfg = small()
    out = tmp_path / "s"
    run_capture(cfg, out, yes=True, show_progress=False)
    ref = fingerprint(out)
    (out / "transparent/arm1/depth/000002.png").write_bytes(b"garbage")
    (out / "opaque/arm0/rgb/000001.png").unlink()
    problems = verify_session(out)
    assert any("arm1/depth/000002.png: checksum mismatch" in p for p in problems)
    assert any("arm0/rgb/000001.png: missing file" in p for p in problems)
    summary = run_capture(cfg, out, yes=True, show_progress=False)
    assert summary.captured == 2 and summary.retaken == 2
    assert fingerprint(out) == ref and verify_session(out) == []


@pytest.mark.parametrize("sig,seed", [(signal.SIGKILL, 1), (signal.SIGKILL, 2), (signal.SIGKILL, 3),
                                      (signal.SIGTERM, 4)])
def test_interrupted_run_resumes_to_the_same_session(tmp_path, reference, sig, seed):
    out = tmp_path / "s"
    rng = np.random.default_rng(seed)
    stop_at = int(rng.integers(1, 110))  # frames journalled before the signal (120 planned)
    cmd = [sys.executable, "-m", "tdof20.cli", "capture", "run", *SIM_ARGS, "--out", str(out), "--yes"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    journal = out / "journal.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if journal.exists() and journal.read_bytes().count(b"\n") >= stop_at:
            break
        time.sleep(0.002)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode != 0
    if sig == signal.SIGTERM:
        assert "stopped by SIGTERM" in err and "resume with: tdof20 capture run" in err
        assert len([ln for ln in err.splitlines() if ln.startswith("error:")]) == 1
    n_before = len(read_journal(out))
    assert n_before < 120
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert verify_session(out) == []
    assert fingerprint(out) == fingerprint(reference), differences(out, reference)
    assert not list(out.rglob(".*.tmp"))


def test_device_failures_are_retried_then_stop_cleanly(tmp_path):
    cfg = small()
    rig = build_rig(cfg, faults={"camera_timeouts": 2, "turntable_timeouts": 1})
    summary = run_capture(cfg, tmp_path / "a", yes=True, show_progress=False, rig=rig)
    assert summary.complete and summary.retries == 3
    # the camera fails for good after 5 frames: a clean stop naming the device and the resume command
    out = tmp_path / "b"
    rig = build_rig(cfg)
    calls = {"n": 0}
    orig = rig.camera.grab

    def flaky(timeout_s):
        calls["n"] += 1
        if calls["n"] > 5:
            rig.world.faults["camera_timeouts"] = 99
        return orig(timeout_s)

    rig.camera.grab = flaky
    with pytest.raises(TdofError, match=r"sim camera: no synchronised.*resume with: tdof20 capture run --sim x"):
        run_capture(cfg, out, yes=True, show_progress=False, rig=rig, resume_command="tdof20 capture run --sim x")
    s = RawSession.open(out)
    assert len(s.entries) == 5 and verify_session(out)[:1] == ["missing frame: transparent arm 1 step 1"]
    assert "stopped" in (out / "capture.log").read_text()


def test_protective_stop_pauses_for_the_operator(tmp_path):
    cfg = small()
    # scripted (--yes): stop cleanly
    rig = build_rig(cfg, faults={"protective_stop_on_move": 2})
    with pytest.raises(TdofError, match="protective stop"):
        run_capture(cfg, tmp_path / "a", yes=True, show_progress=False, rig=rig)
    # interactive: the operator clears it on the pendant and presses Enter; the run goes on
    rig = build_rig(cfg, faults={"protective_stop_on_move": 2})
    prompts = []

    def operator(msg):
        prompts.append(msg)
        rig.world.clear_protective_stop()
        return ""

    summary = run_capture(cfg, tmp_path / "b", yes=False, show_progress=False, rig=rig, prompt=operator)
    assert summary.complete and any("teach pendant" in p for p in prompts)
    assert any("safety stop" in w for w in summary.warnings)


def test_workspace_check_refuses_before_any_motion(tmp_path):
    tight = config_from_dict({"session": {"scene_id": "multi/03"}, "turntable": {"steps": 2},
                              "robot": {"limits": {"tcp_max": [850.0, 850.0, 250.0]}}})
    assert workspace_problems(tight)  # the upper arm positions reach above 250 mm
    d = describe(tight)
    assert not d["ok"] and any(a["problems"] for a in d["arms"])
    rig = build_rig(tight)
    with pytest.raises(TdofError, match="refused before any motion.*TCP z"):
        run_capture(tight, tmp_path / "s", yes=True, show_progress=False, rig=rig)
    assert rig.world.moves == 0 and not (tmp_path / "s").exists()


def test_output_folder_of_another_session_is_refused(tmp_path):
    out = tmp_path / "s"
    run_capture(small(), out, yes=True, show_progress=False)
    before = fingerprint(out)
    with pytest.raises(TdofError, match="different session"):
        run_capture(small(seed=9), out, yes=True, show_progress=False)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    with pytest.raises(TdofError, match="not empty"):
        run_capture(small(), tmp_path / "other", yes=True, show_progress=False)
    assert fingerprint(out) == before


CONFIG = """
[session]
scene_id = "multi/08"
objects = [3, 7, 12]

[hand_eye]
T_tcp_cam = [1,0,0,0, 0,1,0,-60, 0,0,1,45, 0,0,0,1]

[robot]
backend = "ur_rtde"
host = "192.168.1.10"
positions = [[0.37, -1.71, -2.30, -2.71, -1.24, -2.98], [0.31, -1.67, -1.95, 2.95, -1.34, -2.95]]

[turntable]
backend = "grbl"
port = "/dev/ttyUSB0"

[camera]
backend = "oakd"
"""


@pytest.mark.parametrize("edit,needle", [
    (("robot", "speed", "fast"), "robot.speed: must be a number"),
    (("robot", "positions", [[0.1, 0.2, 0.3, 0.4, 0.5]]), "robot.positions[0]: must be 6 joint angles"),
    (("robot", "positions", [[10, 20, 30, 40, 50, 60]]), "looks like degrees"),
    (("robot", "backend", "kuka"), "unknown backend 'kuka'"),
    (("robot", "spead", 1.0), "unknown option 'robot.spead'"),
    (("turntable", "steps", 0), "turntable.steps: must be in 1..36000"),
    (("session", "objects", [3, 3, 12]), "session.objects[1]: object 3 is listed twice"),
    (("session", "objects", [3, 25]), "unknown object id 25"),
    (("session", "scene_id", "multi/30"), "multi/30"),
    (("session", "scene_id", "multi/20"), "multi/00..multi/19"),  # the release numbers multi scenes 00..19
    (("session", "scene_id", "single/mug"), "single/<class name>"),
    (("hand_eye", "T_tcp_cam", [1, 0, 0, 0, 0, 1, 0, -0.06, 0, 0, 1, 0.045, 0, 0, 0, 1]), "looks like metres"),
    (("camera", "backend", "sim"), "mixing is not supported"),
])
def test_config_errors_are_one_line_and_name_the_option(tmp_path, edit, needle):
    import tomllib

    data = tomllib.loads(CONFIG)
    table, key, value = edit
    data[table][key] = value
    with pytest.raises(TdofError) as e:
        config_from_dict(data, "rig.toml")
    assert needle in str(e.value) and str(e.value).startswith("rig.toml: ") and "\n" not in str(e.value)


def test_scene_alias_is_stored_as_the_class_name(tmp_path):
    import tomllib

    data = tomllib.loads(CONFIG)
    data["session"]["scene_id"] = "single/07"
    assert config_from_dict(data, "rig.toml").session.scene_id == "single/handle_cup_280"
    data["session"]["scene_id"] = "multi/00"
    assert config_from_dict(data, "rig.toml").session.scene_id == "multi/00"
    cfg = sim_config("single/06", steps=1, step_deg=90.0, n_arms=1, width=32, height=24, phases=("transparent",))
    assert cfg.session.scene_id == "single/goblet_180"
    run_capture(cfg, tmp_path / "s", yes=True, show_progress=False)
    s = RawSession.open(tmp_path / "s")
    assert s.info.scene_id == "single/goblet_180" and s.info.obj_ids == [6]


def test_example_config_loads_and_plans():
    cfg = load_config(Path(__file__).parents[1] / "examples" / "real_rig.toml")
    assert cfg.robot.backend == "ur_rtde" and cfg.turntable.steps == 400 and not cfg.is_sim
    d = describe(cfg)
    assert d["ok"] and len(d["arms"]) == 4 and d["estimate"]["frames"] == 3200


def test_malformed_toml(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[robot\nhost = 1")
    with pytest.raises(TdofError, match="bad.toml: malformed TOML"):
        load_config(p)
    with pytest.raises(TdofError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_cli_plan_and_verify(tmp_path, capfd, monkeypatch):
    """plan and verify through the CLI's entry point in this process; the last call, a usage
    error, as the console script in a subprocess."""
    exe = [sys.executable, "-m", "tdof20.cli"]
    res = run_here(capfd, monkeypatch, "capture", "plan", "--sim", "--json")
    assert res.returncode == 0 and json.loads(res.stdout)["estimate"]["frames"] == 3200
    out = tmp_path / "s"
    run_capture(small(), out, yes=True, show_progress=False)
    res = run_here(capfd, monkeypatch, "capture", "verify", out)
    assert res.returncode == 0
    (out / "opaque/arm1/rgb/000003.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    lines = (out / "journal.jsonl").read_text().splitlines()
    (out / "journal.jsonl").write_text("\n".join(lines[:-2]) + "\n")
    res = run_here(capfd, monkeypatch, "capture", "verify", out)
    assert res.returncode == 1
    assert "missing frame: opaque arm 1 step 2" in res.stdout and "missing frame: opaque arm 1 step 3" in res.stdout
    res = subprocess.run(exe + ["capture", "run", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "--sim" in res.stderr
