"""An emulated GRBL 1.1 controller on a pseudo-terminal, for tests and for dry runs in the lab.

:class:`GrblEmulator` opens a pty pair (``os.openpty``) in raw mode and plays GRBL on the master
side in a background thread; :attr:`GrblEmulator.port` is the slave's path (``/dev/pts/N``), a real
tty that pyserial, a G-code sender (UGS, CNCjs, bCNC) or ``GrblTurntable`` opens like a USB port.

What it does, after GRBL 1.1h (checked against the firmware compiled for the PC, grbl-sim):

* Opening the port does not reset the board (GRBL 1.1h and 0.9j on a board without an auto-reset
  circuit, or a USB-serial adapter that leaves DTR alone): it booted once at :meth:`start` (its banner
  went nowhere) and keeps its state across the host's close and open, alarm lock, machine position
  and G92 offsets included. ``auto_reset=True``: a board that resets when the host opens the port
  (DTR, like an Arduino Uno): after ``boot_s`` (input is ignored meanwhile, like a bootloader) it
  prints ``Grbl 1.1h ['$' for help]``, the machine position is 0 and G92 offsets are gone.
  ``start_alarm``: at power-up (default ``POWER_UP``) GRBL starts in the homing lock
  (``[MSG:'$H'|'$X' to unlock]``, ``HOMING_INIT_LOCK``) when homing is enabled (``$22=1``), else Idle;
  ``None`` starts Idle anyway (a controller unlocked or homed before the host came); ``0``: the
  lock; ``N`` in 1..9 also prints ``ALARM:N`` first (a controller that powers up with alarm N
  pending). ``version="0.9j"``: the banner and the status reports (``<Idle,MPos:…,WPos:…>``) of
  GRBL 0.9, still on many boards.
* Lines end with ``\\n`` or ``\\r`` (each ends a line; an empty line is answered ``ok``); comments
  and spaces are dropped. It answers ``ok`` / ``error:N`` like GRBL (the commands it knows:
  :mod:`tdof20.capture.hardware.grbl_emulator_commands`); G-code during an alarm gives ``error:9``.
* Motion takes the time GRBL takes (:mod:`tdof20.capture.hardware.grbl_timing`): a move is queued
  (``ok`` at once, like GRBL's planner, 15 blocks), the state is ``Run``, it accelerates at
  ``$120``-``$122`` to ``min(F, $110..$112)``, cruises and decelerates to stop at the target (each
  block from rest to rest), then ``Idle``. ``speed_units_per_s`` sets the max rates,
  ``accel_units_per_s2`` the accelerations (default: the max rate reached in 0.83 s, the ratio of
  GRBL's own defaults 500 mm/min and 10 mm/s²).
* Limit switches are inputs (:mod:`tdof20.capture.hardware.grbl_emulator_limits`): ``switches``
  maps axes to :class:`LimitSwitch` (default: the turntable's home flag on X, limit switches on Y
  and Z, each 2 units ahead of the start); the status report's ``Pn:`` lists the pressed ones.
  Hard limits (``$21=1``, ``hard_limits=True``): a limit pin that changes, pressed or released
  (moving off a switch re-trips it), raises ``ALARM:1`` at the point where it changed; a reset with
  a switch pressed prints ``[MSG:Check Limits]`` and locks. :meth:`GrblEmulator.set_switch` holds
  a switch pressed or released by hand.
* Homing (``$H``, ``error:5`` if ``$22=0``): the build's ``homing_cycles`` in order (default Z,
  then X and Y; ``("X",)`` for a firmware built for X only), each searching at ``$25`` over
  1.5 × ``$130``, pulling off ``$27``, locating at ``$24``, pulling off, with ``$26`` of debounce, as
  long as GRBL takes (5-11 s with GRBL's default rates; tests set fast rates and short travel);
  ``ALARM:9`` when a switch is not found, ``ALARM:8`` when the pull-off leaves it pressed,
  ``ALARM:6`` on a reset and ``ALARM:7`` on the safety-door byte 0x84 during the cycle. GRBL answers
  no ``?`` while it homes (one report when it ends), then ``ok``; the homed axes stand at ``-$27``.
  The physical position, and so the switches, survive resets.
* Soft limits (``$20=1``, needs ``$22=1``, else ``error:10``; ``soft_limits=True``): a move whose
  target leaves the machine travel ``[-$130, 0]`` gives ``ALARM:2`` (a running motion first stops
  with a feed hold); a jog gives ``error:15``.
* Alarms as the firmware raises them: ``ALARM:N``, then a 0.5 s pause (``alarm_pause_s``) in which
  all input is lost. ``ALARM:1`` (hard limit) and ``ALARM:2`` (soft limit) then print ``[MSG:Reset to
  continue]`` and lock the controller: it answers nothing, not even ``?`` or ``$X``, until a soft
  reset (0x18). Every other alarm resets the controller after the pause (``ALARM:3`` reset in
  motion, ``ALARM:6`` reset during homing, ``ALARM:8``/``9`` homing failures). Either way, a reset
  first sends the late ``ok`` of the line GRBL was executing (the ``$H``, the move that hit the
  soft limit), then the banner and ``[MSG:'$H'|'$X' to unlock]``; the machine position is kept.
* Real-time bytes anywhere in the stream: ``?`` status report
  (``<Run|MPos:12.000,0.000,0.000|FS:1800,0>``, ``WCO:`` every 10 reports when idle, 30 when busy,
  and right after an offset change), ``!`` feed hold (``Hold:1`` while decelerating at ``$120``,
  then ``Hold:0``), ``~`` cycle start, 0x18 soft reset (in motion: ``ALARM:3`` as above; after a
  completed hold: no alarm), 0x85 jog cancel.
* :meth:`GrblEmulator.trigger_alarm` raises ``ALARM:N`` at any time as the firmware would (motion
  stops, then the pause and the lock or the reset above);
  ``error_on`` maps commands to error codes (``{"G92": 20}``: any line with a G92 word; ``{"$H": 9}``:
  lines starting with ``$H``), ``drop_replies(n)`` loses the next n answers (a flaky cable),
  ``silent=True`` never answers anything (a wrong port). ``settings`` overrides ``$N`` values.

Dry run in the lab (Linux, macOS)::

    python -m tdof20.capture.hardware.grbl_emulator            # prints the port, Ctrl-C ends
    tdof20 capture ... with [turntable] backend = "grbl", port = "/dev/pts/N"
    python -m tdof20.capture.hardware.grbl --emulate --home     # the driver's smoke test on it
"""

