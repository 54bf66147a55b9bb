"""The GRBL turntable driver against the GRBL 1.1 emulator on a real pseudo-terminal."""

from __future__ import annotations

import threading
import time

import pytest

from tdof20.capture.hardware.grbl import (ALARM_CODES, ERROR_CODES, GrblAlarm, GrblError, GrblTurntable,
                                          describe_alarm, describe_error, parse_status)
from tdof20.capture.hardware.grbl_timing import move_time
from tdof20.capture.hardware.interfaces import HardwareError
from tests.grbl_support import ACCEL, SLOW_HOMING, SPEED, emu_factory, table_for  # noqa: F401 (a fixture)

pytestmark = pytest.mark.timeout(20)


def test_parse_status_and_tables():
    st = parse_status("<Idle|MPos:12.000,0.000,0.000|FS:0,0>")
    assert st.state == "Idle" and st.mpos == (12.0, 0.0, 0.0) and st.wpos is None and st.feed == 0
    st = parse_status("<Hold:1|WPos:-1.500,2.000,3.000|Bf:15,128|FS:500,0|WCO:1.000,0.000,0.000|Pn:X>")
    assert (st.state, st.substate, st.wpos, st.wco) == ("Hold", 1, (-1.5, 2.0, 3.0), (1.0, 0.0, 0.0))
    assert parse_status("ok") is None and parse_status("<Idle|MPos:a,b>") is None
    assert all(k in ALARM_CODES for k in range(1, 10))
    assert all(k in ERROR_CODES for k in (1, 2, 3, 9, 15, 20, 22, 24))
    assert "hard limit" in describe_alarm(1) and "homing" in describe_alarm(9)
    assert "homing required" in describe_alarm(None)
    assert "unknown error 99" in describe_error(99) and "feed rate" in describe_error(22)


def test_connect_home_and_moves_take_the_emulated_time(emu_factory):
    emu = emu_factory(start_alarm=0)                 # power-up homing lock, like $22=1
    table = table_for(emu, home=True)
    table.connect()
    try:
        t = time.monotonic()
        table.home(2.0)
        assert 0.09 <= time.monotonic() - t < 1.0
        assert table.angle() == pytest.approx(0.0, abs=1e-3)
        assert emu.mpos[0] == pytest.approx(-1.0)    # homed machine position -$27; G92 made it 0 deg
        assert emu.state == "Idle"
        previous = 0.0
        for target in (90.0, 45.0, 180.0, 0.9):
            expected = move_time(target - previous, SPEED, ACCEL)
            t = time.monotonic()
            got = table.move_to(target, timeout_s=3.0)
            dt = time.monotonic() - t
            assert got == pytest.approx(target, abs=0.005)
            assert table.angle() == pytest.approx(target, abs=0.005)
            assert emu.wpos[0] == pytest.approx(target, abs=0.005)
            assert 0.9 * expected <= dt <= expected + 0.3, (target, dt, expected)
            previous = target
        assert "G90 G1 X90.0000 F21600.000" in emu.received
        assert table.move_to(0.9, timeout_s=1.0) == pytest.approx(0.9, abs=0.005)   # already there
    finally:
        table.close()


def test_units_per_degree_scales_commands_and_reports(emu_factory):
    emu = emu_factory(report_wpos=True)              # $10=0: WPos reports
    table = table_for(emu, units_per_degree=2.5, feed_deg_per_s=100.0)
    table.connect()
    try:
        t = time.monotonic()
        assert table.move_to(36.0, timeout_s=3.0) == pytest.approx(36.0, abs=0.005)
        dt = time.monotonic() - t
        expected = move_time(90, 250, ACCEL)
        assert 0.9 * expected <= dt <= expected + 0.3          # 90 units at up to 250 units/s
        assert emu.wpos[0] == pytest.approx(90.0, abs=0.005)
        assert "G90 G1 X90.0000 F15000.000" in emu.received    # 100 deg/s * 2.5 * 60
        assert table.angle() == pytest.approx(36.0, abs=0.005)
    finally:
        table.close()


@pytest.mark.parametrize("code, words", [(1, "hard limit"), (9, "limit switch was not found"),
                                         (0, "homing required")])
def test_alarm_at_start_is_reported_in_words_and_refuses_to_move(emu_factory, code, words):
    # GRBL prints ALARM:N once, as it boots: only a board that resets when its port opens (DTR, an
    # Arduino Uno) prints it to this host, and again at the second connect
    emu = emu_factory(start_alarm=code, auto_reset=True)
    table = table_for(emu)
    with pytest.raises(GrblAlarm) as err:
        table.connect()
    assert not err.value.retryable
    assert words in str(err.value) and "$X" in str(err.value) and emu.port in str(err.value)
    assert not table.connected
    # with homing planned the connect goes through, but GRBL refuses G-code until homed
    table = table_for(emu, home=True)
    table.connect()
    try:
        with pytest.raises(HardwareError) as err:
            table.move_to(90.0, timeout_s=1.0)
        assert not err.value.retryable
        if code:                                      # the driver saw ALARM:N: it does not even try
            assert isinstance(err.value, GrblAlarm) and words in str(err.value)
        else:                                         # the code-less lock: GRBL answers error:9
            assert isinstance(err.value, GrblError) and err.value.code == 9 and "G-code lock" in str(err.value)
        assert emu.wpos[0] == pytest.approx(0.0) and emu.state == "Alarm"
        table.home(2.0)
        assert table.move_to(10.0, timeout_s=1.0) == pytest.approx(10.0, abs=0.005)
    finally:
        table.close()


