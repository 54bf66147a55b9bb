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

Protocol, as GRBL 1.1 documents it (codes, reports: :mod:`tdof20.capture.hardware.grbl_protocol`;
reading and answering lines: :mod:`tdof20.capture.hardware.grbl_link`):
one command line at a time, each answered by ``ok`` or ``error:N``; ``ALARM:N`` may arrive at any
time (an alarm stops the driver: a person must act); the real-time byte ``?`` asks for a status
report ``<Idle|MPos:12.000,0.000,0.000|FS:0,0>``; ``!`` is a feed hold and ``0x18`` a soft reset.
The driver works in the G54 work coordinate system plus a G92 offset set after homing, so that the
table's reference is 0 degrees; it tracks the work coordinate offset (``$#`` and the ``WCO``
field) to turn machine positions into table angles.

Every read has a deadline: a silent controller gives a :class:`HardwareError` naming the port and
what was awaited. A command whose ``ok`` does not come is re-sent after a soft re-sync (an empty
line, which GRBL answers with ``ok``), at most ``retries`` times; an acknowledged command is never
re-sent (all commands sent are absolute, so a re-send of an unacknowledged one is harmless).

What the firmware does after an alarm, and how the driver copes (checked against GRBL 1.1h
compiled for the PC, grbl-sim):

* After ``ALARM:N`` GRBL pauses 0.5 s and loses everything sent meanwhile (``?`` and ``$X``
  included). A homing failure (``ALARM:6`` reset during homing, ``8``, ``9``) or a reset in motion
  (``ALARM:3``) then resets the controller: the late ``ok`` of the ``$H`` (or of the line it was
  executing), then the banner. Before it sends anything after an alarm the driver waits for that
  banner (or 0.6 s) and drops the late answers, so none is taken for the answer to a later line.
* ``ALARM:1`` (hard limit) and ``ALARM:2`` (soft limit) lock GRBL until a soft reset: it ignores
  ``?`` and ``$X``. :meth:`GrblTurntable.status` then refuses at once; :meth:`~GrblTurntable.home`
  and :meth:`~GrblTurntable.unlock` reset the controller (ctrl-x) first. A controller that answers
  no ``?`` at connect (such a lock survives a close on a board that does not reset when its port
  opens) gets one soft reset before the driver gives up on it.
* GRBL answers no ``?`` while it homes, and bounds a homing cycle itself (``ALARM:9`` when the
  switch is not found within 1.5 × ``$130``): :meth:`~GrblTurntable.home` waits at least GRBL's own
  worst case from the settings (:func:`~tdof20.capture.hardware.grbl_timing.homing_worst_case_s`);
  if even that passes it aborts the cycle (ctrl-x) so that no later line queues behind it.
* GRBL 0.9 and older (another report format) are refused with their version named.

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

import serial

from tdof20.capture.hardware.grbl_link import _QUERY_RESEND_S, GrblLink, _NoAnswer
from tdof20.capture.hardware.grbl_protocol import (ALARM_CODES, ERROR_CODES, HOMING_REQUIRED, GrblAlarm, GrblError,
                                                   GrblStatus, describe_alarm, describe_error, parse_status)
from tdof20.capture.hardware.grbl_timing import homing_worst_case_s
from tdof20.capture.hardware.interfaces import HardwareError, Turntable

__all__ = ["ALARM_CODES", "ERROR_CODES", "HOMING_REQUIRED", "GrblAlarm", "GrblError", "GrblStatus", "GrblTurntable",
           "describe_alarm", "describe_error", "parse_status"]

log = logging.getLogger(__name__)

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")
AXES = "XYZABC"
_READ_SLICE_S = 0.02          # pyserial read timeout: the granularity of every deadline
_QUIET_S = 0.15               # "nothing more is coming" after the wake-up / a reset
_SILENT_RESET_S = 2.0         # at connect, a "?" unanswered this long: reset (a lock, or homing)


def _locked(fn):
    """Run a public method under the driver's I/O lock (one conversation with GRBL at a time)."""
    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        with self._io:
            return fn(self, *args, **kwargs)
    return wrapper


