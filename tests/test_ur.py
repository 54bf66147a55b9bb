"""URRobot (ur_rtde backend) against fake RTDE interfaces: no robot needed."""

from __future__ import annotations

import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from fake_rtde import FakeRTDEControl, FakeRTDEReceive, FakeURController

from tdof20.capture.hardware.interfaces import HardwareError, SafetyStop
from tdof20.capture.hardware.ur import (
    JointTargetError,
    URRobot,
    T_to_tcp_pose,
    probe_rtde,
    tcp_pose_to_T,
)
from tdof20.errors import TdofError
from tdof20.sim.rig import UR5_HOME, ur5_fk

HOST = "10.20.30.40"
Q1 = UR5_HOME + np.array([0.10, -0.05, 0.08, 0.02, -0.03, 0.20])


@pytest.fixture
def make():
    made = []

    def _make(connect=True, **knobs):
        timeout = knobs.pop("connect_timeout_s", 1.0)
        extra = {k: knobs.pop(k) for k in ("reconnect_attempts", "joint_tolerance_rad", "settle_timeout_s")
                 if k in knobs}
        ctl = FakeURController(**knobs)
        robot = URRobot(HOST, connect_timeout_s=timeout, control_factory=ctl.control,
                        receive_factory=ctl.receive, **extra)
        made.append((ctl, robot))
        if connect:
            robot.connect()
        return ctl, robot

    yield _make
    for ctl, robot in made:
        robot.close()
        ctl.release()


def test_connect_move_state_round_trip(make):
    ctl, robot = make()
    assert [c[:2] for c in ctl.constructed] == [("receive", HOST), ("control", HOST)]
    assert all(c[2] == 125.0 for c in ctl.constructed)
    st = robot.state()
    np.testing.assert_allclose(st.q, UR5_HOME)
    robot.move_joints(Q1, speed=0.5, acceleration=1.0, timeout_s=5.0)
    assert ctl.moveJ_calls == [(Q1.tolist(), 0.5, 1.0, True)]   # asynchronous: watched, stoppable
    assert isinstance(ctl.moveJ_calls[0][0], list)
    st = robot.state()
    assert st.q.shape == (6,) and st.T_base_tcp.shape == (4, 4)
    np.testing.assert_allclose(st.q, Q1, atol=1e-12)
    np.testing.assert_allclose(st.T_base_tcp, ur5_fk(Q1), atol=1e-6)   # millimetres
    assert np.linalg.norm(st.T_base_tcp[:3, 3]) > 100.0


def test_tcp_pose_conversion_round_trip():
    T = ur5_fk(Q1)
    pose = T_to_tcp_pose(T)
    assert np.linalg.norm(pose[:3]) < 2.0            # metres
    np.testing.assert_allclose(tcp_pose_to_T(pose), T, atol=1e-9)


def test_constructor_that_never_answers_times_out_naming_the_host(make):
    ctl, robot = make(connect=False, hang_on_connect=True, connect_timeout_s=0.5)
    t0 = time.monotonic()
    with pytest.raises(HardwareError) as ei:
        robot.connect()
    assert time.monotonic() - t0 < 0.5 + 1.0
    msg = str(ei.value)
    assert HOST in msg and "did not answer" in msg and "remote control" in msg
    assert "\n" not in msg


def test_control_constructor_hangs_receive_is_released(make):
    ctl, robot = make(connect=False, hang_on_connect="control", connect_timeout_s=0.4)
    t0 = time.monotonic()
    with pytest.raises(HardwareError, match="control interface"):
        robot.connect()
    assert time.monotonic() - t0 < 1.4
    assert "receive.disconnect" in ctl.calls


def test_refused_connection_says_what_to_check(make):
    ctl, robot = make(connect=False, refuse_connect=True)
    with pytest.raises(HardwareError) as ei:
        robot.connect()
    assert HOST in str(ei.value) and "Connection refused" in str(ei.value) and "powered" in str(ei.value)