def test_alarm_mid_move_stops_the_move(emu_factory):
    emu = emu_factory()
    table = table_for(emu, feed_deg_per_s=180.0)
    table.connect()
    try:
        timer = threading.Timer(0.15, emu.trigger_alarm, (1,))
        timer.start()
        t = time.monotonic()
        with pytest.raises(HardwareError) as err:
            table.move_to(180.0, timeout_s=5.0)
        timer.join()
        assert time.monotonic() - t < 0.6
        assert not err.value.retryable
        assert "ALARM:1" in str(err.value) and "hard limit" in str(err.value)
        assert emu.state == "Alarm" and 10.0 < emu.wpos[0] < 90.0
        with pytest.raises(GrblAlarm):                # still in alarm: refuses to move
            table.move_to(0.0, timeout_s=1.0)
    finally:
        table.stop()
        table.close()


def test_alarm_during_homing(emu_factory):
    emu = emu_factory(settings=SLOW_HOMING)
    table = table_for(emu)
    table.connect()
    try:
        threading.Timer(0.1, emu.trigger_alarm, (9,)).start()
        with pytest.raises(GrblAlarm) as err:
            table.home(3.0)
        assert err.value.code == 9 and "homing fail" in str(err.value)
    finally:
        table.close()


def test_error_replies_are_reported_with_their_meaning(emu_factory):
    emu = emu_factory(error_on={"G92": 20})
    table = table_for(emu)
    table.connect()
    try:
        with pytest.raises(GrblError) as err:
            table.home(2.0)                           # homing ends at -1 unit: G92 X0 is needed
        assert err.value.code == 20 and "unsupported command" in str(err.value)
        assert "G92 X0" in str(err.value) and not err.value.retryable
    finally:
        table.close()
    emu = emu_factory(error_on={"G21": 99})
    with pytest.raises(GrblError, match=r"error:99 \(unknown error 99"):
        table_for(emu).connect()


def test_homing_disabled_takes_the_current_position_as_zero(emu_factory):
    emu = emu_factory(homing_enabled=False)
    table = table_for(emu)
    table.connect()
    try:
        table.move_to(30.0, timeout_s=1.0)
        table.home(1.0)                               # $H -> error:5: G92 X0 here
        assert table.angle() == pytest.approx(0.0, abs=1e-3) and emu.mpos[0] == pytest.approx(30.0)
        assert table.move_to(-10.0, timeout_s=1.0) == pytest.approx(-10.0, abs=0.005)
        assert emu.mpos[0] == pytest.approx(20.0)
    finally:
        table.close()


def test_lost_answer_is_resynced_without_resending_moves(emu_factory):
    emu = emu_factory()
    table = table_for(emu, timeout_s=1.5)
    table.connect()
    try:
        emu.drop_replies(1)                           # the "ok" to the move is lost
        t = time.monotonic()
        assert table.move_to(20.0, timeout_s=3.0) == pytest.approx(20.0, abs=0.005)
        assert time.monotonic() - t < 1.5
        # the move was executed once or re-sent (absolute: same target); the table is there
        assert emu.wpos[0] == pytest.approx(20.0, abs=0.005)
        assert "" in emu.received                    # the re-sync empty line
    finally:
        table.close()


def test_silent_controller_times_out(emu_factory):
    emu = emu_factory(silent=True)
    table = table_for(emu, timeout_s=0.5)
    t = time.monotonic()
    with pytest.raises(HardwareError) as err:
        table.connect()
    assert time.monotonic() - t < 0.5 + 1.0
    assert emu.port in str(err.value) and "status report" in str(err.value)
    assert err.value.retryable and not table.connected


def test_missing_port():
    table = GrblTurntable("/dev/tty-no-such-grbl", timeout_s=0.5)
    t = time.monotonic()
    with pytest.raises(HardwareError) as err:
        table.connect()
    assert time.monotonic() - t < 1.0
    assert "/dev/tty-no-such-grbl" in str(err.value) and "does not exist" in str(err.value)


def test_stop_keeps_the_angle_and_the_table_goes_on(emu_factory):
    emu = emu_factory()
    table = table_for(emu)
    table.connect()
    try:
        table.home(2.0)                               # G92 offset in place
        table.move_to(30.0, timeout_s=1.0)
        table.stop()                                  # idle: reset keeps the position; G92 re-applied
        assert table.angle() == pytest.approx(30.0, abs=0.005)
        assert table.move_to(60.0, timeout_s=1.0) == pytest.approx(60.0, abs=0.005)
        assert emu.mpos[0] == pytest.approx(59.0, abs=0.005)
    finally:
        table.close()