from __future__ import annotations

import argparse
import collections
import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty
from dataclasses import dataclass

from tdof20.capture.hardware.grbl_emulator_commands import DEFAULT_SETTINGS, GrblCommands, _Deferred
from tdof20.capture.hardware.grbl_emulator_limits import (AXIS_LETTERS, DEFAULT_HOMING_CYCLES, DEFAULT_SWITCHES,
                                                          GrblLimits, Homing, LimitSwitch)
from tdof20.capture.hardware.grbl_timing import Segment

UNLOCK_MSG = "[MSG:'$H'|'$X' to unlock]"
RESET_MSG = "[MSG:Reset to continue]"
CHECK_LIMITS_MSG = "[MSG:Check Limits]"
POWER_UP = "power-up"                 # start_alarm: as GRBL powers up (the homing lock if $22=1)
_RAMP_S = (500.0 / 60.0) / 10.0       # GRBL's defaults reach $110=500 mm/min in 0.83 s at $120=10 mm/s²
_CRITICAL = (1, 2)                    # hard and soft limit: locked until a soft reset


def banner(version: str) -> str:
    """GRBL's welcome line for ``version`` (``1.1h``, ``0.9j``)."""
    return f"Grbl {version} ['$' for help]"


BANNER = banner("1.1h")


