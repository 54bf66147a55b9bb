"""A turntable driven by a GRBL 1.1 stepper controller on a serial port (pyserial).

The lab's table is a stepper on one GRBL axis (``X`` by default). GRBL thinks in *axis units*
(millimetres for a mill); ``units_per_degree`` converts table degrees to those units:

* the lab's set-up sets ``$100`` (X steps per unit) to the motor's steps per table degree
  (``motor steps/rev * microsteps * gear ratio / 360``), so 1 unit = 1 degree and
  ``units_per_degree = 1.0``;
* a table driven by a belt or a rim measured in millimetres uses the millimetres of travel per
  degree instead (``pi * rim_diameter_mm / 360``), or any positive factor.

Angles given to and returned by this driver are degrees; commands and status reports are in
units. The feed ``feed_deg_per_s`` becomes ``F = feed_deg_per_s * units_per_degree * 60`` units
per minute; GRBL clamps it to the axis's max rate (``$110`` for X; the driver warns when it does).

Protocol, as GRBL 1.1 documents it: one command line at a time, each answered by ``ok`` or
``error:N``; ``ALARM:N`` may arrive at any time (an alarm stops the driver: a person must act);
the real-time byte ``?`` asks for a status report ``<Idle|MPos:12.000,0.000,0.000|FS:0,0>``
(``WPos`` instead of ``MPos`` when ``$10=0``; ``WCO`` from time to time); ``!`` is a feed hold
and ``0x18`` a soft reset. The driver works in the G54 work coordinate system plus a G92 offset
set after homing, so that the table's reference is 0 degrees; it tracks the work coordinate
offset (``$#`` and the ``WCO`` field) to turn machine positions into table angles.

Every read has a deadline: a silent controller gives a :class:`HardwareError` naming the port and
what was awaited. A command whose ``ok`` does not come is re-sent after a soft re-sync (an empty
line, which GRBL answers with ``ok``), at most ``retries`` times; an acknowledged command is never
re-sent (all commands sent are absolute, so a re-send of an unacknowledged one is harmless).

Things to know on a real rig:

* Opening the port of an Arduino-based controller resets it (DTR): the machine position starts
  at 0 again and G92 offsets are gone. Without a home switch the angle after ``connect()`` is
  relative to wherever the table stood; use a home switch (``$22=1``) for angles that repeat
  across sessions (transparent objects and their opaque twins in the same slots).
* If homing is disabled on the controller (``$22=0``, ``$H`` answers ``error:5``),
  :meth:`GrblTurntable.home` takes the current position as 0 degrees and logs a warning.
* ``$H`` homes every axis GRBL is configured to home.

Manual smoke test for a real controller (or the emulator with ``--emulate``)::

    python -m tdof20.capture.hardware.grbl --port /dev/ttyUSB0 --home --angles 0 90 180 0.9 0
"""

from __future__ import annotations

import argparse
import collections
import errno
import functools
import logging
import math
import os
import re
import threading
import time
from dataclasses import dataclass
from typing import Callable

import serial

from tdof20.capture.hardware.interfaces import HardwareError, Turntable

log = logging.getLogger(__name__)

#: GRBL 1.1 alarm codes (``ALARM:N``), in words. 10+ are grblHAL's extensions.
ALARM_CODES: dict[int, str] = {
    1: "hard limit: a limit switch was triggered; the position is likely lost, home again",
    2: "soft limit: the motion target exceeds the machine travel; the position is kept, unlocking is safe",
    3: "abort during cycle: reset while in motion; the position is likely lost, home again",
    4: "probe fail: the probe was not in the expected initial state",
    5: "probe fail: the probe did not make contact within the programmed travel",
    6: "homing fail: the homing cycle was reset",
    7: "homing fail: the safety door was opened during homing",
    8: "homing fail: pull-off did not clear the limit switch (increase $27 or check the wiring)",
    9: "homing fail: the limit switch was not found within the search distance "
       "(check $130 max travel, the switch and its wiring)",
    10: "emergency stop (grblHAL)",
    11: "homing required (grblHAL)",
    12: "limit switch engaged (grblHAL)",
}

#: What an Alarm state without a code means: the power-up lock of a controller with homing on.
HOMING_REQUIRED = "homing required: GRBL locks motion at power-up until it is homed ($H) or unlocked ($X)"

