"""The GRBL turntable driver against what GRBL 1.1h does by default (issue 33, part 5): no reset
when the port opens, limit switches as inputs (Pn:, hard limits on any pin change, Check Limits at
a reset), homing Z then X/Y at the configured rates, homing failures; through the real driver
over the emulator's pseudo-terminal, and the emulator byte by byte where the driver cannot see."""

from __future__ import annotations

import functools
import time

import pytest

from tdof20.capture.hardware.grbl import GrblAlarm, parse_status
from tdof20.capture.hardware.grbl_emulator import GrblEmulator, LimitSwitch
from tdof20.capture.hardware.grbl_timing import contact_time, move_time
from tests.grbl_support import ACCEL, Link, emu_factory  # noqa: F401 (a fixture)
from tests.grbl_support import table_for as grbl_table_for

pytestmark = pytest.mark.timeout(30)

table_for = functools.partial(grbl_table_for, timeout_s=3.0)
SHORT_SEARCH = {25: 600.0, 24: 600.0, 26: 10, 130: 2.0, 131: 2.0, 132: 2.0}


# ---------------------------------------------------------------------- no reset on open

def test_reconnect_keeps_the_angle_of_a_board_that_does_not_reset(emu_factory):
    emu = emu_factory()
    table = table_for(emu)
    table.connect()
    table.home(3.0)
    assert table.move_to(30.0, 2.0) == pytest.approx(30.0, abs=0.005)
    table.close()
    table = table_for(emu)
    try:
        table.connect()                               # no banner: the G92 offset and the position survive
        assert table.angle() == pytest.approx(30.0, abs=0.005)
        assert table.move_to(45.0, 2.0) == pytest.approx(45.0, abs=0.005)
        assert emu.mpos[0] == pytest.approx(44.0, abs=0.005)
    finally:
        table.close()


def test_reconnect_after_a_homing_alarm_meets_the_lock(emu_factory):
    """ALARM:9 (no X switch), GRBL resets itself into the alarm lock; the next session's connect meets
    that lock without its ALARM line and says so at once; with homing planned it homes."""
    emu = emu_factory(switches={"Y": 2.0, "Z": 2.0}, settings=SHORT_SEARCH)
    table = table_for(emu)
    table.connect()
    with pytest.raises(GrblAlarm) as err:
        table.home(3.0)
    assert err.value.code == 9
    table.close()
    time.sleep(0.6)                                   # GRBL's pause, its reset into the lock
    table = table_for(emu)
    t = time.monotonic()
    with pytest.raises(GrblAlarm) as err:
        table.connect()
    assert time.monotonic() - t < 1.0                 # it answers '?': no reset needed, none sent
    msg = str(err.value)
    assert "from before this connection" in msg and "did not reset when its port opened" in msg
    assert "$X" in msg and not err.value.retryable and emu.state == "Alarm"
    # the operator mends the switch (a home flag 1 unit ahead of where X now stands) and resumes
    x = emu.physical_position[0]
    emu.switches["X"] = LimitSwitch(x + 1.0, 0.5, 360.0)
    table = table_for(emu, home=True)
    try:
        table.connect()
        table.home(3.0)
        assert emu.state == "Idle" and table.angle() == pytest.approx(0.0, abs=1e-3)
        assert emu.physical_position[0] == pytest.approx(x, abs=0.01)   # pulled off the flag by $27
        assert table.move_to(10.0, 2.0) == pytest.approx(10.0, abs=0.005)
    finally:
        table.close()


# ---------------------------------------------------------------------- limit switches

def test_a_switch_is_an_input_without_hard_limits(emu_factory):
    emu = emu_factory()                               # X home flag 2 units ahead, 2 wide, every 360
    table = table_for(emu)
    table.connect()
    try:
        table.home(3.0)                               # machine 0 (1 deg) is where the flag triggers
        assert table.status().pins == ""
        table.move_to(2.0, 2.0)
        st = table.status()
        assert st.pins == "X" and st.state == "Idle" and "|Pn:X" in st.raw
        assert table.move_to(5.0, 2.0) == pytest.approx(5.0, abs=0.005)   # off it: nothing happens
        assert table.status().pins == ""
    finally:
        table.close()


