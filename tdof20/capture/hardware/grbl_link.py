"""The line conversation with a GRBL 1.1 controller, under the turntable driver
(:class:`~tdof20.capture.hardware.grbl.GrblTurntable`, which holds the state): sending a line and
waiting for its answer (with a soft re-sync when one is lost), status reports, reading and
handling every line GRBL sends, and reading past the aftermath of an alarm.

Every read has a deadline, in slices of the serial port's read timeout. ``ALARM:N`` raises
:class:`~tdof20.capture.hardware.grbl_protocol.GrblAlarm` where it is read (or is recorded, while
the driver expects alarms: at connect, in stop()); a banner the driver did not expect is a
controller that reset by itself.
"""

from __future__ import annotations

import logging
import re
import time
from typing import Callable

import serial

from tdof20.capture.hardware.grbl_protocol import (LOCKING_ALARMS, GrblAlarm, GrblError, GrblStatus, banner_version,
                                                   parse_status)
from tdof20.capture.hardware.interfaces import HardwareError

log = logging.getLogger("tdof20.capture.hardware.grbl")

_QUERY_RESEND_S = 0.25        # resend "?" when a status report is late (lost byte, booting board)
_ALARM_SETTLE_S = 0.6         # GRBL pauses 0.5 s after ALARM:N, then its late "ok" and its banner

_OK = "ok"
_ERROR_RE = re.compile(r"^error:\s*(\d+)", re.I)
_ALARM_RE = re.compile(r"^ALARM:\s*(\d+)", re.I)
_PARAM_RE = re.compile(r"^\[(G5[4-9]|G28|G30|G92|TLO):([^\]]*)\]$")
_SETTING_RE = re.compile(r"^\$(\d+)=([-+0-9.]+)")


class _NoAnswer(HardwareError):
    """Nothing (useful) came back before a deadline."""


class GrblLink:
    """Reading, writing and handling GRBL's lines (a mixin of the turntable driver, which holds the
    port, the buffers and the controller's state)."""

    def _command(self, line: str, timeout_s: float | None = None, resend: bool = True,
                 deadline: float | None = None) -> None:
        """Send one line and wait for its answer, all within the deadline (``timeout_s`` from now)."""
        self._settle()
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
        self._settle()
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
            if st is None or (st.mpos is None and st.wpos is None):   # garbled on the line: ask again
                log.debug("%s: unparsable status %r", self.device, line)
                return
            if st.wco is not None and len(st.wco) > self._i:
                self._wco = st.wco[self._i]
            self._status, self._fresh_status = st, True
            self._alarm_at, self._critical = None, False    # a locked or pausing GRBL sends no report
            return
        m = _ALARM_RE.match(line)
        if m:
            self._alarm = int(m.group(1))
            self._alarm_at = time.monotonic()
            self._critical = self._alarm in LOCKING_ALARMS
            self._homing = False
            log.warning("%s: %s", self.device, line)
            if not self._collect_alarms:
                raise GrblAlarm(self.device, self._alarm, locked=self._critical)
            return
        version = banner_version(line)
        if version is not None:
            self._banner_seen = True
            self.version = version
            self._critical, self._homing = False, False
            if self._alarm_at is not None or self._alarm is not None:
                # the reset that ends an alarm (ALARM:3/6/8/9): G92 and modes are gone, the position kept
                self._alarm_at = None
                if not self._needs_resync:
                    self._saved_wco = self._wco
                    self._reset_context = "GRBL reset itself after it"
                self._needs_resync = True
                return
            if not self._expect_reset:
                self._reference_lost = True
                self._needs_resync = True
                self._reset_context = "after the controller reset by itself"
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
            if "check limits" in line.lower():        # a reset with a limit switch pressed, hard limits on
                self._check_limits = True
            if "reset to continue" in line.lower():   # after ALARM:1/2: locked until a soft reset
                self._critical, self._alarm_at = True, None
            log.info("%s: %s", self.device, line)
            return
        log.debug("%s: ignored %r", self.device, line)

    def _settle(self) -> None:
        """After ALARM:N GRBL pauses 0.5 s losing all input, then (unless the alarm locks it) sends the
        late ``ok`` of the line it was executing and its banner: read until the banner, the lock
        message or a status report (or 0.6 s after the alarm), and drop those late answers."""
        if self._alarm_at is None:
            return
        collect, expect = self._collect_alarms, self._expect_reset
        self._collect_alarms = self._expect_reset = True
        try:
            # _alarm_at moves on if another ALARM line comes; the pause is GRBL's, so is the deadline
            self._pump(time.monotonic() + 2 * _ALARM_SETTLE_S + self.timeout_s,
                       until=lambda: self._alarm_at is None or time.monotonic() >= self._alarm_at + _ALARM_SETTLE_S)
            self._drain_quiet(0.05, time.monotonic() + 0.2)   # "[MSG:'$H'|'$X' to unlock]", bytes in flight
        finally:
            self._collect_alarms, self._expect_reset = collect, expect
        self._alarm_at = None
        if self._responses:
            log.debug("%s: dropping %d late answers after ALARM:%s", self.device, len(self._responses), self._alarm)
            self._responses.clear()
