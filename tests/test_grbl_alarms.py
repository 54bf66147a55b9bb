"""The GRBL turntable driver through what the real firmware (GRBL 1.1h) does around alarms, homing and
old versions, against the emulator on a real pseudo-terminal (issue 22, G1-G6), and the emulator's
faithfulness on those points."""

from __future__ import annotations

import functools
import threading
import time

import pytest

from tdof20.capture.hardware.grbl import GrblAlarm, GrblTurntable, parse_status
from tdof20.capture.hardware.grbl_emulator import GrblEmulator
from tdof20.capture.hardware.grbl_timing import homing_worst_case_s, move_time
from tdof20.capture.hardware.interfaces import HardwareError
from tdof20.capture.hardware.grbl_emulator import LimitSwitch
from tests.grbl_support import ACCEL, SLOW_HOMING, SPEED, Link, emu_factory  # noqa: F401 (a fixture)
from tests.grbl_support import table_for as grbl_table_for

pytestmark = pytest.mark.timeout(30)

# a homing cycle that searches 1.5 x 2 units at 10 units/s: ALARM:9 after about 0.3 s without a switch
SHORT_SEARCH = {25: 600.0, 24: 600.0, 26: 10, 130: 2.0, 131: 2.0, 132: 2.0}


table_for = functools.partial(grbl_table_for, timeout_s=3.0)  # alarms and resets take longer


def homing_fails(emu_factory) -> tuple[GrblEmulator, GrblTurntable]:
    """A table whose homing switch is never found: $H homes Z, then ends in ALARM:9 searching X and Y
    (no switch on X), then GRBL resets itself."""
    emu = emu_factory(switches={"Y": 2.0, "Z": 2.0}, settings=SHORT_SEARCH)
    table = table_for(emu)
    table.connect()
    with pytest.raises(GrblAlarm) as err:
        table.home(3.0)
    assert err.value.code == 9 and "not found" in str(err.value)
    return emu, table


# ---------------------------------------------------------------------- the firmware's normal run

def test_capture_sequence_with_grbl_default_acceleration(emu_factory):
    """Connect, home, 20 x 0.9 deg, 5 x 18 deg, stop: the angles exact to a motor step."""
    emu = emu_factory(start_alarm=0, accel_units_per_s2=None)          # GRBL's own ratio: 432 units/s²
    table = table_for(emu, home=True)
    table.connect()
    try:
        table.home(3.0)
        for i in range(1, 21):
            assert table.move_to(0.9 * i, 3.0) == pytest.approx(0.9 * i, abs=0.004)
        for i in range(1, 6):
            assert table.move_to(18.0 + 18.0 * i, 3.0) == pytest.approx(18.0 + 18.0 * i, abs=0.004)
        table.stop()
        assert table.angle() == pytest.approx(108.0, abs=0.004)
        assert table.move_to(0.0, 3.0) == pytest.approx(0.0, abs=0.004)
    finally:
        table.close()


# ---------------------------------------------------------------------- G1: the $H's late "ok"

def test_g1_late_ok_after_homing_alarm_is_not_taken_for_the_next_answer(emu_factory):
    emu, table = homing_fails(emu_factory)
    try:
        table.command("$130=201")                     # sent at once: GRBL is still in its 0.5 s pause
        table.command("$$")
        assert emu.settings[130] == 201 and table.settings[130] == 201
        assert "$130=201" in emu.received
    finally:
        table.close()


def test_g1_stop_during_homing(emu_factory):
    """stop() from another thread during $H: the reset gives ALARM:6, the pause, the $H's ok, the banner."""
    emu = emu_factory(settings=SLOW_HOMING)
    table = table_for(emu)
    table.connect()
    try:
        box: dict = {}

        def home():
            try:
                table.home(5.0)
            except HardwareError as e:
                box["error"] = e

        th = threading.Thread(target=home)
        th.start()
        time.sleep(0.2)
        t = time.monotonic()
        table.stop()
        th.join(3.0)
        assert time.monotonic() - t < 1.5 and "stop()" in str(box["error"])
        table.command("$130=201")
        table.command("$$")
        assert emu.settings[130] == 201 and table.settings[130] == 201
        assert emu.state == "Alarm"
        table.home(3.0)
        assert table.move_to(10.0, 2.0) == pytest.approx(10.0, abs=0.005)
    finally:
        table.close()