def test_hard_limit_from_a_real_switch_unlock_refused_home_recovers(emu_factory):
    """A linear X limit with $21=1: moving onto it trips ALARM:1 where it triggers; the reset prints
    [MSG:Check Limits]; unlock() refuses ($X then a step off it would trip again); home() works."""
    emu = emu_factory(hard_limits=True, switches={"X": LimitSwitch(40.0), "Y": 2.0, "Z": 2.0})
    table = table_for(emu)
    table.connect()
    try:
        table.home(3.0)                               # found at 40: machine 0 is the switch, 1 deg
        assert table.move_to(-30.0, 2.0) == pytest.approx(-30.0, abs=0.005)
        with pytest.raises(GrblAlarm) as err:
            table.move_to(10.0, 2.0)
        assert err.value.code == 1 and err.value.locked
        assert emu.mpos[0] == pytest.approx(0.0, abs=0.01) and emu.pins == "X"   # stopped dead at it
        with pytest.raises(GrblAlarm) as err:
            table.unlock()
        msg = str(err.value)
        assert "the X limit switch is pressed (Pn:X) with hard limits on ($21=1), so $X was not sent" in msg
        assert "home the table" in msg and "trips ALARM:1 again" in msg and "\n" not in msg
        assert "$X" not in emu.received and emu.state == "Alarm"
        table.home(3.0)                               # from the switch: pulls off it, locates, pulls off
        assert emu.state == "Idle" and emu.pins == "" and table.angle() == pytest.approx(0.0, abs=1e-3)
        assert table.move_to(-20.0, 2.0) == pytest.approx(-20.0, abs=0.005)
    finally:
        table.close()


def test_check_limits_at_connect_to_a_board_that_resets(emu_factory):
    emu = emu_factory(auto_reset=True, hard_limits=True)
    emu.set_switch("X", True)                         # a hand on the switch
    link = Link(emu.port)                             # the firmware's own words, as it boots
    got = [s for _, s in link.lines(1.0, lambda s: "unlock" in s)]
    link.close()
    assert got == ["Grbl 1.1h ['$' for help]", "[MSG:Check Limits]", "[MSG:'$H'|'$X' to unlock]"]
    table = table_for(emu)
    with pytest.raises(GrblAlarm) as err:
        table.connect()
    msg = str(err.value)
    assert "started with a limit switch pressed and locked itself ([MSG:Check Limits])" in msg
    assert "the X limit switch is pressed (Pn:X) with hard limits on ($21=1)" in msg and "home the table" in msg
    assert "trips ALARM:1 again" in msg and "\n" not in msg
    emu.set_switch("X", None)                         # let go: the switch follows the axis again
    table = table_for(emu, home=True)
    try:
        table.connect()
        table.home(3.0)
        assert table.move_to(-5.0, 2.0) == pytest.approx(-5.0, abs=0.005)
    finally:
        table.close()


def test_emulator_retrips_when_moving_off_a_switch(emu_factory):
    """GRBL's limit interrupt fires on any pin change: $X on a pressed switch, then the first step off
    it is ALARM:1 again; with hard limits off the same move is fine."""
    emu = emu_factory(hard_limits=True, switches={"X": LimitSwitch(5.0)})
    link = Link(emu.port)
    try:
        assert link.ask("G0 X8") == ["ok"]            # onto the switch at 5
        got = [s for _, s in link.lines(1.0, lambda s: s.startswith("[MSG:Reset"))]
        assert got == ["ALARM:1", "[MSG:Reset to continue]"]
        link.send(b"\x18")
        got = [s for _, s in link.lines(1.0, lambda s: "unlock" in s)]
        # no late ok: the G0 was answered when it was queued, unlike a $H or a soft limit's line
        assert got == ["Grbl 1.1h ['$' for help]", "[MSG:Check Limits]", "[MSG:'$H'|'$X' to unlock]"]
        link.send(b"?")
        st = parse_status(link.lines(0.5, lambda s: s.startswith("<"))[-1][1])
        assert st.state == "Alarm" and st.pins == "X" and st.mpos[0] == pytest.approx(5.0)
        assert link.ask("$X") == ["[MSG:Caution: Unlocked]", "ok"]     # 1.1h unlocks, switch pressed or not
        assert link.ask("G0 X0") == ["ok"]
        got = [s for _, s in link.lines(1.0, lambda s: s.startswith("[MSG:Reset"))]
        assert got == ["ALARM:1", "[MSG:Reset to continue]"]
        assert emu.mpos[0] == pytest.approx(5.0, abs=0.01)             # the first step off it
        link.send(b"\x18")
        link.lines(1.0, lambda s: "unlock" in s)
        assert link.ask("$21=0") == ["ok"] and link.ask("$X")[-1] == "ok"
        assert link.ask("G0 X0") == ["ok"]
        time.sleep(0.2)
        assert emu.state == "Idle" and emu.mpos[0] == 0.0 and emu.pins == ""
    finally:
        link.close()


# ---------------------------------------------------------------------- homing

RATES = {24: 120.0, 25: 600.0, 26: 20, 27: 1.0}      # locate 2 units/s, seek 10 units/s, 20 ms debounce


