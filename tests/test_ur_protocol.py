"""URRobot with the real ur_rtde library, over its wire protocol, against the emulated controller
(tests/ur_controller.py) on 127.0.0.1: the RTDE data channel, the script port running ur_rtde's
own uploaded control script, the dashboard server.

ur_rtde binds fixed ports (30004, 29999, 30003): every test of this kind lives in this one file,
which xdist runs in one worker (``--dist loadfile``), one test at a time."""

from __future__ import annotations

import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("rtde_receive")

from ur_controller import IDLE, POWER_OFF, EmulatedController  # noqa: E402

from tdof20.capture.hardware.interfaces import HardwareError, SafetyStop  # noqa: E402
from tdof20.capture.hardware.ur import URRobot  # noqa: E402
from tdof20.sim.rig import ur5_fk  # noqa: E402

HOST = "127.0.0.1"
ROOT = Path(__file__).resolve().parents[1]
POSITIONS = [np.array(q) for q in tomllib.loads((ROOT / "examples/real_rig.toml").read_text())["robot"]["positions"]]


@pytest.fixture
def rig():
    made = []

    def _make(connect=True, robot_options=None, **emulator_options):
        emu = EmulatedController(q0=tuple(POSITIONS[0]), **emulator_options)
        robot = URRobot(HOST, **{"connect_timeout_s": 5.0, **(robot_options or {})})
        made.append((emu, robot))
        if connect:
            robot.connect()
        return emu, robot

    yield _make
    for emu, robot in made:
        robot.close()
        emu.close()


def _move_time(d: float, v: float, a: float) -> float:
    """The time of a trapezoidal (or triangular) profile over ``d`` rad."""
    return d / v + v / a if d >= v * v / a else 2 * np.sqrt(d / a)


def test_the_four_arm_positions_read_back_exactly_in_the_profiles_time(rig):
    emu, robot = rig()
    assert emu.get("script_errors") == [] and len(emu.get("scripts")) == 1
    for q in POSITIONS[1:] + POSITIONS[:1]:
        q_before = robot.state().q
        t0 = time.monotonic()
        robot.move_joints(q, speed=1.5, acceleration=6.0, timeout_s=10.0)
        took = time.monotonic() - t0
        expected = _move_time(float(np.abs(q - q_before).max()), 1.5, 6.0)
        assert expected - 0.02 < took < expected + 0.3, (took, expected)
        st = robot.state()
        np.testing.assert_array_equal(st.q, q)
        np.testing.assert_allclose(st.T_base_tcp, ur5_fk(q), atol=1e-9)   # mm; the emulator's own DH
    # moveJ went asynchronously through the script (command 1), never blocking it
    assert [c for _, c in emu.get("commands")].count(1) == 4


def test_a_timed_out_move_stops_the_arm_and_says_where_it_stands(rig):
    emu, robot = rig()
    target = POSITIONS[0] + np.array([0, 0, 0, 0, 0, 1.5])
    t0 = time.monotonic()
    with pytest.raises(HardwareError) as ei:
        robot.move_joints(target, speed=1.0, acceleration=4.0, timeout_s=0.5)
    took = time.monotonic() - t0
    msg = str(ei.value)
    assert "did not finish within 0.5 s" in msg and "the arm was stopped (stopJ at 2 rad/s^2" in msg
    assert "stands still at joints" in msg and "rad from the target" in msg and "\n" not in msg
    assert took < 0.5 + 1.0 / 2.0 + 0.4          # the deadline, a 1 rad/s -> 0 stop at 2 rad/s^2, margin
    assert ei.value.retryable                    # the run may take the move again
    # the controller says so too: the arm stands still now and stays where it stopped
    assert emu.get("leading_speed") == 0.0
    q_stop = emu.get("q")
    time.sleep(0.5)
    np.testing.assert_allclose(emu.get("q"), q_stop, atol=1e-12)
    assert abs(q_stop[5] - POSITIONS[0][5]) < 1.0          # it did not go on to the target
    assert 34 in [c for _, c in emu.get("commands")]       # stopJ reached the script
    # the next move works
    robot.move_joints(POSITIONS[1], speed=3.0, acceleration=20.0, timeout_s=5.0)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[1])