# ---------------------------------------------------------------------- G2: $X in the pause

def test_g2_unlock_right_after_a_homing_alarm(emu_factory):
    emu, table = homing_fails(emu_factory)
    try:
        with pytest.raises(GrblAlarm) as err:
            table.move_to(5.0, 2.0)
        assert "ALARM:9" in str(err.value) and "stop()" not in str(err.value)
        table.unlock()                                # after the pause: heard
        assert emu.state == "Idle"
        assert table.move_to(5.0, 2.0) == pytest.approx(5.0, abs=0.005)
    finally:
        table.close()


def test_g2_unlock_sent_at_once(emu_factory):
    emu, table = homing_fails(emu_factory)
    try:
        table.unlock()                                # would fall in GRBL's pause
        assert emu.state == "Idle" and emu.received.count("$X") == 1
        assert table.move_to(-5.0, 2.0) == pytest.approx(-5.0, abs=0.005)
    finally:
        table.close()


# ---------------------------------------------------------------------- G3: hard and soft limits lock

def test_g3_hard_limit_needs_a_reset(emu_factory):
    emu = emu_factory()
    table = table_for(emu, feed_deg_per_s=90.0)
    table.connect()
    try:
        table.home(2.0)
        threading.Timer(0.2, emu.trigger_alarm, (1,)).start()
        with pytest.raises(GrblAlarm) as err:
            table.move_to(90.0, 5.0)
        msg = str(err.value)
        assert "ALARM:1" in msg and "reset" in msg and "unlock it with $X" not in msg and err.value.locked
        t = time.monotonic()
        with pytest.raises(GrblAlarm) as err:         # no status report while locked: at once
            table.status()
        assert time.monotonic() - t < 1.0 and err.value.locked
        stopped_at = emu.mpos[0] + 1.0                # machine position -1 is 0 deg after homing
        t = time.monotonic()
        table.unlock()                                # ctrl-x, then $X
        assert time.monotonic() - t < 1.5 and emu.state == "Idle"
        assert table.angle() == pytest.approx(stopped_at, abs=0.005)   # the G92 offset is back
        assert table.move_to(0.0, 2.0) == pytest.approx(0.0, abs=0.005)
    finally:
        table.close()


def test_g3_soft_limit_needs_a_reset_and_home_does_it(emu_factory):
    emu = emu_factory(soft_limits=True)
    table = table_for(emu)
    table.connect()
    try:
        table.home(2.0)
        assert table.move_to(-30.0, 2.0) == pytest.approx(-30.0, abs=0.005)
        with pytest.raises(GrblAlarm) as err:
            table.move_to(10.0, 2.0)                  # machine +9: beyond the travel [-200, 0]
        assert err.value.code == 2 and "soft limit" in str(err.value) and "unlocking is safe" not in str(err.value)
        time.sleep(0.7)                               # the lock is on: GRBL hears nothing but ctrl-x
        assert emu.state == "Alarm"
        with pytest.raises(GrblAlarm):
            table.move_to(0.0, 2.0)
        t = time.monotonic()
        table.home(2.0)                               # resets first
        assert time.monotonic() - t < 1.5
        assert table.move_to(-10.0, 2.0) == pytest.approx(-10.0, abs=0.005)
    finally:
        table.close()


# ---------------------------------------------------------------------- G4: a lock that outlives close()

@pytest.mark.parametrize("home", [True, False])
def test_g4_connect_to_a_controller_locked_by_a_soft_limit(emu_factory, home):
    emu = emu_factory(auto_reset=False, soft_limits=True)
    table = table_for(emu)
    table.connect()
    table.home(2.0)
    with pytest.raises(GrblAlarm):
        table.move_to(10.0, 2.0)
    table.close()                                     # the board keeps its lock: no reset on open
    time.sleep(0.6)
    table = table_for(emu, home=home)
    t = time.monotonic()
    try:
        if not home:
            with pytest.raises(GrblAlarm) as err:
                table.connect()
            assert time.monotonic() - t < 2.5
            assert "reset" in str(err.value) and "powered" not in str(err.value)
            return
        table.connect()                               # as the capture rig builds it: homing planned
        assert time.monotonic() - t < 2.5
        table.home(2.0)
        assert table.move_to(-20.0, 2.0) == pytest.approx(-20.0, abs=0.005)
    finally:
        table.close()