def test_other_safety_modes(make):
    ctl, robot = make(connect=False, safety_mode=5)
    with pytest.raises(SafetyStop, match="safeguard stop"):
        robot.connect()
    ctl, robot = make(safety_mode=2)          # reduced mode: allowed
    robot.move_joints(Q1, 0.5, 1.0, 5.0)
    ctl.safety_mode = 4
    with pytest.raises(SafetyStop, match="recovery mode"):
        robot.check_safety()


def test_powered_off_arm_is_refused(make):
    ctl, robot = make(robot_mode=3)
    with pytest.raises(HardwareError, match="power"):
        robot.move_joints(Q1, 0.5, 1.0, 5.0)
    assert ctl.moveJ_calls == []


def test_not_arrived_is_a_hardware_error(make):
    ctl, robot = make(arrive_offset=[0, 0, 0, 0, 0, 0.01], settle_timeout_s=0.1)
    with pytest.raises(HardwareError) as ei:
        robot.move_joints(Q1, 0.5, 1.0, 5.0)
    assert not isinstance(ei.value, SafetyStop)
    assert "did not arrive" in str(ei.value) and "joint 6" in str(ei.value)


def test_within_tolerance_is_fine(make):
    ctl, robot = make(arrive_offset=[0.001, 0, 0, 0, 0, -0.001])
    robot.move_joints(Q1, 0.5, 1.0, 5.0)


def test_moveJ_returns_false(make):
    ctl, robot = make(moveJ_returns_false=True)
    with pytest.raises(HardwareError, match="did not take the move .moveJ returned False") as ei:
        robot.move_joints(Q1, 0.5, 1.0, 5.0)
    assert not isinstance(ei.value, SafetyStop)


def test_connection_dropped_once_reconnects(make):
    ctl, robot = make(drop_connection_once=True, motion_time_s=0.1)
    robot.move_joints(Q1, 0.5, 1.0, 5.0)
    assert ctl.reconnects >= 1 and len(ctl.moveJ_calls) == 2
    np.testing.assert_allclose(robot.state().q, Q1)


def test_connection_dropped_between_calls_reconnects(make):
    ctl, robot = make()
    ctl.drop()
    np.testing.assert_allclose(robot.state().q, UR5_HOME)
    assert ctl.reconnects == 1


def test_connection_dropped_for_good(make):
    ctl, robot = make(drop_connection_for_good=True, reconnect_attempts=2)
    with pytest.raises(HardwareError, match="could not reconnect after 2 attempt") as ei:
        robot.move_joints(Q1, 0.5, 1.0, 5.0)
    assert not isinstance(ei.value, SafetyStop)
    assert ctl.reconnects == 2


@pytest.mark.parametrize("q", [np.zeros(5), np.zeros(7), [0, 0, 0, 0, 0, float("nan")], "abc", [[0] * 6]])
def test_bad_joint_target_before_any_motion(make, q):
    ctl, robot = make()
    with pytest.raises(JointTargetError) as ei:
        robot.move_joints(q, 0.5, 1.0, 5.0)
    assert isinstance(ei.value, TdofError) and isinstance(ei.value, ValueError)
    assert ctl.moveJ_calls == []


def test_bad_speed_acceleration_before_any_motion(make):
    ctl, robot = make()
    with pytest.raises(JointTargetError, match="speed"):
        robot.move_joints(Q1, 0.0, 1.0, 5.0)
    with pytest.raises(JointTargetError, match="acceleration"):
        robot.move_joints(Q1, 0.5, 100.0, 5.0)
    assert ctl.moveJ_calls == []