def test_the_rigs_stop_deceleration_is_what_stopj_brakes_at(tmp_path):
    """robot.stop_deceleration of the rig's config (examples/real_rig.toml, set to 8 rad/s^2) goes
    from the driver the registry builds through ur_rtde's stopJ to the controller, which brakes at
    it: a timed-out move at 1 rad/s stands still 0.125 s after the stop (the default 2: 0.5 s)."""
    from tdof20.capture import load_config
    from tdof20.capture.hardware.registry import vendor

    text = (ROOT / "examples/real_rig.toml").read_text()
    assert 'host = "192.168.1.10"' in text and "\nstop_deceleration = 2.0 " in text
    path = tmp_path / "rig.toml"
    path.write_text(text.replace('host = "192.168.1.10"', f'host = "{HOST}"')
                    .replace("\nstop_deceleration = 2.0 ", "\nstop_deceleration = 8.0 "))
    cfg = load_config(path)
    assert cfg.robot.stop_deceleration == 8.0
    emu = EmulatedController(q0=tuple(POSITIONS[0]))
    robot = vendor("robot", cfg.robot.backend).make(cfg.robot)
    try:
        robot.connect()
        target = POSITIONS[0] + np.array([0, 0, 0, 0, 0, 1.5])
        with pytest.raises(HardwareError) as ei:
            robot.move_joints(target, speed=1.0, acceleration=4.0, timeout_s=0.5)
        assert "the arm was stopped (stopJ at 8 rad/s^2" in str(ei.value)
        (t_stop, dec), = emu.get("stops")                # what the control script read from its registers
        assert dec == 8.0
        after = [(t, v) for t, _, v in emu.get("history") if t >= t_stop]
        assert after[0][1] == pytest.approx(1.0, abs=0.05)          # cruising at 1 rad/s when told
        t_still = next(t for t, v in after if v == 0.0)
        assert t_still - t_stop == pytest.approx(1.0 / 8.0, abs=0.02)
        braking = np.array([(t, v) for t, v in after if 0.1 < v < 0.9])
        assert np.polyfit(braking[:, 0], braking[:, 1], 1)[0] == pytest.approx(-8.0, rel=0.05)
    finally:
        robot.close()
        emu.close()


def test_a_stalled_arm_times_out_stopped(rig):
    emu, robot = rig()
    emu.set(stalled=True)
    with pytest.raises(HardwareError, match=r"did not finish within 0.4 s; the arm was stopped .* stands still"):
        robot.move_joints(POSITIONS[1], speed=1.0, acceleration=4.0, timeout_s=0.4)


def _after(emu: EmulatedController, condition: str, fault: str) -> threading.Thread:
    def run():
        emu.wait_until(condition, 10.0)
        emu.call(fault)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


MOVING = "e.leading_speed() > 0.2"


def test_protective_stop_during_a_move_is_said_and_resumed(rig):
    emu, robot = rig(unlock_delay_s=1.0)
    _after(emu, MOVING, "protective_stop")
    with pytest.raises(SafetyStop) as ei:
        robot.move_joints(POSITIONS[2], speed=1.0, acceleration=4.0, timeout_s=10.0)
    msg = str(ei.value)
    assert "protective stop: clear it on the teach pendant" in msg and "during the move" in msg
    assert ei.value.retryable is False
    moves = [c for _, c in emu.get("commands")].count(1)
    with pytest.raises(SafetyStop, match="protective stop"):   # still stopped: refused before moving
        robot.move_joints(POSITIONS[2], speed=1.0, acceleration=4.0, timeout_s=10.0)
    assert [c for _, c in emu.get("commands")].count(1) == moves   # no moveJ sent
    t_stop = time.monotonic()
    robot.resume()
    # PolyScope refused the unlock for the first second; then the script was uploaded again
    log = emu.get("dashboard_log")
    assert log.count("unlock protective stop") >= 2 and time.monotonic() - t_stop > 0.5
    assert len(emu.get("scripts")) == 2 and emu.get("runtime_state") == 2
    robot.move_joints(POSITIONS[2], speed=3.0, acceleration=20.0, timeout_s=5.0)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[2])


def test_emergency_stop_is_said_and_resumed_once_released(rig):
    emu, robot = rig()
    _after(emu, MOVING, "emergency_stop")
    with pytest.raises(SafetyStop, match="emergency stop: an emergency-stop button is pressed"):
        robot.move_joints(POSITIONS[3], speed=1.0, acceleration=4.0, timeout_s=10.0)
    with pytest.raises(SafetyStop, match="still stopped: emergency stop"):
        robot.resume(timeout_s=1.0)
    emu.release_emergency_stop()
    robot.resume()                                   # powers on, releases the brakes, uploads the script
    log = emu.get("dashboard_log")
    assert "power on" in log and "brake release" in log and emu.get("robot_mode") == 7
    robot.move_joints(POSITIONS[3], speed=3.0, acceleration=20.0, timeout_s=5.0)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[3])


@pytest.mark.parametrize("options, words", [
    (dict(robot_mode=IDLE), "the arm's brakes are on: release them on the teach pendant"),
    (dict(robot_mode=POWER_OFF), "the arm is powered off: power it on and release the brakes"),
    (dict(safety_mode=3), "protective stop: clear it on the teach pendant"),
    (dict(safety_mode=7), "emergency stop: an emergency-stop button is pressed"),
])
def test_an_arm_not_ready_at_connect_is_said_before_any_interface_opens(rig, options, words):
    emu, robot = rig(connect=False, **options)
    t0 = time.monotonic()
    with pytest.raises(HardwareError) as ei:
        robot.connect()
    assert time.monotonic() - t0 < 1.0                   # not ur_rtde's 5 s wait for the script
    msg = str(ei.value)
    assert words in msg and "found at connect, before any motion" in msg and "\n" not in msg
    assert isinstance(ei.value, SafetyStop) == ("safety_mode" in options)
    assert emu.get("scripts") == []                      # the control interface was never opened