# ---------------------------------------------------------------------- G5: homing from far away

def test_g5_homing_waits_for_grbls_own_bound(emu_factory):
    settings = {25: 600.0, 24: 600.0, 26: 10, 130: 20.0, 131: 20.0, 132: 20.0}
    # the X home flag 25 units away (at 10 units/s), after the Z cycle
    emu = emu_factory(switches={"X": LimitSwitch(25.0, 2.0, 360.0), "Y": 2.0, "Z": 2.0}, settings=settings)
    table = table_for(emu, timeout_s=1.0)
    table.connect()
    try:
        t = time.monotonic()
        table.home(1.0)                               # longer than 1 s: GRBL's settings say so
        assert 2.5 <= time.monotonic() - t < 5.0
        assert table.angle() == pytest.approx(0.0, abs=1e-3) and emu.state == "Idle"
        assert table.move_to(10.0, 2.0) == pytest.approx(10.0, abs=0.005)
    finally:
        table.close()


def test_g5_homing_past_the_bound_is_aborted_and_names_the_settings(emu_factory):
    settings = {25: 6000.0, 24: 6000.0, 26: 0, 27: 0.5, 130: 1.0, 131: 1.0, 132: 1.0}
    emu = emu_factory(switches={"X": LimitSwitch(1.0, 2.0, 360.0), "Y": 1.0, "Z": 1.0}, settings=settings)
    table = table_for(emu, timeout_s=1.0)
    table.connect()
    # the rates changed behind the driver's back after it read them (another sender on the port):
    # the real cycle (about 5 s at 1 unit/s) outlives the bound the driver computed (about 2 s)
    emu.settings.update({24: 60.0, 25: 60.0})
    try:
        t = time.monotonic()
        with pytest.raises(HardwareError) as err:
            table.home(0.5)
        assert time.monotonic() - t < 4.0
        msg = str(err.value)
        assert "homing did not finish" in msg and "$130=1" in msg and "$25=6000" in msg and "aborted" in msg
        assert emu.state == "Alarm"                   # aborted (ALARM:6), not homing on
        table.command("$130=2")                       # nothing queued behind the cycle
        table.command("$$")
        assert emu.settings[130] == 2 and table.settings[130] == 2
    finally:
        table.close()


def test_homing_worst_case_from_grbl_defaults():
    bound = homing_worst_case_s({})
    # GRBL's defaults: per axis 1.5 x 200 units at 500 units/min (36 s), 5 x 1 unit at 25 units/min (12 s)
    assert 3 * (36.0 + 12.0) < bound < 3 * (36.0 + 12.0 + 5.0)


# ---------------------------------------------------------------------- G6: GRBL 0.9

@pytest.mark.parametrize("auto_reset", [True, False])
def test_g6_grbl_09_is_named(emu_factory, auto_reset):
    emu = emu_factory(version="0.9j", auto_reset=auto_reset)
    table = table_for(emu)
    t = time.monotonic()
    with pytest.raises(HardwareError) as err:
        table.connect()
    assert time.monotonic() - t < 1.5
    msg = str(err.value)
    assert ("GRBL 0.9j" if auto_reset else "GRBL 0.9 or older") in msg and "GRBL 1.1" in msg
    assert "powered" not in msg and not err.value.retryable and not table.connected


def test_parse_status_of_grbl_09():
    st = parse_status("<Idle,MPos:5.000,0.000,0.000,WPos:4.000,0.000,0.000>")
    assert st.legacy and st.state == "Idle" and st.mpos == (5.0, 0.0, 0.0) and st.wpos == (4.0, 0.0, 0.0)
    assert not parse_status("<Idle|MPos:5.000,0.000,0.000|FS:0,0>").legacy


# ---------------------------------------------------------------------- the emulator, byte by byte