@pytest.mark.parametrize("value, words", [
    ("0.0", "must be in (0, 40] rad/s^2 (the UR5's joint acceleration limit), got 0.0"),
    ("-2.0", "got -2.0"),
    ("100.0", "must be in (0, 40] rad/s^2 (the UR5's joint acceleration limit), got 100.0"),
    ('"fast"', "must be a number"),
    ("nan", "must be a number"),
])
def test_stop_deceleration_of_the_rig_config_is_checked_in_one_line(tmp_path, value, words):
    from pathlib import Path

    from tdof20.capture import load_config

    text = (Path(__file__).resolve().parents[1] / "examples/real_rig.toml").read_text()
    assert text.count("\nstop_deceleration = 2.0 ") == 1
    path = tmp_path / "rig.toml"
    path.write_text(text.replace("\nstop_deceleration = 2.0 ", f"\nstop_deceleration = {value} "))
    with pytest.raises(TdofError) as ei:
        load_config(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: robot.stop_deceleration: ") and words in msg and "\n" not in msg


def test_stop_deceleration_default_and_the_drivers_own_check():
    from tdof20.capture import config_from_dict
    from tdof20.capture.hardware.registry import vendor

    cfg = config_from_dict({"robot": {"backend": "ur_rtde", "positions": [list(Q1)]},
                            "turntable": {"backend": "grbl"}, "camera": {"backend": "oakd"},
                            "session": {"objects": [3]}, "hand_eye": {"T_tcp_cam": list(np.eye(4).ravel())}},
                           "rig.toml")
    assert cfg.robot.stop_deceleration == 2.0      # ur_rtde's own stopJ default
    assert vendor("robot", "ur_rtde").make(cfg.robot).stop_deceleration == 2.0
    for bad in (0.0, -1.0, 41.0, float("nan")):
        with pytest.raises(ValueError, match="stop_deceleration must be in"):
            URRobot(HOST, stop_deceleration=bad)


def test_not_connected(make):
    ctl, robot = make(connect=False)
    with pytest.raises(HardwareError, match="not connected"):
        robot.state()
    robot.stop()
    robot.close()


def test_stop_and_close_never_raise(make):
    ctl, robot = make(raise_on_stop=True)
    robot.stop()
    robot.close()
    robot.close()
    robot.stop()
    assert "control.stopJ" in ctl.calls and "control.stopScript" in ctl.calls
    ctl, robot = make()
    robot.close()
    assert {"control.stopScript", "control.disconnect", "receive.disconnect"} <= set(ctl.calls)


def test_fakes_have_the_library_method_names():
    rtde_control = pytest.importorskip("rtde_control")
    rtde_receive = pytest.importorskip("rtde_receive")
    for fake, real in ((FakeRTDEControl, rtde_control.RTDEControlInterface),
                       (FakeRTDEReceive, rtde_receive.RTDEReceiveInterface)):
        for name in dir(fake):
            if not name.startswith("_") and callable(getattr(fake, name)):
                assert hasattr(real, name), f"{real.__name__} has no {name}"


def test_module_imports_without_ur_rtde():
    code = "import sys, tdof20.capture.hardware.ur; assert 'rtde_control' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


# ---------------------------------------------------------------- the pure-Python RTDE probe

def _server(reply: bool):
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    conns = []

    def serve():
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            conns.append(c)
            if reply:
                c.recv(5)
                c.sendall(struct.pack(">HBB", 4, 86, 1))

    threading.Thread(target=serve, daemon=True).start()
    return srv, conns


def test_probe_rtde():
    srv, conns = _server(reply=True)
    try:
        probe_rtde("127.0.0.1", 1.0, port=srv.getsockname()[1])
    finally:
        srv.close()
    srv, conns = _server(reply=False)
    try:
        t0 = time.monotonic()
        with pytest.raises(HardwareError, match="did not answer.*remote control"):
            probe_rtde("127.0.0.1", 0.3, port=srv.getsockname()[1])
        assert time.monotonic() - t0 < 1.0
    finally:
        srv.close()
        for c in conns:
            c.close()
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    with pytest.raises(HardwareError, match="cannot reach"):
        probe_rtde("127.0.0.1", 0.5, port=port)


def test_preflight_runs_before_the_constructors():
    srv, conns = _server(reply=False)
    ctl = FakeURController()
    robot = URRobot("127.0.0.1", connect_timeout_s=0.3, control_factory=ctl.control, receive_factory=ctl.receive,
                    preflight=True, rtde_port=srv.getsockname()[1], dashboard_port=srv.getsockname()[1])
    try:
        with pytest.raises(HardwareError, match="127.0.0.1.*did not answer on its dashboard port"):
            robot.connect()
        assert ctl.constructed == []
    finally:
        srv.close()
        for c in conns:
            c.close()