class GrblEmulator(GrblLimits, GrblCommands):
    """An emulated GRBL 1.1 controller on a pty; see the module docstring."""

    def __init__(self, start_alarm: int | None | str = POWER_UP, silent: bool = False,
                 speed_units_per_s: float = 360.0, error_on: dict[str, int] | None = None, *,
                 homing_pulloff: float = 1.0, homing_enabled: bool = True, report_wpos: bool = False,
                 steps_per_unit: float = 250.0, boot_s: float = 0.05, accel_units_per_s2: float | None = None,
                 alarm_pause_s: float = 0.5, auto_reset: bool = False, soft_limits: bool = False,
                 hard_limits: bool = False, switches: dict[str, LimitSwitch | float | None] | None = None,
                 homing_cycles: tuple[str, ...] = DEFAULT_HOMING_CYCLES, version: str = "1.1h",
                 settings: dict[int, float] | None = None):
        if not (speed_units_per_s > 0):
            raise ValueError(f"speed_units_per_s must be > 0, got {speed_units_per_s!r}")
        accel = float(accel_units_per_s2) if accel_units_per_s2 is not None else speed_units_per_s / _RAMP_S
        if not (accel > 0):
            raise ValueError(f"accel_units_per_s2 must be > 0, got {accel_units_per_s2!r}")
        if not (start_alarm is None or start_alarm == POWER_UP or isinstance(start_alarm, int)):
            raise ValueError(f"start_alarm must be None, {POWER_UP!r} or an alarm code, got {start_alarm!r}")
        self.start_alarm = start_alarm
        self.silent = bool(silent)
        self.error_on = {self._clean(k): int(v) for k, v in (error_on or {}).items()}
        self.boot_s = float(boot_s)
        self.alarm_pause_s = float(alarm_pause_s)
        self.auto_reset = bool(auto_reset)
        given = DEFAULT_SWITCHES if switches is None else switches
        self.switches: dict[str, LimitSwitch] = {}
        for axis, sw in given.items():
            if axis.upper() not in AXIS_LETTERS:
                raise ValueError(f"switches: no axis {axis!r} (X, Y, Z)")
            if sw is not None:
                self.switches[axis.upper()] = sw if isinstance(sw, LimitSwitch) else LimitSwitch(float(sw))
        cycles = tuple(str(c).upper() for c in homing_cycles)
        if not cycles or any(not c or set(c) - set(AXIS_LETTERS) for c in cycles):
            raise ValueError(f"homing_cycles must be groups of the axes X, Y, Z, got {homing_cycles!r}")
        self.homing_cycles = cycles
        self.version = str(version)
        self.settings = dict(DEFAULT_SETTINGS)
        for i in range(3):
            self.settings[100 + i] = float(steps_per_unit)
            self.settings[110 + i] = float(speed_units_per_s) * 60.0
            self.settings[120 + i] = accel
        self.settings[10] = 0 if report_wpos else 1
        self.settings[22] = 1 if homing_enabled else 0
        self.settings[20] = 1 if soft_limits else 0
        self.settings[21] = 1 if hard_limits else 0
        self.settings[27] = float(homing_pulloff)
        self.settings.update({int(k): float(v) for k, v in (settings or {}).items()})
        self.received: list[str] = []     # every command line received (as sent, without line end)
        self._lock = threading.RLock()
        self._master: int | None = None
        self._port: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._host_open = False
        self._drop = 0
        self._phys0 = [0.0, 0.0, 0.0]      # physical position of machine zero (survives resets)
        self._forced: dict[int, bool] = {}   # switches held pressed / released by hand (set_switch)
        self._pins_seen = ""
        self._init_machine(hard=True)

    # ------------------------------------------------------------------ public

    @property
    def port(self) -> str:
        if self._port is None:
            raise RuntimeError("GrblEmulator: call start() first")
        return self._port

    def start(self) -> "GrblEmulator":
        if self._thread is not None:
            return self
        master, slave = os.openpty()
        tty.setraw(slave)
        self._port = os.ttyname(slave)
        os.close(slave)                   # the host's open is detected as the end of the hang-up
        fl = fcntl.fcntl(master, fcntl.F_GETFL)
        fcntl.fcntl(master, fcntl.F_SETFL, fl | os.O_NONBLOCK)
        self._packet = False
        if hasattr(termios, "TIOCPKT"):     # packet mode: see the input flush pyserial does on open
            try:
                fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
                self._packet = True
            except OSError:
                pass
        self._master = master
        if not self.auto_reset:             # booted long before the host came: its banner went nowhere
            with self._lock:
                self._init_machine(hard=True)
                if self._limits_at_init():
                    self._alarm = True
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"grbl-emulator {self._port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        th, self._thread = self._thread, None
        if th is not None:
            th.join(2.0)
        fd, self._master = self._master, None
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "GrblEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def trigger_alarm(self, code: int) -> None:
        """Raise ``ALARM:code`` now, as the firmware does (see the module docstring)."""
        with self._lock:
            self._tick(time.monotonic())
            self._enter_alarm(int(code))

    @property
    def physical_position(self) -> tuple[float, ...]:
        """Where the axes really stand, units from where they stood at :meth:`start` (the switches'
        frame; survives resets and homing, unlike the machine position)."""
        with self._lock:
            self._tick(time.monotonic())
            return tuple(z + m for z, m in zip(self._phys0, self._mpos))

    def homing_plan(self) -> tuple[float, int | None]:
        """How long a ``$H`` from here would take, seconds, and the alarm it would end in (``None``:
        homed), from the settings and the switches."""
        with self._lock:
            self._tick(time.monotonic())
            h = self._plan_homing(0.0)
            return h.until, h.alarm

    @property
    def pins(self) -> str:
        """The pressed limit pins (``"X"``, ``""``), as the status report's ``Pn:`` lists them."""
        with self._lock:
            self._tick(time.monotonic())
            return self._pins()

    def drop_replies(self, n: int = 1) -> None:
        """Lose the next ``n`` ``ok``/``error`` answers (an unreliable link)."""
        with self._lock:
            self._drop += int(n)

    @property
    def state(self) -> str:
        with self._lock:
            self._tick(time.monotonic())
            return self._state_text()

    @property
    def mpos(self) -> tuple[float, ...]:
        with self._lock:
            self._tick(time.monotonic())
            return tuple(self._mpos)

    @property
    def wpos(self) -> tuple[float, ...]:
        with self._lock:
            self._tick(time.monotonic())
            return tuple(m - w for m, w in zip(self._mpos, self._wco()))

    @property
    def host_connected(self) -> bool:
        return self._host_open

    # ------------------------------------------------------------------ machine state

    def _init_machine(self, hard: bool, alarm: int | None = None) -> None:
        if hard:
            mpos = getattr(self, "_mpos", [0.0, 0.0, 0.0])
            self._phys0 = [p + m for p, m in zip(self._phys0, mpos)]
            self._mpos = [0.0, 0.0, 0.0]
            self._alarm = self._power_up_alarm() is not None
        self._parser_mpos = list(self._mpos)
        self._g92 = [0.0, 0.0, 0.0]
        self._absolute = True
        self._inches = False
        self._feed: float | None = None
        self._motion_mode: int | None = 0
        self._queue: collections.deque[Segment] = collections.deque()
        self._seg: Segment | None = None
        self._hold: str | None = None          # None, "decel", "held"
        self._homing: Homing | None = None
        self._report_asked = False             # a "?" during homing, answered when it ends
        self._deferred: _Deferred | None = None
        self._pending: collections.deque[bytes] = collections.deque()
        self._line = bytearray()
        self._overflow = False
        self._critical = False                 # ALARM:1/2: deaf until a soft reset
        self._pause_until: float | None = None  # the 0.5 s after an ALARM line: input is lost
        self._reset_after_pause = False
        self._late_ok = False                  # the line being executed is answered at the reset
        self._check = False
        self._sleep = False
        self._wco_counter = 0
        self._ovr_counter = 0
        self._last_tick = time.monotonic()
        self._boot_until: float | None = None
        if alarm is not None:
            self._alarm = True

    @staticmethod
    def _now() -> float:
        return time.monotonic()

    def _power_up_alarm(self) -> int | None:
        """The alarm GRBL powers up in: ``None`` (Idle), 0 (the homing lock) or N."""
        if self.start_alarm == POWER_UP:
            return 0 if int(self.settings.get(22, 0)) else None
        return self.start_alarm

    def _wco(self) -> list[float]:
        return list(self._g92)             # G54..G59 offsets are all zero here

    def _moving(self) -> bool:
        return self._seg is not None or bool(self._queue)

    def _state_text(self) -> str:
        if self._homing is not None:           # a $H from the alarm lock is Home until it ends
            return "Home"
        if self._alarm or self._critical:
            return "Alarm"
        if self._sleep:
            return "Sleep"
        if self._hold == "decel":
            return "Hold:1"
        if self._hold == "held":
            return "Hold:0"
        if self._check:
            return "Check"
        if self._moving():
            seg = self._seg or self._queue[0]
            return "Jog" if seg.jog else "Run"
        return "Idle"

    def _max_rate(self, axis: int) -> float:
        return max(self.settings.get(110 + axis, 500.0), 1e-6) / 60.0

    def _max_accel(self, axis: int) -> float:
        return max(self.settings.get(120 + axis, 10.0), 1e-6)

    def _steps(self, axis: int) -> float:
        return self.settings.get(100 + axis, 250.0)

    # ------------------------------------------------------------------ I/O thread

    def _run(self) -> None:
        """Serve the pty. The host opening the port (the hang-up ends, or pyserial's input flush on
        open, seen in packet mode) resets the emulated board like an Arduino's DTR line."""
        fd = self._master
        poller = select.poll()
        poller.register(fd, select.POLLIN | select.POLLPRI | select.POLLHUP | select.POLLERR)
        while not self._stop.is_set():
            try:
                events = poller.poll(5)
            except InterruptedError:
                continue
            except (OSError, ValueError):
                return
            hup = any(ev & (select.POLLHUP | select.POLLERR) for _, ev in events)
            data = b""
            opened = False
            if any(ev & (select.POLLIN | select.POLLPRI) for _, ev in events):
                try:
                    packet = os.read(fd, 4097)
                    if not self._packet:
                        data = packet
                    elif packet[:1] == b"\x00":
                        data = packet[1:]
                    elif packet and packet[0] & getattr(termios, "TIOCPKT_FLUSHREAD", 1):
                        opened = True             # pyserial flushes the input when it opens the port
                except BlockingIOError:
                    pass
                except OSError:
                    hup = True
            with self._lock:
                now = time.monotonic()
                if hup and not data:
                    self._host_open = False
                    self._tick(now)
                    time.sleep(0.01)
                    continue
                if not self._host_open or opened:
                    self._host_open = True
                    if self.auto_reset:
                        self._power_on(now)
                self._tick(now)
                if data:
                    self._feed_bytes(data)
                    self._tick(time.monotonic())

    def _out(self, text: str) -> None:
        if self.silent or self._master is None:
            return
        data = (text + "\r\n").encode("ascii", "replace")
        try:
            while data:
                n = os.write(self._master, data)
                data = data[n:]
        except OSError:
            pass                                    # nobody listening / buffer full: a UART does not care

    def _reply(self, code: int = 0) -> None:
        if self._drop > 0:
            self._drop -= 1
            return
        self._out("ok" if code == 0 else f"error:{code}")

    def _power_on(self, now: float) -> None:
        """The board (re)starts: an Arduino resets when the host opens the port (DTR), boots, prints
        its banner."""
        self._init_machine(hard=True)
        self._boot_until = now + self.boot_s

    def _boot_output(self) -> None:
        self._out("")
        self._out(banner(self.version))
        code = self._power_up_alarm()
        if code:
            self._out(f"ALARM:{code}")
        if self._limits_at_init():
            self._alarm = True
            self._out(CHECK_LIMITS_MSG)
        if self._alarm:
            self._out(UNLOCK_MSG)

    def _soft_reset(self) -> None:
        """0x18 (or the end of an alarm's pause): the late ``ok`` of the line in execution, then
        GRBL's reset: parser and planner cleared, G92 gone, the machine position kept."""
        if self._pause_until is not None:
            return                                  # GRBL is already resetting
        if not self._critical:
            if self._homing is not None:
                self._enter_alarm(6)
                return
            if self._moving() and self._hold != "held" and not self._check:
                self._enter_alarm(3)
                return
        if self._deferred is not None and self._deferred.reply:
            self._late_ok = True
        if self._late_ok:
            self._reply(0)
        was_alarm = self._alarm or self._critical or self._sleep
        self._init_machine(hard=False)
        self._alarm = bool(was_alarm)
        self._out("")
        self._out(banner(self.version))
        if self._limits_at_init():               # CHECK_LIMITS_AT_INIT: a switch pressed, hard limits on
            self._alarm = True
            self._out(CHECK_LIMITS_MSG)
        if self._alarm:
            self._out(UNLOCK_MSG)

    def _enter_alarm(self, code: int, late_ok: bool = False) -> None:
        """``ALARM:code``: motion stops, then the pause; then the lock (1, 2), or the reset."""
        self._seg = None
        self._queue.clear()
        self._parser_mpos = list(self._mpos)
        self._homing = None
        if self._deferred is not None and self._deferred.reply:
            late_ok = True
        self._deferred = None
        self._late_ok = self._late_ok or late_ok
        self._pending.clear()
        self._line.clear()
        self._hold = None
        self._alarm = True
        self._out(f"ALARM:{code}")
        self._critical = code in _CRITICAL
        self._reset_after_pause = code in (3, 6, 7, 8, 9)
        self._pause_until = time.monotonic() + self.alarm_pause_s

    def _end_pause(self) -> None:
        self._pause_until = None
        self._pending.clear()
        self._line.clear()
        if self._critical:
            self._out(RESET_MSG)
        elif self._reset_after_pause:
            self._reset_after_pause = False
            self._soft_reset()

    def _feed_bytes(self, data: bytes) -> None:
        for b in data:
            if self._boot_until is not None or self._pause_until is not None:
                continue                            # a bootloader, or an alarm's pause: input is lost
            if self.silent:
                continue
            if b == 0x18:
                self._soft_reset()
                continue
            if self._critical:
                continue                            # locked: only a reset is heard
            if b == 0x3F:                           # ?
                if self._homing is not None:
                    self._report_asked = True       # no time for reports while homing
                else:
                    self._report()
                continue
            if b == 0x21:                           # !
                self._feed_hold()
                continue
            if b == 0x7E:                           # ~ cycle start: resume after a completed hold
                if self._hold == "held":
                    self._hold = None
                continue
            if b >= 0x80:
                if b == 0x84 and self._homing is not None:
                    self._enter_alarm(7)            # the safety door opened during homing
                    continue
                if b == 0x85 and self._moving() and (self._seg or self._queue[0]).jog:
                    self._feed_hold()
                continue
            if b in (0x0A, 0x0D):
                self._pending.append(b"\xff" if self._overflow else bytes(self._line))
                self._line.clear()
                self._overflow = False
                continue
            if len(self._line) >= self.LINE_BUFFER:
                self._overflow = True
            else:
                self._line.append(b)
        self._process_pending()

    def _feed_hold(self) -> None:
        if self._moving() and self._hold is None and self._homing is None and not self._check:
            self._hold = "decel"

    def _process_pending(self) -> None:
        while self._pending and self._deferred is None and self._pause_until is None:
            raw = self._pending.popleft()
            if self._critical:
                continue
            if raw == b"\xff":
                self.received.append("<overflow>")
                self._reply(11)
                continue
            text = raw.decode("ascii", "replace")
            self.received.append(text)
            code = self._execute(text)
            if code is not None:
                self._reply(code)

    def _tick(self, now: float) -> None:
        dt = max(now - self._last_tick, 0.0)
        self._last_tick = now
        if self._boot_until is not None:
            if now < self._boot_until:
                return
            self._boot_until = None
            self._boot_output()
        if self._pause_until is not None:
            if now < self._pause_until:
                return
            self._end_pause()
        if self._critical:
            return
        if self._homing is not None:
            self._homing_tick(now)
        if self._hold == "decel":
            seg = self._seg or (self._queue[0] if self._queue else None)
            if seg is not None and seg.v > 0:
                before, done0 = list(self._mpos), seg.done
                seg.advance(dt, hold=True)
                self._mpos = seg.at()
                dt = 0.0
                f = self._first_pin_change(before, self._mpos)
                if f is not None:                      # a limit pin changed while stopping
                    seg.done = done0 + (seg.done - done0) * f
                    self._mpos = seg.at()
                    self._check_pins()
                    return
            if seg is None or seg.v <= 0:
                self._hold = "held"
                if seg is not None and seg.jog:      # a held jog is cancelled
                    self._seg = None
                    self._queue.clear()
                    self._parser_mpos = list(self._mpos)
                    self._hold = None
        if self._hold is None and self._homing is None:
            self._advance(dt)
        if self._homing is None and not self._critical:
            self._check_pins()
        d = self._deferred
        if d is not None and d.ready() and self._deferred is d:
            self._deferred = None
            if d.reply:
                self._reply(0)
            self._process_pending()

    def _advance(self, dt: float) -> None:
        while dt > 0:
            if self._seg is None:
                if not self._queue:
                    return
                self._seg = self._queue.popleft()
            seg = self._seg
            before = list(self._mpos)
            done0 = seg.done
            dt = seg.advance(dt)
            self._mpos = seg.at()
            f = self._first_pin_change(before, self._mpos)
            if f is not None:                          # a limit pin changed on the way: a hard limit
                seg.done = done0 + (seg.done - done0) * f
                self._mpos = seg.at()
                self._check_pins()
                return
            if seg.finished:
                self._mpos = list(seg.target)
                self._seg = None

    def _report(self, tick: bool = True, state: str | None = None) -> None:
        if tick:
            self._tick(time.monotonic())
        state = state or self._state_text()
        wco = self._wco()
        pos = [round(p * self._steps(i)) / self._steps(i) if self._steps(i) > 0 else p
               for i, p in enumerate(self._mpos)]
        wpos = [p - w for p, w in zip(pos, wco)]
        if self.version.startswith("0."):        # GRBL 0.9: commas, both positions
            self._out(f"<{state.split(':')[0]},MPos:" + ",".join(f"{p:.3f}" for p in pos)
                      + ",WPos:" + ",".join(f"{p:.3f}" for p in wpos) + ">")
            return
        wpos_mode = int(self.settings.get(10, 1)) & 1 == 0
        seg = self._seg
        feed = seg.v * 60.0 if seg is not None and self._homing is None else 0.0
        fields = [state, ("WPos:" + ",".join(f"{p:.3f}" for p in wpos)) if wpos_mode
                  else ("MPos:" + ",".join(f"{p:.3f}" for p in pos)), f"FS:{feed:.0f},0"]
        pins = self._pins()
        if pins:
            fields.append(f"Pn:{pins}")
        if self._wco_counter <= 0:
            fields.append("WCO:" + ",".join(f"{w:.3f}" for w in wco))
            self._wco_counter = 30 if self._moving() else 10
        else:
            self._wco_counter -= 1
            if self._ovr_counter <= 0:
                fields.append("Ov:100,100,100")
                self._ovr_counter = 20
            else:
                self._ovr_counter -= 1
        self._out("<" + "|".join(fields) + ">")

    def _soft_limit_hit(self, target: list[float]) -> bool:
        """Whether ``target`` (machine units) leaves the travel ``[-$130, 0]`` with ``$20=1``."""
        if not int(self.settings.get(20, 0)):
            return False
        return any(t > 1e-9 or t < -self.settings.get(130 + i, 200.0) - 1e-9 for i, t in enumerate(target))

    def _soft_limit_alarm(self) -> None:
        """A move beyond the soft limits: GRBL holds a running motion, then ``ALARM:2``; the line's
        ``ok`` comes after the reset."""
        if not self._moving():
            self._enter_alarm(2, late_ok=True)
            return
        self._feed_hold()

        def stopped() -> bool:
            if self._hold == "held" or not self._moving():
                self._enter_alarm(2, late_ok=True)
            return False
        self._deferred = _Deferred(stopped)


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Run an emulated GRBL 1.1 controller on a pseudo-terminal.")
    p.add_argument("--speed", type=float, default=360.0, help="max rate, units per second")
    p.add_argument("--accel", type=float, default=None, help="acceleration, units per second squared")
    p.add_argument("--start-alarm", type=int, default=None,
                   help="start in alarm: 0 = homing lock, 1..9 = ALARM:N pending (default: as GRBL powers up)")
    p.add_argument("--no-homing", action="store_true", help="homing disabled ($22=0)")
    p.add_argument("--x-only", action="store_true", help="a firmware built to home X only (default: Z, then XY)")
    p.add_argument("--switch-distance", type=float, default=2.0,
                   help="units from the start to the X home flag (once per 360 units) and the Y/Z limit switches")
    p.add_argument("--auto-reset", action="store_true", help="a board that resets when the port opens (DTR)")
    p.add_argument("--soft-limits", action="store_true", help="soft limits on ($20=1)")
    p.add_argument("--hard-limits", action="store_true", help="hard limits on ($21=1)")
    p.add_argument("--set", action="append", default=[], metavar="N=V", help="a setting, e.g. --set 25=3000")
    a = p.parse_args(argv)
    d = a.switch_distance
    settings = {}
    for item in a.set:
        key, _, val = item.partition("=")
        try:
            settings[int(key.lstrip("$"))] = float(val)
        except ValueError:
            p.error(f"--set {item!r}: expected N=VALUE, e.g. 25=3000")
    emu = GrblEmulator(POWER_UP if a.start_alarm is None else a.start_alarm, speed_units_per_s=a.speed,
                       homing_enabled=not a.no_homing, accel_units_per_s2=a.accel, auto_reset=a.auto_reset,
                       soft_limits=a.soft_limits, hard_limits=a.hard_limits,
                       switches={"X": LimitSwitch(d, 2.0, 360.0), "Y": LimitSwitch(d), "Z": LimitSwitch(d)},
                       homing_cycles=("X",) if a.x_only else DEFAULT_HOMING_CYCLES, settings=settings).start()
    print(f"GRBL emulator on {emu.port} (Ctrl-C ends)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