#: GRBL 1.1 error codes (``error:N``), in words.
ERROR_CODES: dict[int, str] = {
    1: "expected command letter: a G-code word has no letter",
    2: "bad number format: a G-code word has a missing or invalid value",
    3: "invalid statement: the '$' system command is not recognised or supported",
    4: "value < 0: a negative value where a positive one is expected",
    5: "setting disabled: homing is not enabled in the settings ($22)",
    6: "value < 3 usec: the minimum step pulse must be at least 3 microseconds",
    7: "EEPROM read fail: settings restored to defaults",
    8: "not idle: this '$' command needs GRBL to be idle",
    9: "G-code lock: G-code is locked out during an alarm or a jog (home with $H or unlock with $X)",
    10: "homing not enabled: soft limits need homing enabled",
    11: "line overflow: too many characters in the line, not executed",
    12: "step rate > 30 kHz: the setting makes the step rate too high",
    13: "check door: the safety door is open",
    14: "line length exceeded: build info or startup line too long for EEPROM",
    15: "travel exceeded: the jog target exceeds the machine travel, jog ignored",
    16: "invalid jog command: no '=' or a prohibited G-code",
    17: "setting disabled: laser mode needs PWM output",
    20: "unsupported command: an unsupported or invalid G-code in the block",
    21: "modal group violation: more than one G-code of the same modal group",
    22: "undefined feed rate: no feed rate set",
    23: "G-code command in the block needs an integer value",
    24: "more than one G-code command that needs axis words in the block",
    25: "repeated G-code word in the block",
    26: "no axis words in the block for a command that needs them",
    27: "invalid line number",
    28: "a G-code command is missing a required value word",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 is only allowed with G0 and G1",
    31: "axis words in a block where no command uses them",
    32: "G2/G3 arcs need at least one in-plane axis word",
    33: "invalid motion command target",
    34: "invalid arc radius",
    35: "G2/G3 arcs need at least one in-plane offset word",
    36: "unused value words in the block",
    37: "G43.1 dynamic tool length offset is not on the tool length axis",
    38: "tool number greater than the maximum supported",
}

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")
AXES = "XYZABC"
_READ_SLICE_S = 0.02          # pyserial read timeout: the granularity of every deadline
_QUERY_RESEND_S = 0.25        # resend "?" when a status report is late (lost byte, booting board)
_QUIET_S = 0.15               # "nothing more is coming" after the wake-up / a reset

_OK = "ok"
_ERROR_RE = re.compile(r"^error:\s*(\d+)", re.I)
_ALARM_RE = re.compile(r"^ALARM:\s*(\d+)", re.I)
_BANNER_RE = re.compile(r"^Grbl(HAL)?\s+\S+\s+\[", re.I)
_PARAM_RE = re.compile(r"^\[(G5[4-9]|G28|G30|G92|TLO):([^\]]*)\]$")
_SETTING_RE = re.compile(r"^\$(\d+)=([-+0-9.]+)")


def describe_alarm(code: int | None) -> str:
    """``ALARM:N`` in words (``None``: the code-less power-up lock)."""
    if code is None:
        return HOMING_REQUIRED
    return ALARM_CODES.get(code, f"unknown alarm {code} (see the controller's documentation)")


def describe_error(code: int) -> str:
    """``error:N`` in words; unknown codes keep their number."""
    return ERROR_CODES.get(code, f"unknown error {code} (see the controller's documentation)")


class GrblError(HardwareError):
    """GRBL rejected a command with ``error:N`` (``code``). Not retryable: the same line fails again."""

    def __init__(self, device: str, command: str, code: int):
        self.code = code
        self.command = command
        super().__init__(device, f"GRBL rejected {command!r}: error:{code} ({describe_error(code)})",
                         retryable=False)


class GrblAlarm(HardwareError):
    """GRBL is in an alarm (``code`` None: the power-up homing lock). A person must act."""

    def __init__(self, device: str, code: int | None, context: str = ""):
        self.code = code
        head = f"ALARM:{code} ({describe_alarm(code)})" if code is not None else f"ALARM ({describe_alarm(None)})"
        tail = (f"{context}; " if context else "") + (
            "clear the cause, then home the table ($H, or home() / [turntable] home = true) "
            "or unlock it with $X after checking it turns freely")
        super().__init__(device, f"{head}; {tail}", retryable=False)


class _NoAnswer(HardwareError):
    """Nothing (useful) came back before a deadline."""


def _locked(fn):
    """Run a public method under the driver's I/O lock (one conversation with GRBL at a time)."""
    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        with self._io:
            return fn(self, *args, **kwargs)
    return wrapper


@dataclass(frozen=True)
class GrblStatus:
    """A parsed real-time status report (positions in axis units)."""

    state: str                                   # Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep
    substate: int | None = None                  # Hold:0 (complete) / Hold:1 (decelerating), Door:N, ...
    mpos: tuple[float, ...] | None = None        # machine position ($10=1, the default)
    wpos: tuple[float, ...] | None = None        # work position ($10=0)
    wco: tuple[float, ...] | None = None         # work coordinate offset, sent now and then
    feed: float | None = None                    # current feed, units/min
    raw: str = ""