def test_stop_from_another_thread_interrupts_a_move(emu_factory):
    emu = emu_factory()
    table = table_for(emu, feed_deg_per_s=90.0)
    table.connect()
    try:
        box: dict = {}

        def move():
            try:
                table.move_to(180.0, timeout_s=5.0)
            except HardwareError as e:
                box["error"] = e

        th = threading.Thread(target=move)
        th.start()
        time.sleep(0.2)
        t = time.monotonic()
        table.stop()
        th.join(2.0)
        assert time.monotonic() - t < 1.0 and not th.is_alive()
        assert "stop()" in str(box["error"])
        stopped_at = table.angle()                    # hold completed before the reset: no alarm
        assert 5.0 < stopped_at < 60.0 and emu.state == "Idle"
        assert table.move_to(0.0, timeout_s=2.0) == pytest.approx(0.0, abs=0.005)
    finally:
        table.close()


def test_stop_and_close_never_raise(emu_factory):
    table = GrblTurntable("/dev/tty-no-such-grbl")
    table.stop()
    table.close()                                     # never connected
    emu = emu_factory()
    table = table_for(emu)
    table.connect()
    emu.stop()                                        # the controller is gone
    t = time.monotonic()
    table.stop()
    table.close()
    table.stop()
    table.close()
    assert time.monotonic() - t < 2.0
    with pytest.raises(HardwareError):
        table.connect()                               # its port is gone too


def test_not_connected():
    table = GrblTurntable("/dev/tty-no-such-grbl")
    with pytest.raises(HardwareError, match="not connected"):
        table.move_to(1.0, timeout_s=1.0)
    with pytest.raises(ValueError, match="units_per_degree"):
        GrblTurntable("/dev/null", units_per_degree=0)


def test_move_that_does_not_finish_in_time_is_retryable(emu_factory):
    emu = emu_factory()
    table = table_for(emu, feed_deg_per_s=90.0)
    table.connect()
    try:
        t = time.monotonic()
        with pytest.raises(HardwareError) as err:
            table.move_to(60.0, timeout_s=0.3)       # needs 0.67 s
        assert 0.3 <= time.monotonic() - t < 0.8
        assert err.value.retryable and "did not finish within 0.3 s" in str(err.value)
        assert table.move_to(60.0, timeout_s=3.0) == pytest.approx(60.0, abs=0.005)   # the retry
    finally:
        table.close()


def test_emulator_speaks_grbl(emu_factory):
    import serial

    emu = emu_factory(auto_reset=True)                # a board that resets on open: its banner comes
    with serial.Serial(emu.port, 115200, timeout=0.05) as ser:
        buf = bytearray()

        def lines_until(pred, timeout=1.0):
            got, end = [], time.monotonic() + timeout
            while time.monotonic() < end:
                buf.extend(ser.read(256))
                while b"\n" in buf:
                    line, _, rest = bytes(buf).partition(b"\n")
                    buf[:] = rest
                    if line.strip():
                        got.append(line.strip().decode())
                        if pred(got[-1]):
                            return got
            raise AssertionError(f"timed out; got {got}")

        def ask(line):
            ser.write(line.encode() + b"\n")
            return lines_until(lambda s: s == "ok" or s.startswith("error:"))

        def status():
            ser.write(b"?")
            return parse_status(lines_until(lambda s: s.startswith("<"))[-1])

        assert "Grbl 1.1h ['$' for help]" in lines_until(lambda s: s.startswith("Grbl"))
        assert ask("G1 X1") == ["error:22"]                  # no feed rate yet
        assert ask("G2 X1 Y1 I1") == ["error:20"]            # arcs unsupported here
        assert ask("$Q") == ["error:3"] and ask("X1Q2") == ["error:20"] and ask("1") == ["error:1"]
        assert ask("G91 G0 X10 (comment)") == ["ok"]
        time.sleep(move_time(10, SPEED, ACCEL) + 0.05)
        assert status().mpos[0] == pytest.approx(10.0)
        assert ask("G92 X0") == ["ok"]
        st = status()
        assert st.wco[0] == pytest.approx(10.0) and st.state == "Idle"   # WCO right after a change
        assert ask("G90 G1 X20 F1200") == ["ok"]            # 20 units/s: 1 s
        time.sleep(0.1)
        assert status().state == "Run"
        ser.write(b"!")
        time.sleep(0.1)
        st = status()
        assert (st.state, st.substate) == ("Hold", 0)
        ser.write(b"~")
        time.sleep(0.05)
        assert status().state == "Run"
        ser.write(b"\x18")                                   # reset in motion: ALARM:3
        got = lines_until(lambda s: "unlock" in s)
        assert got[0] == "ALARM:3" and any(s.startswith("Grbl") for s in got)
        assert ask("G0 X0") == ["error:9"] and status().state == "Alarm"
        assert ask("$X") == ["[MSG:Caution: Unlocked]", "ok"] and status().state == "Idle"
