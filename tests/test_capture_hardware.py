"""The capture runner driving the real drivers: the GRBL turntable driver against the emulated
controller on a pseudo-terminal, the UR driver against fake RTDE interfaces, and a camera that
sees the table angle — the whole hardware path short of the devices themselves."""

import time

import numpy as np
import pytest

from tdof20.capture import config_from_dict, run_capture, verify_session
from tdof20.capture.hardware.grbl import GrblTurntable
from tdof20.capture.hardware.grbl_emulator import GrblEmulator
from tests.grbl_support import FAST_HOMING
from tdof20.capture.hardware.interfaces import RGBDCamera, RGBDFrame
from tdof20.capture.hardware.ur import URRobot
from tdof20.capture.rig import Rig
from tdof20.errors import TdofError
from tdof20.formats import RawSession
from tdof20.sim.rig import RigLayout

from fake_rtde import FakeURController


class AngleCamera(RGBDCamera):
    """A camera whose colour encodes the angle the turntable driver reports."""

    name = "test camera"

    def __init__(self, table):
        self.table = table

    def connect(self):
        pass

    def close(self):
        pass

    def intrinsics(self):
        return {"K": [60.0, 0, 31.5, 0, 60.0, 23.5, 0, 0, 1], "width": 64, "height": 48, "depth_scale": 1.0}

    def grab(self, timeout_s):
        a = self.table.angle()
        rgb = np.full((48, 64, 3), int(round(a)) % 256, np.uint8)
        depth = np.full((48, 64), 500 + int(round(a)), np.uint16)
        t = time.time()
        return RGBDFrame(rgb, depth, t, t)


def hardware_config(steps=4):
    targets = [q for q, _ in RigLayout().arm_positions(2)]
    return config_from_dict({
        "session": {"scene_id": "multi/08", "objects": [3, 7, 12]},
        "hand_eye": {"T_tcp_cam": list(np.asarray(RigLayout().T_tcp_cam).reshape(-1))},
        "robot": {"backend": "ur_rtde", "host": "10.0.0.5", "positions": [list(q) for q in targets]},
        "turntable": {"backend": "grbl", "port": "unused", "steps": steps, "step_deg": 90.0, "timeout_s": 5.0,
                      "feed_deg_per_s": 3600.0},
        "camera": {"backend": "oakd", "width": 64, "height": 48},
    }, "rig.toml")


@pytest.fixture
def devices():
    # GRBL as it powers up with homing on ($22=1): in the homing lock; the table built as build_rig
    # builds it for [turntable] home = true (the runner homes it); a fast homing cycle for the test
    emu = GrblEmulator(speed_units_per_s=3600.0, settings=FAST_HOMING)
    emu.start()
    ctl = FakeURController(motion_time_s=0.01)
    robot = URRobot("10.0.0.5", control_factory=ctl.control, receive_factory=ctl.receive, connect_timeout_s=2.0)
    table = GrblTurntable(emu.port, timeout_s=3.0, feed_deg_per_s=3600.0, home=True)
    yield emu, ctl, robot, table
    ctl.release()
    emu.stop()


def test_the_config_reaches_the_real_drivers():
    """build_rig hands the config's robot options to the UR driver (the arrival tolerance was left at
    the driver's own 0.002 rad); nothing connects."""
    import dataclasses

    from tdof20.capture.rig import build_rig

    cfg = hardware_config()
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, joint_tolerance_rad=0.01))
    rig = build_rig(cfg)
    assert rig.robot.joint_tolerance_rad == 0.01
    assert rig.turntable.timeout_s == cfg.turntable.timeout_s


def test_capture_with_the_real_drivers(tmp_path, devices):
    emu, ctl, robot, table = devices
    cfg = hardware_config()
    prompts = []
    summary = run_capture(cfg, tmp_path / "s", yes=False, show_progress=False,
                          rig=Rig(robot, table, AngleCamera(table)), prompt=lambda m: prompts.append(m) or "")
    assert summary.complete and summary.captured == 16
    assert len(prompts) == 2 and "opaque twins" in prompts[1]  # the operator is asked before each phase
    s = RawSession.open(tmp_path / "s")
    assert verify_session(tmp_path / "s") == []
    for e in s.entries:
        assert e.extra["table_angle_reported_deg"] == pytest.approx(e.step * 90.0, abs=0.01)
        assert np.allclose(e.extra["q_actual"], s.info.arm_positions[e.arm].q, atol=1e-6)
        assert s.load_rgb(e.phase, e.arm, e.step)[0, 0, 0] == int(e.step * 90) % 256


def test_alarm_mid_run_stops_cleanly_and_resumes(tmp_path, devices):
    emu, ctl, robot, table = devices
    cfg = hardware_config(steps=4)
    cam = AngleCamera(table)
    grabs = {"n": 0}
    orig = cam.grab

    def grab(timeout_s):
        grabs["n"] += 1
        if grabs["n"] == 6:
            emu.trigger_alarm(1)  # hard limit while capturing
        return orig(timeout_s)

    cam.grab = grab
    with pytest.raises(TdofError) as e:
        run_capture(cfg, tmp_path / "s", yes=True, show_progress=False, rig=Rig(robot, table, cam),
                    resume_command="tdof20 capture run rig.toml --out s")
    msg = str(e.value)
    assert "ALARM" in msg and "resume with: tdof20 capture run rig.toml --out s" in msg
    kept = len(RawSession.open(tmp_path / "s").entries)
    assert 5 <= kept <= 6 and verify_session(tmp_path / "s")[0].startswith("missing frame")
    # the operator runs the same command again: the controller kept its ALARM:1 lock across the close
    # and the open (no reset on open); the driver resets it (ctrl-x) at connect and the run homes it
    assert emu.state == "Alarm"
    table2 = GrblTurntable(emu.port, timeout_s=3.0, feed_deg_per_s=3600.0, home=True)
    summary = run_capture(cfg, tmp_path / "s", yes=True, show_progress=False,
                          rig=Rig(robot, table2, AngleCamera(table2)))
    assert summary.present_before == kept and summary.captured == 16 - kept
    assert verify_session(tmp_path / "s") == []
    assert "$H" in emu.received and emu.state == "Idle"