def parse_status(line: str) -> GrblStatus | None:
    """Parse ``<Idle|MPos:12.000,0.000,0.000|FS:0,0>``; ``None`` if the line is not a report."""
    line = line.strip()
    if not (line.startswith("<") and line.endswith(">")) or len(line) < 3:
        return None
    fields = line[1:-1].split("|")
    state, _, sub = fields[0].partition(":")
    if not state or not state.isalpha():
        return None
    try:
        substate = int(sub) if sub else None
    except ValueError:
        substate = None
    values: dict = {}
    for f in fields[1:]:
        key, _, val = f.partition(":")
        if key in ("MPos", "WPos", "WCO", "FS", "F"):
            try:
                values[key] = tuple(float(v) for v in val.split(","))
            except ValueError:
                return None
    feed = values.get("FS", values.get("F", (None,)))[0]
    return GrblStatus(state, substate, values.get("MPos"), values.get("WPos"), values.get("WCO"), feed, line)


class GrblTurntable(Turntable):
    """A turntable on one axis of a GRBL 1.1 controller.

    ``port``: a serial device (``/dev/ttyUSB0``, ``COM3``) or a pyserial URL (``socket://host:23``
    for a networked GRBL). ``units_per_degree``: GRBL axis units per table degree (any positive
    factor; see the module docstring). ``timeout_s`` bounds connecting and every command's answer;
    ``home``: the caller homes the table right after connecting (the capture runner does with
    ``[turntable] home = true``), so an alarm at connect (e.g. the power-up homing lock) is expected
    and only logged; without it an alarm at connect raises. ``retries``: re-sends of a command whose
    ``ok`` did not come. ``tolerance_deg``: arrival tolerance (at least one motor step is allowed,
    read from ``$100``-``$102``). ``poll_s``: status polling period while the table turns.
    """

    name = "turntable"

    def __init__(self, port: str, baudrate: int = 115200, axis: str = "X", units_per_degree: float = 1.0,
                 feed_deg_per_s: float = 30.0, timeout_s: float = 5.0, home: bool = False, retries: int = 2,
                 *, tolerance_deg: float = 0.01, poll_s: float = 0.1):
        axis = str(axis).upper()
        if axis not in AXES:
            raise ValueError(f"turntable axis must be one of {', '.join(AXES)}, got {axis!r}")
        for label, v in (("units_per_degree", units_per_degree), ("feed_deg_per_s", feed_deg_per_s),
                         ("timeout_s", timeout_s), ("tolerance_deg", tolerance_deg), ("poll_s", poll_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"turntable {label} must be a positive number, got {v!r}")
        if int(retries) < 0:
            raise ValueError(f"turntable retries must be >= 0, got {retries!r}")
        self.port = str(port)
        self.baudrate = int(baudrate)
        self.axis = axis
        self.units_per_degree = float(units_per_degree)
        self.feed_deg_per_s = float(feed_deg_per_s)
        self.timeout_s = float(timeout_s)
        self.home_on_connect = bool(home)
        self.retries = int(retries)
        self.tolerance_deg = float(tolerance_deg)
        self.poll_s = float(poll_s)
        self.device = f"turntable (GRBL on {self.port})"
        self._i = AXES.index(axis)
        self._ser = None
        self._buf = bytearray()
        self._responses: collections.deque[int | None] = collections.deque()   # None = ok, N = error:N
        self._status: GrblStatus | None = None
        self._fresh_status = False
        self._wco = 0.0                  # work coordinate offset of our axis, units
        self._params: dict[str, tuple[float, ...]] = {}
        self.settings: dict[int, float] = {}
        self._alarm: int | None = None   # last ALARM:N seen
        self._lock_msg = False           # "[MSG:'$H'|'$X' to unlock]" seen
        self._collect_alarms = False     # record ALARM lines instead of raising (handshake, stop)
        self._expect_reset = False       # a banner is expected (connect, after stop())
        self._banner_seen = False
        self._needs_resync = False       # after stop(): the controller was reset
        self._saved_wco: float | None = None
        self._reference_lost = False     # the controller reset by itself: home again
        self._io = threading.RLock()
        self._stop_requested = threading.Event()

    # ------------------------------------------------------------------ public API

    @property
    def feed_units_per_min(self) -> float:
        return self.feed_deg_per_s * self.units_per_degree * 60.0

    @property
    def connected(self) -> bool:
        return self._ser is not None

    @_locked
    def connect(self) -> None:
        """Open the port, wake GRBL, check its state, set G21 G90 G94 G54 and read the offsets."""
        self.close()
        try:
            if "://" in self.port:
                self._ser = serial.serial_for_url(self.port, self.baudrate, timeout=_READ_SLICE_S,
                                                  write_timeout=self.timeout_s)
            else:
                self._ser = serial.Serial(self.port, self.baudrate, timeout=_READ_SLICE_S,
                                          write_timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as e:
            raise HardwareError(self.device, self._open_problem(e), retryable=False) from e
        try:
            st = self._handshake()
            if st.state in ("Run", "Jog", "Home", "Hold", "Door"):
                st = self._wait_idle(st)
            if st.state == "Alarm":
                code = self._alarm if self._alarm is not None else st.substate
                if not self.home_on_connect:
                    raise GrblAlarm(self.device, code, "at connect")
                log.warning("%s: ALARM at connect (%s); homing is planned", self.device, describe_alarm(code))
            else:
                self._check_usable(st, "at connect")
            self._read_settings()
            if st.state != "Alarm":
                self._set_modes()
            self._refresh_wco()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Close the port; never raises."""
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - close never raises
                pass

    @_locked
    def home(self, timeout_s: float) -> None:
        """``$H`` (homing cycle), then make the table's angle 0 (``G92`` if needed)."""
        self._ready(allow_alarm=True)
        deadline = time.monotonic() + timeout_s
        self._alarm = None
        try:
            self._command("$H", timeout_s=timeout_s, resend=False)
        except GrblError as e:
            if e.code != 5:
                raise
            log.warning("%s: homing is disabled on the controller ($22=0): taking the current position "
                        "as 0 degrees", self.device)
        self._set_modes(deadline)
        self._refresh_wco(deadline)
        st = self._query_status(deadline)
        if abs(self._work_units(st)) > self._tolerance_units():
            self._command(f"G92 {self.axis}0", deadline=deadline)
            self._refresh_wco(deadline)
            st = self._query_status(deadline)
        angle = self._work_units(st) / self.units_per_degree
        if abs(angle) > self.tolerance_deg + self._step_deg():
            raise HardwareError(self.device, f"after homing the table reports {angle:.3f} deg instead of 0")
        self._reference_lost = False
        self._alarm = None

    @_locked
    def move_to(self, angle_deg: float, timeout_s: float) -> float:
        """``G90 G1`` to ``angle_deg``, poll ``?`` until Idle at the target; returns the reported angle."""
        angle_deg = float(angle_deg)
        if not math.isfinite(angle_deg):
            raise HardwareError(self.device, f"cannot move to {angle_deg!r} deg", retryable=False)
        t0 = time.monotonic()
        deadline = t0 + float(timeout_s)
        self._ready()
        if self._reference_lost:
            raise HardwareError(self.device, "the controller was reset: the angle reference is lost, "
                                "home the table before moving it", retryable=False)
        if self._alarm is not None:           # GRBL is locked (and deaf after a limit) until $H / $X / reset
            raise GrblAlarm(self.device, self._alarm, f"not cleared, cannot move to {angle_deg:g} deg")
        target = angle_deg * self.units_per_degree
        tol = self._tolerance_units()
        line = f"G90 G1 {self.axis}{target:.4f} F{self.feed_units_per_min:.3f}"
        self._command(line, deadline=deadline)
        off_target_since: float | None = None
        while True:
            # the last report may be asked for at the deadline: give it a moment to come back
            grace = time.monotonic() + min(0.5, self.timeout_s)
            st = self._query_status(max(deadline, grace), what=f"a status report while moving to {angle_deg:g} deg")
            pos = self._work_units(st)
            now = time.monotonic()
            if st.state == "Idle":
                if abs(pos - target) <= tol:
                    return pos / self.units_per_degree
                # GRBL may report Idle for an instant before the cycle starts; a lasting Idle away
                # from the target means the move was dropped (a reset, a hold + reset, ...).
                off_target_since = off_target_since if off_target_since is not None else now
                if now - off_target_since > max(3 * self.poll_s, 0.3):
                    raise HardwareError(self.device, f"the table stopped at {pos / self.units_per_degree:.3f} deg "
                                        f"instead of {angle_deg:.3f} deg")
            else:
                off_target_since = None
                if st.state == "Alarm":
                    raise GrblAlarm(self.device, self._alarm if self._alarm is not None else st.substate,
                                    f"while moving to {angle_deg:g} deg")
                self._check_usable(st, f"while moving to {angle_deg:g} deg")
            if now >= deadline:
                why = {"Hold": " (feed hold: resume with cycle start '~')",
                       "Door": " (safety door open)"}.get(st.state, "")
                raise HardwareError(self.device, f"move to {angle_deg:g} deg did not finish within "
                                    f"{timeout_s:g} s: state {st.state}{why} at "
                                    f"{pos / self.units_per_degree:.3f} deg")
            self._pump(min(deadline, now + self.poll_s))

    def angle(self) -> float:
        """The angle the controller reports, degrees."""
        return self._work_units(self.status()) / self.units_per_degree

    @_locked
    def status(self) -> GrblStatus:
        """A fresh status report."""
        self._ready(allow_alarm=True)
        return self._query_status(time.monotonic() + self.timeout_s)

    @_locked
    def unlock(self) -> None:
        """``$X``: leave an alarm without homing (the operator checked the table)."""
        self._ready(allow_alarm=True)
        self._command("$X")
        self._alarm = None
        self._set_modes()
        self._refresh_wco()

    @_locked
    def command(self, line: str, timeout_s: float | None = None) -> None:
        """Send one raw line and wait for its ``ok`` (for manual use; no re-send)."""
        self._ready(allow_alarm=True)
        self._command(line.strip(), timeout_s=timeout_s, resend=False)

    def stop(self) -> None:
        """Feed hold ``!`` now, wait (at most ``timeout_s``) for the table to stop, then soft reset
        (0x18); never raises. Callable from another thread: a running move_to()/home() there ends with
        a HardwareError. A reset after a completed hold keeps the position and the next call re-applies
        the modes and the G92 offset; a reset in motion puts GRBL in ALARM:3 (home again)."""
        if self._ser is None:
            return
        self._stop_requested.set()
        try:
            self._write(b"!")                 # at once, even while another thread talks to GRBL
        except Exception as e:  # noqa: BLE001 - best effort
            log.debug("%s: feed hold: %s", self.device, e)
        got = self._io.acquire(timeout=self.timeout_s)
        self._stop_requested.clear()
        self._collect_alarms = True
        try:
            try:
                if got and self._alarm is None and not self._needs_resync:
                    end = time.monotonic() + self.timeout_s
                    while time.monotonic() < end:
                        st = self._query_status(end)
                        if st.state in ("Idle", "Alarm", "Sleep", "Door", "Check") or \
                                (st.state == "Hold" and st.substate == 0):
                            break
                        self._pump(min(end, time.monotonic() + 0.02))
            except Exception as e:  # noqa: BLE001 - best effort
                log.debug("%s: waiting for the hold: %s", self.device, e)
            try:
                if not self._needs_resync:
                    self._saved_wco = self._wco
                self._expect_reset = True
                self._needs_resync = True
                self._write(b"\x18")
                if got:
                    self._drain_quiet(0.05, time.monotonic() + 0.3)
            except Exception as e:  # noqa: BLE001 - best effort
                log.debug("%s: soft reset: %s", self.device, e)
        finally:
            self._collect_alarms = False
            if got:
                self._io.release()

    # ------------------------------------------------------------------ protocol

    def _open_problem(self, e: BaseException) -> str:
        err = getattr(e, "errno", None)
        text = str(e)
        if err == errno.ENOENT or "No such file" in text or "FileNotFound" in text or \
                (self.port.startswith("/") and not os.path.exists(self.port)):
            return (f"serial port {self.port} does not exist: is the controller plugged in and powered "
                    f"(ls /dev/ttyUSB* /dev/ttyACM*)?")
        if err == errno.EACCES or "Permission denied" in text:
            return f"no permission to open serial port {self.port} (add the user to the dialout group)"
        if err == errno.EBUSY or "busy" in text.lower():
            return f"serial port {self.port} is busy (another program, e.g. a G-code sender, has it open)"
        return f"cannot open serial port {self.port}: {' '.join(text.split())}"

    def _handshake(self) -> GrblStatus:
        """Wake GRBL, skip its banner, get a status report; all within ``timeout_s``."""
        deadline = time.monotonic() + self.timeout_s
        self._buf.clear()
        self._responses.clear()
        self._alarm, self._lock_msg, self._banner_seen = None, False, False
        self._needs_resync, self._reference_lost, self._saved_wco = False, False, None
        self._collect_alarms, self._expect_reset = True, True
        try:
            self._write(b"\r\n\r\n")
            next_query = time.monotonic() + 0.1
            self._fresh_status = False
            banner_asked = False
            while not self._fresh_status:
                now = time.monotonic()
                if now >= deadline:
                    raise _NoAnswer(self.device, f"no answer within {self.timeout_s:g} s: waited for GRBL's "
                                    f"startup banner or a status report (is this the controller's port, "
                                    f"{self.baudrate} baud, and is it powered?)")
                if now >= next_query or (self._banner_seen and not banner_asked):
                    banner_asked = banner_asked or self._banner_seen
                    self._write(b"?")
                    next_query = now + _QUERY_RESEND_S
                self._pump(min(deadline, now + 0.05), until=lambda: self._fresh_status)
            self._drain_quiet(_QUIET_S, deadline)   # the wake-up lines' "ok"s, late banner / messages
        finally:
            self._collect_alarms, self._expect_reset = False, False
        self._responses.clear()
        st = self._status
        assert st is not None
        if st.state != "Alarm" and self._alarm is not None:
            self._alarm = None                      # a reported alarm that was cleared since
        return st

    def _ready(self, allow_alarm: bool = False) -> None:
        if self._ser is None:
            raise HardwareError(self.device, "not connected: call connect() first", retryable=False)
        if self._needs_resync:
            self._resync_after_reset(allow_alarm)

    def _resync_after_reset(self, allow_alarm: bool) -> None:
        """After stop()'s soft reset: swallow the banner, re-apply modes and the G92 offset."""
        deadline = time.monotonic() + self.timeout_s
        self._collect_alarms, self._expect_reset = True, True
        try:
            self._drain_quiet(0.05, deadline)
            st = self._query_status(deadline)
            self._drain_quiet(0.05, deadline)
        finally:
            self._collect_alarms, self._expect_reset = False, False
        self._responses.clear()
        self._needs_resync = False
        if st.state == "Alarm":
            if allow_alarm:
                return
            raise GrblAlarm(self.device, self._alarm if self._alarm is not None else st.substate,
                            "after stop()")
        self._alarm = None
        self._set_modes(deadline)
        self._refresh_wco(deadline)
        if self._saved_wco is not None and abs(self._wco - self._saved_wco) > 1e-6:
            st = self._query_status(deadline)
            mpos = self._work_units(st) + self._wco
            self._command(f"G92 {self.axis}{mpos - self._saved_wco:.4f}", deadline=deadline)
            self._refresh_wco(deadline)
        self._saved_wco = None

    def _wait_idle(self, st: GrblStatus) -> GrblStatus:
        """At connect the controller is still busy (a move of a previous run): wait for it."""
        end = time.monotonic() + self.timeout_s
        while st.state in ("Run", "Jog", "Home") and time.monotonic() < end:
            self._pump(min(end, time.monotonic() + self.poll_s))
            st = self._query_status(end)
        if st.state in ("Run", "Jog", "Home", "Hold", "Door"):
            why = {"Hold": "in a feed hold (resume with '~' or reset)", "Door": "stopped by the safety door"}
            raise HardwareError(self.device, f"GRBL is {why.get(st.state, f'busy ({st.state})')} at connect; "
                                "is another program driving it?")
        return st

    def _check_usable(self, st: GrblStatus, context: str) -> None:
        if st.state == "Check":
            raise HardwareError(self.device, f"GRBL is in check mode ($C) {context}: nothing moves; send $C "
                                "to leave it", retryable=False)
        if st.state == "Sleep":
            raise HardwareError(self.device, f"GRBL is asleep ($SLP) {context}: reset it and home",
                                retryable=False)

    def _set_modes(self, deadline: float | None = None) -> None:
        self._command("G21 G90 G94 G54", deadline=deadline)

    def _read_settings(self, deadline: float | None = None) -> None:
        self._command("$$", deadline=deadline)
        steps = self.settings.get(100 + self._i)
        rate = self.settings.get(110 + self._i)
        if rate is not None and rate > 0 and self.feed_units_per_min > rate * 1.0001:
            log.warning("%s: feed %.1f units/min exceeds $%d=%.1f: GRBL will turn slower (%.1f deg/s)",
                        self.device, self.feed_units_per_min, 110 + self._i, rate,
                        rate / 60.0 / self.units_per_degree)
        if steps is not None and steps > 0:
            log.debug("%s: %.3f steps per unit on %s", self.device, steps, self.axis)

    def _refresh_wco(self, deadline: float | None = None) -> None:
        """Work coordinate offset of our axis from ``$#``: G54 + G92 (+ TLO on Z)."""
        self._params.clear()
        self._command("$#", deadline=deadline)
        i = self._i
        wco = 0.0
        for key in ("G54", "G92"):
            v = self._params.get(key)
            if v is not None and len(v) > i:
                wco += v[i]
        if self.axis == "Z" and self._params.get("TLO"):
            wco += self._params["TLO"][0]
        self._wco = wco

    def _step_units(self) -> float:
        steps = self.settings.get(100 + self._i)
        return 1.0 / steps if steps and steps > 0 else 0.0

    def _step_deg(self) -> float:
        return self._step_units() / self.units_per_degree

    def _tolerance_units(self) -> float:
        # reports have 3 decimals; a target between two steps is reached to within half a step
        return max(self.tolerance_deg * self.units_per_degree, 1.01 * self._step_units(), 0.0015)

    def _work_units(self, st: GrblStatus) -> float:
        pos = st.wpos if st.wpos is not None else st.mpos
        if pos is None:
            raise HardwareError(self.device, f"status report without a position: {st.raw!r}")
        if len(pos) <= self._i:
            raise HardwareError(self.device, f"the controller reports {len(pos)} axes, no {self.axis} axis",
                                retryable=False)
        return pos[self._i] if st.wpos is not None else pos[self._i] - self._wco

    def _command(self, line: str, timeout_s: float | None = None, resend: bool = True,
                 deadline: float | None = None) -> None:
        """Send one line and wait for its answer, all within the deadline (``timeout_s`` from now)."""
        start = now = time.monotonic()
        end = now + (self.timeout_s if timeout_s is None else float(timeout_s))
        if deadline is not None:
            end = min(end, deadline)
        self._pump(now)                       # handle whatever is already there
        if self._responses:
            log.debug("%s: dropping %d stale answers", self.device, len(self._responses))
            self._responses.clear()
        attempts = self.retries + 1 if resend else 1
        data = (line + "\n").encode("ascii")
        for attempt in range(attempts):
            self._write(data)
            now = time.monotonic()
            slot_end = now + max(end - now, 0.0) / (attempts - attempt)
            try:
                self._wait(lambda: bool(self._responses), slot_end, f"'ok' to {line!r}")
                break
            except _NoAnswer:
                if attempt == attempts - 1:
                    raise _NoAnswer(self.device, f"no answer within {end - start:.3g} s: waited for 'ok' to "
                                    f"{line!r} ({attempts} tries; cable, power, or a reset?)") from None
                log.warning("%s: no 'ok' to %r, re-syncing (try %d of %d)", self.device, line,
                            attempt + 2, attempts)
                if self._resync(end, line):
                    break                     # the answer came late: acknowledged, never re-sent
        code = self._responses.popleft()
        if code is not None:
            raise GrblError(self.device, line, code)

    def _resync(self, deadline: float, line: str) -> bool:
        """Soft re-sync after a missing answer. True if the original line's answer arrived late."""
        try:
            self._wait(lambda: bool(self._responses), min(deadline, time.monotonic() + 0.1), "a late answer")
            return True
        except _NoAnswer:
            pass
        self._write(b"\n")                    # GRBL answers an empty line with "ok"
        self._wait(lambda: bool(self._responses), deadline, f"'ok' to a re-sync line after {line!r}")
        self._pump(min(deadline, time.monotonic() + 0.05), until=lambda: len(self._responses) >= 2)
        if len(self._responses) >= 2:         # the first answer was the original line's
            first = self._responses.popleft()
            self._responses.clear()
            self._responses.append(first)
            return True
        self._responses.clear()               # that "ok" was the re-sync's: re-send the line
        return False

    def _query_status(self, deadline: float, what: str = "a status report") -> GrblStatus:
        self._fresh_status = False
        start = time.monotonic()
        while True:
            self._write(b"?")
            now = time.monotonic()
            try:
                self._wait(lambda: self._fresh_status, min(deadline, now + _QUERY_RESEND_S), what)
                assert self._status is not None
                return self._status
            except _NoAnswer:
                if time.monotonic() >= deadline:
                    raise _NoAnswer(self.device, f"no answer within {max(deadline - start, 0):.3g} s: "
                                    f"waited for {what}") from None

    def _wait(self, pred: Callable[[], bool], deadline: float, what: str) -> None:
        start = time.monotonic()
        self._pump(deadline, until=pred)
        if not pred():
            raise _NoAnswer(self.device, f"no answer within {time.monotonic() - start:.3g} s: waited for {what}")

    def _pump(self, deadline: float, until: Callable[[], bool] | None = None) -> None:
        """Read and handle lines until ``until()`` holds or the deadline passes."""
        while True:
            if self._stop_requested.is_set():
                raise HardwareError(self.device, "interrupted by stop()")
            self._handle_buffered()
            if until is not None and until():
                return
            if time.monotonic() >= deadline:
                return
            self._read_some()

    def _drain_quiet(self, quiet_s: float, deadline: float) -> None:
        """Read until nothing arrives for ``quiet_s`` (or the deadline)."""
        last = time.monotonic()
        while True:
            self._handle_buffered()
            now = time.monotonic()
            if now >= deadline or now - last >= quiet_s:
                return
            if self._read_some():
                last = time.monotonic()

    def _read_some(self) -> int:
        ser = self._ser
        if ser is None:
            raise HardwareError(self.device, "not connected", retryable=False)
        try:
            n = ser.in_waiting
            data = ser.read(n if n > 0 else 1)
        except (serial.SerialException, OSError) as e:
            raise HardwareError(self.device, f"serial read failed: {e}") from e
        if data:
            self._buf += data
            if len(self._buf) > 65536 and b"\n" not in self._buf:
                del self._buf[:-1024]         # garbage without line ends (wrong baud rate)
        return len(data)

    def _write(self, data: bytes) -> None:
        ser = self._ser
        if ser is None:
            raise HardwareError(self.device, "not connected", retryable=False)
        try:
            ser.write(data)
        except serial.SerialTimeoutException as e:
            raise HardwareError(self.device, f"serial write timed out after {self.timeout_s:g} s") from e
        except (serial.SerialException, OSError) as e:
            raise HardwareError(self.device, f"serial write failed: {e}") from e

    def _handle_buffered(self) -> None:
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                return
            raw = bytes(self._buf[:nl])
            del self._buf[:nl + 1]
            text = raw.decode("ascii", "replace").strip()
            if text:
                self._handle(text)

    def _handle(self, line: str) -> None:
        if line == _OK:
            self._responses.append(None)
            return
        m = _ERROR_RE.match(line)
        if m:
            self._responses.append(int(m.group(1)))
            return
        if line.startswith("<"):
            st = parse_status(line)
            if st is None:
                log.debug("%s: unparsable status %r", self.device, line)
                return
            if st.wco is not None and len(st.wco) > self._i:
                self._wco = st.wco[self._i]
            self._status, self._fresh_status = st, True
            return
        m = _ALARM_RE.match(line)
        if m:
            self._alarm = int(m.group(1))
            log.warning("%s: %s", self.device, line)
            if not self._collect_alarms:
                raise GrblAlarm(self.device, self._alarm)
            return
        if _BANNER_RE.match(line):
            self._banner_seen = True
            if not self._expect_reset:
                self._reference_lost = True
                self._needs_resync = True
                self._saved_wco = None
                raise HardwareError(self.device, f"the controller reset by itself ({line!r}: power, USB or a "
                                    "reset button): the angle reference is lost, home the table again",
                                    retryable=False)
            return
        m = _PARAM_RE.match(line)
        if m:
            try:
                self._params[m.group(1)] = tuple(float(v) for v in m.group(2).split(":")[0].split(","))
            except ValueError:
                pass
            return
        m = _SETTING_RE.match(line)
        if m:
            try:
                self.settings[int(m.group(1))] = float(m.group(2))
            except ValueError:
                pass
            return
        if line.startswith("[MSG:"):
            if "unlock" in line.lower():
                self._lock_msg = True
            log.info("%s: %s", self.device, line)
            return
        log.debug("%s: ignored %r", self.device, line)


# ---------------------------------------------------------------------- manual smoke test

def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="GRBL turntable smoke test: connect, (home), move, print status.")
    p.add_argument("--port", help="serial port of the controller, e.g. /dev/ttyUSB0")
    p.add_argument("--emulate", action="store_true", help="use the GRBL emulator instead of a controller")
    p.add_argument("--baudrate", type=int, default=115200)
    p.add_argument("--axis", default="X")
    p.add_argument("--units-per-degree", type=float, default=1.0)
    p.add_argument("--feed", type=float, default=30.0, help="degrees per second")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds per command")
    p.add_argument("--move-timeout", type=float, default=60.0)
    p.add_argument("--home", action="store_true", help="run the homing cycle first ($H)")
    p.add_argument("--unlock", action="store_true", help="unlock an alarm with $X (check the table first!)")
    p.add_argument("--angles", type=float, nargs="*", default=[0.0, 90.0, 180.0, 0.9, 0.0])
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    emu = None
    if a.emulate:
        from tdof20.capture.hardware.grbl_emulator import GrblEmulator
        emu = GrblEmulator(start_alarm=0 if a.home else None).start()
        a.port = emu.port
    if not a.port:
        p.error("give --port (or --emulate)")
    table = GrblTurntable(a.port, a.baudrate, a.axis, a.units_per_degree, a.feed, a.timeout, home=a.home)
    try:
        t = time.monotonic()
        table.connect()
        print(f"connected in {time.monotonic() - t:.2f} s: {table.status().raw}")
        if a.unlock:
            table.unlock()
            print("unlocked")
        if a.home:
            t = time.monotonic()
            table.home(a.move_timeout)
            print(f"homed in {time.monotonic() - t:.2f} s: angle {table.angle():.3f} deg")
        for ang in a.angles:
            t = time.monotonic()
            got = table.move_to(ang, a.move_timeout)
            print(f"move_to({ang:g}) -> {got:.3f} deg in {time.monotonic() - t:.2f} s; {table.status().raw}")
        return 0
    except HardwareError as e:
        print(f"error: {e}")
        return 1
    except KeyboardInterrupt:
        table.stop()
        print("stopped")
        return 130
    finally:
        table.close()
        if emu is not None:
            emu.stop()


if __name__ == "__main__":
    raise SystemExit(_main())