def test_a_silent_controller_at_connect_errors_within_the_timeout(rig):
    emu, robot = rig(connect=False, silent=True, robot_options={"connect_timeout_s": 1.0})
    t0 = time.monotonic()
    with pytest.raises(HardwareError, match=r"127.0.0.1 did not answer on its dashboard port 29999 within 1 s"):
        robot.connect()
    assert time.monotonic() - t0 < 1.5


def test_a_frozen_stream_is_an_error_never_a_stale_pose(rig):
    emu, robot = rig()
    robot.state()
    emu.freeze()
    t0 = time.monotonic()
    with pytest.raises(HardwareError, match="no new state from the controller for 0.2") as ei:
        robot.state()
    assert time.monotonic() - t0 < 0.6 and "no stale pose is used" in str(ei.value)
    emu.freeze(False)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[0])


def test_a_stream_frozen_during_a_move_stops_it(rig):
    emu, robot = rig()
    _after(emu, MOVING, "freeze")
    with pytest.raises(HardwareError, match="no new state from the controller .* during a move"):
        robot.move_joints(POSITIONS[1], speed=1.0, acceleration=4.0, timeout_s=10.0)


def test_every_pose_is_newer_than_the_call(rig):
    emu, robot = rig()
    for _ in range(5):
        t_call = emu.get("timestamp")
        robot.state()
        # the state came from a package the controller sent after the call began
        assert robot._last_ts[0] > t_call


def test_a_network_drop_between_calls_is_survived(rig):
    """The network is down for 0.5 s (every connection reset, new ones refused), the controller
    stays up. (A reset with the network up at once is not tested: ur_rtde 1.6.5's control
    interface then reconnects from its own receive thread again and again and crashes the process.)"""
    emu, robot = rig()
    emu.drop(down_s=0.5)
    time.sleep(1.0)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[0])
    robot.move_joints(POSITIONS[1], speed=3.0, acceleration=20.0, timeout_s=5.0)
    np.testing.assert_array_equal(robot.state().q, POSITIONS[1])


def test_a_capture_session_resumes_across_a_protective_stop(rig, tmp_path):
    """A bump during the second arm move: the run pauses, the operator presses Enter, the backend
    unlocks the stop and restarts the script, the move is taken again and every frame is there."""
    from tdof20.capture import config_from_dict, run_capture, verify_session
    from tdof20.capture.hardware.interfaces import RGBDCamera, RGBDFrame, Turntable
    from tdof20.capture.rig import Rig
    from tdof20.sim.rig import RigLayout

    class Table(Turntable):
        name = "test table"
        a = 0.0

        def connect(self): pass
        def close(self): pass
        def home(self, timeout_s): self.a = 0.0
        def move_to(self, angle_deg, timeout_s):
            self.a = angle_deg
            return angle_deg
        def angle(self): return self.a

    class Camera(RGBDCamera):
        name = "test camera"

        def connect(self): pass
        def close(self): pass
        def intrinsics(self):
            return {"K": [60.0, 0, 31.5, 0, 60.0, 23.5, 0, 0, 1], "width": 64, "height": 48, "depth_scale": 1.0}
        def grab(self, timeout_s):
            t = time.time()
            return RGBDFrame(np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 500, np.uint16), t, t)

    emu, robot = rig(connect=False, unlock_delay_s=1.0)
    cfg = config_from_dict({
        "session": {"scene_id": "multi/08", "objects": [3, 7, 12]},
        "hand_eye": {"T_tcp_cam": list(np.asarray(RigLayout().T_tcp_cam).reshape(-1))},
        "robot": {"backend": "ur_rtde", "host": HOST, "positions": [q.tolist() for q in POSITIONS[:2]],
                  "speed": 3.0, "acceleration": 20.0, "move_timeout_s": 10.0},
        "turntable": {"backend": "grbl", "port": "unused", "steps": 2, "step_deg": 90.0},
        "camera": {"backend": "oakd", "width": 64, "height": 48},
    }, "rig.toml")
    _after(emu, "sum(1 for _, c in e.commands if c == 1) >= 2 and e.leading_speed() > 0.2", "protective_stop")
    prompts = []
    summary = run_capture(cfg, tmp_path / "s", prompt=lambda m: prompts.append(m) or "", show_progress=False,
                          rig=Rig(robot=robot, turntable=Table(), camera=Camera()))
    assert summary.complete and summary.captured == summary.planned == 8
    assert any("safety stop during moveJ to arm position" in w for w in summary.warnings)
    assert any("Clear the stop" in p for p in prompts)
    assert len(emu.get("scripts")) == 2                      # the control script was uploaded again
    assert verify_session(tmp_path / "s") == []