def cycle_s(to_switch: float) -> float:
    """One homing cycle as GRBL 1.1h's limits_go_home runs it: search, pull-off, locate, pull-off."""
    seek, locate, debounce = 10.0, 2.0, 0.02
    return (contact_time(to_switch, seek, ACCEL) + move_time(1.0, seek, ACCEL) + contact_time(1.0, locate, ACCEL)
            + move_time(1.0, seek, ACCEL) + 4 * debounce)


@pytest.mark.parametrize("cycles, expected", [(("Z", "XY"), 2 * cycle_s(2.0)), (("X",), cycle_s(2.0))])
def test_homing_takes_the_time_grbl_takes(emu_factory, cycles, expected):
    emu = emu_factory(settings=RATES, homing_cycles=cycles)
    table = table_for(emu, timeout_s=1.0)
    table.connect()
    try:
        assert emu.homing_plan() == (pytest.approx(expected, abs=1e-6), None)   # what homing_plan() tells
        t = time.monotonic()
        table.home(1.0)
        dt = time.monotonic() - t
        assert expected <= dt <= expected + 0.35, (dt, expected)
        homed = [0, 1, 2] if len(cycles) == 2 else [0]
        for i in range(3):                            # homed axes at -$27, the others where they were
            assert emu.mpos[i] == pytest.approx(-1.0 if i in homed else 0.0)
            assert emu.physical_position[i] == pytest.approx(1.0 if i in homed else 0.0, abs=1e-6)
    finally:
        table.close()


def test_homing_at_grbls_default_rates_takes_seconds():
    """GRBL's defaults ($25=500, $24=25 units/min, $26=250 ms, $27=1, $120=10 units/s²) with each
    switch 2 units away: Z then X/Y take 5-11 s (one cycle about half), as the firmware does."""
    emu = GrblEmulator(speed_units_per_s=500.0 / 60.0, accel_units_per_s2=10.0)
    seconds, alarm = emu.homing_plan()
    assert alarm is None and 5.0 <= seconds <= 11.0
    x_only, _ = GrblEmulator(speed_units_per_s=500.0 / 60.0, accel_units_per_s2=10.0,
                             homing_cycles=("X",)).homing_plan()
    assert x_only == pytest.approx(seconds / 2, rel=1e-6)


def test_homing_fail_alarms_8_and_9(emu_factory):
    emu = emu_factory(settings=SHORT_SEARCH)          # search 1.5 x $130-$132 = 3 units at 10 units/s
    emu.set_switch("Z", True)                         # stuck: the pull-off cannot clear it
    table = table_for(emu)
    table.connect()
    try:
        with pytest.raises(GrblAlarm) as err:
            table.home(3.0)
        assert err.value.code == 8 and "pull-off did not clear" in str(err.value)
        assert emu.physical_position[2] == pytest.approx(-1.0)      # the Z cycle's one pull-off ($27)
        emu.set_switch("Z", None)                     # freed: 3 units behind its switch now
        emu.set_switch("Y", False)                    # broken: never triggers
        with pytest.raises(GrblAlarm) as err:
            table.home(3.0)
        assert err.value.code == 9 and "not found" in str(err.value)
        x, y, z = emu.physical_position
        assert y == pytest.approx(3.0)                # the whole search travel, past the dead switch
        assert x == pytest.approx(2.0) and emu.pins == "X"   # X of the same cycle stopped at its flag
        assert z == pytest.approx(1.0)                # Z homed in its own cycle first, at -$27
        # the operator fits a new Y switch (2 units ahead of where Y now stands) and homes again
        emu.set_switch("Y", None)
        emu.switches["Y"] = LimitSwitch(y + 2.0)
        table.home(3.0)
        assert emu.state == "Idle" and emu.pins == "" and table.angle() == pytest.approx(0.0, abs=1e-3)
        assert emu.physical_position == pytest.approx((1.0, y + 1.0, 1.0), abs=1e-6)
    finally:
        table.close()


def test_emulator_homing_door_alarm_7(emu_factory):
    emu = emu_factory(settings={24: 60.0, 25: 600.0})
    link = Link(emu.port)
    try:
        link.send(b"$H\n")
        time.sleep(0.2)
        link.send(b"\x84")                            # the safety door opens during the cycle
        got = [s for _, s in link.lines(1.5, lambda s: "unlock" in s)]
        assert got == ["ALARM:7", "ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    finally:
        link.close()


def test_power_up_lock_follows_homing_enabled():
    """GRBL 1.1h's HOMING_INIT_LOCK: with $22=1 it powers up in the alarm lock, with $22=0 Idle."""
    with GrblEmulator() as emu:
        assert emu.state == "Alarm"
    with GrblEmulator(homing_enabled=False) as emu:
        assert emu.state == "Idle"