def test_emulator_reset_during_homing_pause_late_ok_banner(emu_factory):
    emu = emu_factory(settings=SLOW_HOMING)
    link = Link(emu.port)
    try:
        link.send(b"$H\n")
        time.sleep(0.1)
        link.send(b"?")
        assert link.lines(0.2) == []                  # no status report while homing
        link.send(b"\x18")
        got = link.lines(0.3, lambda s: s.startswith("ALARM"))
        assert got[-1][1] == "ALARM:6"
        t_alarm = got[-1][0]
        link.send(b"$X\n?")                           # lost in the pause
        got = link.lines(1.5, lambda s: "unlock" in s)
        assert [s for _, s in got] == ["ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
        assert 0.45 <= got[0][0] - t_alarm < 0.7
        assert link.ask("G0 X1") == ["error:9"]       # still locked: the $X was lost
    finally:
        link.close()


def test_emulator_homing_answers_one_report_at_its_end(emu_factory):
    emu = emu_factory()                               # FAST_HOMING: about 0.35 s
    link = Link(emu.port)
    try:
        link.send(b"$H\n")
        time.sleep(0.05)
        link.send(b"???")
        got = [s for _, s in link.lines(1.0, lambda s: s == "ok")]
        assert len(got) == 2 and got[0].startswith("<Home|") and got[1] == "ok"
        link.send(b"?")
        assert parse_status(link.lines(0.5, lambda s: s.startswith("<"))[-1][1]).state == "Idle"
    finally:
        link.close()


def test_emulator_soft_limit_locks_until_reset_then_late_ok(emu_factory):
    emu = emu_factory(soft_limits=True)
    link = Link(emu.port)
    try:
        link.lines(0.3)
        assert link.ask("$X")[-1] == "ok"
        link.send(b"G0 X5\n")                         # machine +5: beyond [-200, 0]
        got = [s for _, s in link.lines(1.0, lambda s: s.startswith("[MSG:Reset"))]
        assert got == ["ALARM:2", "[MSG:Reset to continue]"]
        link.send(b"?$X\n?")
        assert link.lines(0.6) == []                  # deaf
        link.send(b"\x18")
        got = [s for _, s in link.lines(1.0, lambda s: "unlock" in s)]
        assert got == ["ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]   # the G0's late ok
        link.send(b"?")
        st = parse_status(link.lines(0.5, lambda s: s.startswith("<"))[-1][1])
        assert st.state == "Alarm" and st.mpos[0] == 0.0
        assert link.ask("$J=G91 X5 F600") == ["error:9"]
        assert link.ask("$X")[-1] == "ok" and link.ask("$J=G91 X5 F600") == ["error:15"]
    finally:
        link.close()


def test_emulator_accelerates_and_decelerates(emu_factory):
    emu = emu_factory(speed_units_per_s=50.0, accel_units_per_s2=100.0)
    link = Link(emu.port)
    try:
        link.lines(0.3)
        expected = move_time(5.0, 50.0, 100.0)        # a triangle: 0.45 s (0.1 s without acceleration)
        t = time.monotonic()
        assert link.ask("G1 X5 F3000") == ["ok"]
        while emu.state != "Idle":
            time.sleep(0.005)
        assert expected - 0.03 <= time.monotonic() - t <= expected + 0.1
        assert link.ask("G1 X200 F3000") == ["ok"]    # full speed (50 units/s) after 0.5 s
        time.sleep(1.0)
        t = time.monotonic()
        link.send(b"!")
        while emu.state == "Run" and time.monotonic() - t < 0.1:
            time.sleep(0.002)
        while emu.state == "Hold:1":
            time.sleep(0.005)
        assert emu.state == "Hold:0" and 0.4 <= time.monotonic() - t <= 0.6   # 50 / 100 s to stop
    finally:
        link.close()


def test_emulator_without_auto_reset_keeps_its_state_across_opens(emu_factory):
    emu = emu_factory(auto_reset=False)
    link = Link(emu.port)
    assert link.lines(0.3) == []                      # no banner: the board did not reset
    assert link.ask("G0 X7") == ["ok"]
    time.sleep(0.2)
    link.close()
    link = Link(emu.port)
    try:
        assert link.lines(0.3) == []
        link.send(b"?")
        assert parse_status(link.lines(0.5, lambda s: s.startswith("<"))[-1][1]).mpos[0] == 7.0
    finally:
        link.close()
    emu2 = emu_factory(auto_reset=True)               # an Arduino: opening resets it
    link = Link(emu2.port)
    try:
        assert any(s.startswith("Grbl 1.1h") for _, s in link.lines(0.5, lambda s: s.startswith("Grbl")))
    finally:
        link.close()