class GrblTurntable(GrblLink, Turntable):
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
        self._alarm_at: float | None = None   # when it came, until its aftermath (pause, late ok, banner) is read
        self._critical = False           # ALARM:1/2: GRBL is deaf to all but a soft reset
        self._homing = False             # a $H is running: GRBL answers no "?"
        self._reset_context = ""         # why the controller was reset (for the message after it)
        self.version: str | None = None  # from the banner
        self._lock_msg = False           # "[MSG:'$H'|'$X' to unlock]" seen
        self._check_limits = False       # "[MSG:Check Limits]" seen: a reset found a limit switch pressed
        self._collect_alarms = False     # record ALARM lines instead of raising (handshake, stop)
        self._expect_reset = False       # a banner is expected (connect, stop(), the driver's resets)
        self._banner_seen = False
        self._needs_resync = False       # the controller was reset (stop(), an alarm, the driver): re-sync
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
            self._check_version(st)
            if st.state in ("Run", "Jog", "Home", "Hold", "Door"):
                st = self._wait_idle(st)
            if st.state != "Alarm":
                self._check_usable(st, "at connect")
            self._read_settings()             # $21 (hard limits) tells what a pressed switch means
            if st.state == "Alarm":
                code = self._alarm if self._alarm is not None else st.substate
                what = todo = None
                if self._reset_context and code is None:
                    what = ("it answered nothing until the driver reset it (ctrl-x): locked by a hard or soft "
                            "limit alarm, or busy homing")
                elif code is None and self._check_limits:
                    what = "GRBL started with a limit switch pressed and locked itself ([MSG:Check Limits])"
                elif code is None and not self._banner_seen:
                    what = ("GRBL is in its alarm lock from before this connection: an earlier alarm, whose "
                            "ALARM line went to an earlier host, or its power-up homing lock (this board did not "
                            "reset when its port opened)")
                pressed = self._pressed_limits(st)
                context = f"at connect; {pressed}" if pressed else "at connect"
                if pressed:
                    todo = self._switch_todo()
                if not self.home_on_connect:
                    raise GrblAlarm(self.device, code, context, what=what, todo=todo)
                log.warning("%s: ALARM at connect (%s%s); homing is planned", self.device,
                            what or describe_alarm(code), f"; {pressed}" if pressed else "")
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
        """``$H`` (homing cycle), then make the table's angle 0 (``G92`` if needed). A controller
        locked by ``ALARM:1``/``2`` is reset first. The wait for the cycle is ``timeout_s`` or GRBL's
        own worst case from its settings, whichever is longer; past it the cycle is aborted."""
        self._ready(allow_alarm=True, reset_if_locked=True)
        wait = float(timeout_s)
        bound = self._homing_bound_s()
        if bound is not None and bound > wait:
            log.info("%s: homing may take up to %.0f s (GRBL's own limit from $130-$132, $24-$27): waiting that "
                     "long instead of %g s; to home faster lower $130 (max travel) or raise $25 (seek rate)",
                     self.device, bound, wait)
            wait = bound
        self._alarm = None
        self._saved_wco = None                # homing sets the reference anew
        self._homing = True                   # until its answer, an alarm or a reset
        try:
            self._command("$H", timeout_s=wait, resend=False)
        except GrblError as e:
            self._homing = False
            if e.code != 5:
                raise
            log.warning("%s: homing is disabled on the controller ($22=0): taking the current position "
                        "as 0 degrees", self.device)
        except _NoAnswer:
            self._abort_homing()
            raise HardwareError(self.device, f"homing did not finish within {wait:.0f} s "
                                f"({self._homing_limits(bound)}); the cycle was aborted (reset): check the home "
                                "switch and its wiring, then home again", retryable=False) from None
        self._homing = False
        deadline = time.monotonic() + self.timeout_s
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
        self._ready(context=f"cannot move to {angle_deg:g} deg")
        deadline = t0 + float(timeout_s)
        if self._reference_lost:
            raise HardwareError(self.device, "the controller was reset: the angle reference is lost, "
                                "home the table before moving it", retryable=False)
        if self._alarm is not None:           # GRBL is locked until $H / $X
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
        """A fresh status report (a controller locked by ``ALARM:1``/``2`` sends none: GrblAlarm)."""
        self._ready(allow_alarm=True, context="no status report while locked")
        return self._query_status(time.monotonic() + self.timeout_s)

    @_locked
    def unlock(self) -> None:
        """``$X``: leave an alarm without homing (the operator checked the table); a controller locked
        by ``ALARM:1``/``2`` is reset first. The machine position survives; the G92 offset is re-applied."""
        self._ready(allow_alarm=True, reset_if_locked=True)
        deadline = time.monotonic() + self.timeout_s
        pressed = self._pressed_limits(self._query_status(deadline))
        if pressed:
            # GRBL's limit interrupt fires on any pin change: after $X the first step off the switch
            # trips ALARM:1 again (and the position with it), so do not unlock into that
            raise GrblAlarm(self.device, self._alarm, f"{pressed}, so $X was not sent", todo=self._switch_todo())
        self._command("$X", deadline=deadline)
        self._alarm = None
        self._set_modes(deadline)
        self._refresh_wco(deadline)
        self._restore_offset(deadline)

    @_locked
    def command(self, line: str, timeout_s: float | None = None) -> None:
        """Send one raw line and wait for its ``ok`` (for manual use; no re-send)."""
        self._ready(allow_alarm=True, context=f"cannot send {line.strip()!r}")
        self._command(line.strip(), timeout_s=timeout_s, resend=False)

    def stop(self) -> None:
        """Feed hold ``!`` now, wait (at most ``timeout_s``) for the table to stop, then soft reset
        (0x18); never raises. Callable from another thread: a running move_to()/home() there ends with
        a HardwareError. A reset after a completed hold keeps the position and the next call re-applies
        the modes and the G92 offset; a reset in motion puts GRBL in ALARM:3 (home again), one during
        homing in ALARM:6. Right after an alarm it first waits out GRBL's 0.5 s pause (a reset sent in
        it is lost)."""
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
                if got:
                    self._settle()            # a reset sent in an alarm's pause would be lost
            except Exception as e:  # noqa: BLE001 - best effort
                log.debug("%s: after the alarm: %s", self.device, e)
            try:
                if got and self._alarm is None and not self._needs_resync and not self._homing:
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
                self._reset_context = "after stop()"
                self._critical = False
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
        self._alarm, self._lock_msg, self._banner_seen, self._check_limits = None, False, False, False
        self._needs_resync, self._reference_lost, self._saved_wco = False, False, None
        self._alarm_at, self._critical, self._homing, self._reset_context = None, False, False, ""
        self.version = None
        self._collect_alarms, self._expect_reset = True, True
        start = time.monotonic()
        reset_at = start + min(_SILENT_RESET_S, self.timeout_s / 2)
        try:
            self._write(b"\r\n\r\n")
            next_query = start + 0.1
            self._fresh_status = False
            banner_asked = False
            while not self._fresh_status:
                now = time.monotonic()
                if now >= deadline:
                    after = ", also after a soft reset" if self._reset_context else ""
                    raise _NoAnswer(self.device, f"no answer within {self.timeout_s:g} s: waited for GRBL's "
                                    f"startup banner or a status report{after} (is this the controller's port, "
                                    f"{self.baudrate} baud, and is it powered?)")
                if now >= reset_at and not self._reset_context and (not self._banner_seen or self._critical):
                    # GRBL answers no "?" while locked by ALARM:1/2 (it outlives a close on a board that
                    # does not reset when opened) or while homing: a soft reset ends both
                    log.warning("%s: no answer to '?' within %.1f s: resetting the controller (ctrl-x)",
                                self.device, now - start)
                    self._reset_context = "after the reset at connect"
                    self._banner_seen = False
                    self._write(b"\x18")
                    next_query = now + 0.1
                if now >= next_query or (self._banner_seen and not banner_asked):
                    banner_asked = banner_asked or self._banner_seen
                    self._write(b"?")
                    next_query = now + _QUERY_RESEND_S
                self._pump(min(deadline, now + 0.05), until=lambda: self._fresh_status)
            self._drain_quiet(_QUIET_S, deadline)   # the wake-up lines' "ok"s, late banner / messages
        finally:
            self._collect_alarms, self._expect_reset = False, False
        self._responses.clear()
        self._alarm_at, self._needs_resync, self._saved_wco = None, False, None   # connect() sets up anew
        st = self._status
        assert st is not None
        if st.state != "Alarm" and self._alarm is not None:
            self._alarm = None                      # a reported alarm that was cleared since
        return st

    def _check_version(self, st: GrblStatus) -> None:
        """Refuse GRBL 0.9 and older (another report format, errors in words), naming the version."""
        old = self.version is not None and re.match(r"^0\.|^1\.0", self.version)
        if st.legacy or old:
            seen = f"GRBL {self.version}" if self.version else f"GRBL 0.9 or older (status report {st.raw!r})"
            raise HardwareError(self.device, f"the controller runs {seen}; this driver speaks GRBL 1.1: flash "
                                "GRBL 1.1h onto the board (github.com/gnea/grbl, e.g. with the Arduino IDE)",
                                retryable=False)

    def _ready(self, allow_alarm: bool = False, reset_if_locked: bool = False, context: str = "") -> None:
        """Before a public call talks to GRBL: read an alarm's aftermath; a controller locked by
        ALARM:1/2 is reset (``reset_if_locked``) or refused; after a reset, re-sync."""
        if self._ser is None:
            raise HardwareError(self.device, "not connected: call connect() first", retryable=False)
        self._settle()
        if self._critical:
            if not reset_if_locked:
                raise GrblAlarm(self.device, self._alarm, context, locked=True)
            self._reset_locked()
        if self._needs_resync:
            self._resync_after_reset(allow_alarm)

    def _reset_locked(self) -> None:
        """Soft reset (ctrl-x) of a controller locked by ALARM:1/2; afterwards it is in the alarm lock,
        the machine position kept, the G92 offset gone (re-applied by unlock())."""
        deadline = time.monotonic() + self.timeout_s
        log.warning("%s: resetting the controller (ctrl-x) to leave ALARM:%s", self.device, self._alarm)
        if not self._needs_resync:
            self._saved_wco = self._wco
        self._collect_alarms = self._expect_reset = True
        self._banner_seen = self._check_limits = False
        try:
            self._write(b"\x18")
            self._wait(lambda: self._banner_seen, deadline, "GRBL's banner after a reset (ctrl-x)")
            self._drain_quiet(0.05, min(deadline, time.monotonic() + 0.3))
        finally:
            self._collect_alarms = self._expect_reset = False
        self._responses.clear()
        self._critical, self._alarm_at = False, None
        self._needs_resync, self._reset_context = True, f"after the reset that ended ALARM:{self._alarm}"

    def _abort_homing(self) -> None:
        """A homing cycle that outlived its wait: reset (ALARM:6, then its late ``ok`` and the banner)
        so that no later line queues behind it; best effort."""
        try:
            self._expect_reset = True
            self._alarm_at = time.monotonic()
            self._write(b"\x18")
            self._settle()
        except HardwareError as e:
            log.debug("%s: aborting the homing cycle: %s", self.device, e)
        finally:
            self._expect_reset = False
            self._homing = False
        self._needs_resync, self._reset_context = True, "after the aborted homing"

    def _homing_bound_s(self) -> float | None:
        """GRBL's own worst case for ``$H`` from the settings read at connect (``None``: unknown)."""
        if not all(k in self.settings for k in (24, 25, 27, 130)):
            return None
        return 1.25 * homing_worst_case_s(self.settings) + 2.0

    def _homing_limits(self, bound: float | None) -> str:
        if bound is None:
            return ("GRBL's homing settings are unknown: allow 1.5 x $130 (max travel) at $25 (seek rate) per axis, "
                    "or raise [turntable] timeout_s")
        s = self.settings
        return (f"GRBL's own limit from $130={s[130]:g} (max travel), $25={s[25]:g} (seek rate), "
                f"$24={s[24]:g}, $27={s[27]:g} is {bound:.0f} s")

    def _restore_offset(self, deadline: float) -> None:
        """Re-apply the G92 offset a soft reset removed (the machine position survives it)."""
        if self._saved_wco is not None and abs(self._wco - self._saved_wco) > 1e-6:
            st = self._query_status(deadline)
            mpos = self._work_units(st) + self._wco
            self._command(f"G92 {self.axis}{mpos - self._saved_wco:.4f}", deadline=deadline)
            self._refresh_wco(deadline)
        self._saved_wco = None

    def _resync_after_reset(self, allow_alarm: bool) -> None:
        """After a soft reset (stop(), an alarm's, the driver's): swallow the banner, re-apply modes and
        the G92 offset (kept for unlock() while GRBL stays in the alarm lock)."""
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
                            self._reset_context)
        self._alarm = None
        self._set_modes(deadline)
        self._refresh_wco(deadline)
        self._restore_offset(deadline)

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

    def _pressed_limits(self, st: GrblStatus) -> str:
        """Words for limit switches GRBL reports pressed (``Pn:``, or its ``[MSG:Check Limits]``) while
        hard limits are on (``$21=1``); ``""`` when none is, or hard limits are off (then a pressed
        switch is only an input)."""
        pins = st.limit_pins()
        hard = int(self.settings.get(21, 1 if self._check_limits else 0))
        if not hard or not (pins or self._check_limits):
            return ""
        which = f"the {'/'.join(pins)} limit switch is pressed (Pn:{st.pins})" if pins else \
            "a limit switch is pressed ([MSG:Check Limits])"
        return f"{which} with hard limits on ($21=1)"

    @staticmethod
    def _switch_todo() -> str:
        return ("home the table (the homing cycle starts from the switch and pulls off it: home() or [turntable] "
                "home = true), or free the switch by hand; $X is not enough: while hard limits are on, the first "
                "step off the switch trips ALARM:1 again")

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
