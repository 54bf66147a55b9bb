"""An emulated GRBL 1.1 controller on a pseudo-terminal, for tests and for dry runs in the lab.

:class:`GrblEmulator` opens a pty pair (``os.openpty``) in raw mode and plays GRBL on the master
side in a background thread; :attr:`GrblEmulator.port` is the slave's path (``/dev/pts/N``), a real
tty that pyserial, a G-code sender (UGS, CNCjs, bCNC) or ``GrblTurntable`` opens like a USB port.

What it does, after GRBL 1.1h:

* Opening the port resets the "board" like an Arduino's DTR line: after ``boot_s`` (input is
  ignored meanwhile, like a bootloader) it prints ``Grbl 1.1h ['$' for help]``, the machine
  position is 0 and G92 offsets are gone. ``start_alarm``: ``None`` starts Idle; ``0`` starts in the
  power-up homing lock (``[MSG:'$H'|'$X' to unlock]``, as with ``$22=1``); ``N`` in 1..9 also
  prints ``ALARM:N`` first (a controller that powers up with alarm N pending).
* Lines end with ``\\n`` or ``\\r`` (each ends a line; an empty line is answered ``ok``); comments
  and spaces are dropped. It answers ``ok`` / ``error:N`` like GRBL: ``G0``/``G1`` with X/Y/Z and F
  (``error:22`` without a feed), ``G4 P``, ``G20``/``G21``, ``G90``/``G91``, ``G92``, ``G53``,
  ``G54``-``G59``, ``G17``-``G19``, ``G94``, ``M0``-``M9``/``M30`` (no-ops); other G-codes give
  ``error:20``; G-code during an alarm ``error:9``. System commands: ``$``, ``$$``, ``$#``,
  ``$G``, ``$I``, ``$H`` (homing: state Home for ``homing_s``, then machine position
  ``-$27`` = ``-homing_pulloff``, ``ok`` at the end; ``error:5`` if ``homing_enabled`` is False),
  ``$X`` (unlock), ``$C`` (check mode), ``$SLP``, ``$J=`` (jog), ``$N=value`` (``$10`` switches
  MPos/WPos reports, ``$22`` homing, ``$27`` pull-off, ``$100``-``$102`` steps/unit, which quantise
  reported positions, ``$110``-``$112`` max rates, units/min).
* Motion takes time: a move is queued (``ok`` at once, like GRBL's planner, 15 blocks), the state
  is ``Run`` and the position moves at ``min(F/60, max rate)`` units/s (``speed_units_per_s`` is
  the max rate; no acceleration); then ``Idle``.
* Real-time bytes anywhere in the stream: ``?`` status report
  (``<Run|MPos:12.000,0.000,0.000|FS:1800,0>``, ``WCO:`` every 10 reports when idle, 30 when busy,
  and right after an offset change), ``!`` feed hold (``Hold:1`` for ``hold_decel_s``, then
  ``Hold:0``), ``~`` cycle start, 0x18 soft reset (in motion: ``ALARM:3`` and the Alarm state;
  after a completed hold: position kept), 0x85 jog cancel.
* :meth:`GrblEmulator.trigger_alarm` sends ``ALARM:N`` at any time and stops all motion: Alarm
  state (for 1 hard limit and 2 soft limit, like GRBL, ``[MSG:Reset to continue]`` and only a
  soft reset is heard); ``error_on`` maps commands to error codes (``{"G92": 20}``: any line with a
  G92 word; ``{"$H": 9}``: lines starting with ``$H``), ``drop_replies(n)`` loses the next n
  answers (a flaky cable), ``silent=True`` never answers anything (a wrong port).

Dry run in the lab (Linux, macOS)::

    python -m tdof20.capture.hardware.grbl_emulator            # prints the port, Ctrl-C ends
    tdof20 capture ... with [turntable] backend = "grbl", port = "/dev/pts/N"
    python -m tdof20.capture.hardware.grbl --emulate --home     # the driver's smoke test on it
"""

from __future__ import annotations

import argparse
import collections
import fcntl
import math
import os
import re
import select
import struct
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Callable

BANNER = "Grbl 1.1h ['$' for help]"
UNLOCK_MSG = "[MSG:'$H'|'$X' to unlock]"
PLANNER_BLOCKS = 15
LINE_BUFFER = 80
_NUM_RE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")

_DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0, 22: 1,
    23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0, 100: 250.0, 101: 250.0, 102: 250.0,
    110: 500.0, 111: 500.0, 112: 500.0, 120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}
_INT_SETTINGS = {0, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}


@dataclass
class _Segment:
    start: list[float]
    target: list[float]
    speed: float                          # units/s along the path
    jog: bool = False
    length: float = 0.0
    done: float = 0.0

    def __post_init__(self) -> None:
        self.length = math.dist(self.start, self.target)

    def at(self) -> list[float]:
        if self.length <= 0:
            return list(self.target)
        f = min(self.done / self.length, 1.0)
        return [s + (t - s) * f for s, t in zip(self.start, self.target)]


@dataclass
class _Homing:
    start: list[float]
    until: float
    duration: float


@dataclass
class _Deferred:
    """A line whose answer waits (homing, dwell, a full planner)."""

    ready: Callable[[], bool]             # True once the line is done (may act, then answers ok)
    reply: bool = True
    extra: dict = field(default_factory=dict)


class GrblEmulator:
    """An emulated GRBL 1.1 controller on a pty; see the module docstring."""

    def __init__(self, start_alarm: int | None = None, silent: bool = False, speed_units_per_s: float = 360.0,
                 error_on: dict[str, int] | None = None, *, homing_s: float = 0.2, homing_pulloff: float = 1.0,
                 homing_enabled: bool = True, report_wpos: bool = False, steps_per_unit: float = 250.0,
                 boot_s: float = 0.05, hold_decel_s: float = 0.03):
        if not (speed_units_per_s > 0):
            raise ValueError(f"speed_units_per_s must be > 0, got {speed_units_per_s!r}")
        self.start_alarm = start_alarm
        self.silent = bool(silent)
        self.error_on = {self._clean(k): int(v) for k, v in (error_on or {}).items()}
        self.homing_s = float(homing_s)
        self.boot_s = float(boot_s)
        self.hold_decel_s = float(hold_decel_s)
        self.settings = dict(_DEFAULT_SETTINGS)
        for i in range(3):
            self.settings[100 + i] = float(steps_per_unit)
            self.settings[110 + i] = float(speed_units_per_s) * 60.0
        self.settings[10] = 0 if report_wpos else 1
        self.settings[22] = 1 if homing_enabled else 0
        self.settings[27] = float(homing_pulloff)
        self.received: list[str] = []     # every command line received (as sent, without line end)
        self._lock = threading.RLock()
        self._master: int | None = None
        self._port: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._host_open = False
        self._drop = 0
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
        """Send ``ALARM:code`` now, stop all motion and enter the Alarm state."""
        with self._lock:
            self._tick(time.monotonic())
            self._enter_alarm(int(code))

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
            self._mpos = [0.0, 0.0, 0.0]
            self._alarm = self.start_alarm is not None
        self._parser_mpos = list(self._mpos)
        self._g92 = [0.0, 0.0, 0.0]
        self._absolute = True
        self._inches = False
        self._feed: float | None = None
        self._motion_mode: int | None = 0
        self._queue: collections.deque[_Segment] = collections.deque()
        self._seg: _Segment | None = None
        self._hold: str | None = None          # None, "decel", "held"
        self._hold_until = 0.0
        self._homing: _Homing | None = None
        self._deferred: _Deferred | None = None
        self._pending: collections.deque[bytes] = collections.deque()
        self._line = bytearray()
        self._overflow = False
        self._critical = False
        self._check = False
        self._sleep = False
        self._wco_counter = 0
        self._ovr_counter = 0
        self._last_tick = time.monotonic()
        self._boot_until: float | None = None
        if alarm is not None:
            self._alarm = True

    def _wco(self) -> list[float]:
        return list(self._g92)             # G54..G59 offsets are all zero here

    def _moving(self) -> bool:
        return self._seg is not None or bool(self._queue)

    def _state_text(self) -> str:
        if self._alarm or self._critical:
            return "Alarm"
        if self._sleep:
            return "Sleep"
        if self._homing is not None:
            return "Home"
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
        """The host opened the port: an Arduino resets (DTR), boots, prints its banner."""
        self._init_machine(hard=True)
        self._boot_until = now + self.boot_s

    def _boot_output(self) -> None:
        self._out("")
        self._out(BANNER)
        if self.start_alarm is not None:
            if self.start_alarm > 0:
                self._out(f"ALARM:{self.start_alarm}")
            self._out(UNLOCK_MSG)

    def _soft_reset(self) -> None:
        alarm = None
        if self._homing is not None:
            alarm = 6
        elif self._moving() and self._hold != "held" and not self._check:
            alarm = 3
        was_alarm = self._alarm or self._critical or self._sleep
        if alarm is not None:
            self._out(f"ALARM:{alarm}")
        self._init_machine(hard=False, alarm=alarm)
        if was_alarm:
            self._alarm = True
        self._out("")
        self._out(BANNER)
        if self._alarm:
            self._out(UNLOCK_MSG)

    def _enter_alarm(self, code: int) -> None:
        self._seg = None
        self._queue.clear()
        self._parser_mpos = list(self._mpos)
        self._homing = None
        self._deferred = None
        self._pending.clear()
        self._hold = None
        self._alarm = True
        self._out(f"ALARM:{code}")
        if code in (1, 2):
            self._critical = True
            self._out("[MSG:Reset to continue]")

    def _feed_bytes(self, data: bytes) -> None:
        for b in data:
            if self._boot_until is not None:
                continue                            # the bootloader swallows what comes meanwhile
            if self.silent:
                continue
            if b == 0x18:
                self._soft_reset()
                continue
            if b == 0x3F:                           # ?
                self._report()
                continue
            if self._critical:
                continue
            if b == 0x21:                           # !
                self._feed_hold()
                continue
            if b == 0x7E:                           # ~ cycle start: resume after a completed hold
                if self._hold == "held":
                    self._hold = None
                continue
            if b >= 0x80:
                if b == 0x85 and self._moving() and (self._seg or self._queue[0]).jog:
                    self._feed_hold()
                continue
            if b in (0x0A, 0x0D):
                self._pending.append(b"\xff" if self._overflow else bytes(self._line))
                self._line.clear()
                self._overflow = False
                continue
            if len(self._line) >= LINE_BUFFER:
                self._overflow = True
            else:
                self._line.append(b)
        self._process_pending()

    def _feed_hold(self) -> None:
        if self._moving() and self._hold is None and self._homing is None and not self._check:
            self._hold = "decel"
            self._hold_until = time.monotonic() + self.hold_decel_s

    def _process_pending(self) -> None:
        while self._pending and self._deferred is None:
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
        if self._homing is not None:
            h = self._homing
            home = [-self.settings.get(27, 1.0)] * 3
            if now >= h.until:
                self._mpos = home
                self._parser_mpos = list(home)
                self._homing = None
                self._alarm = False
            else:
                f = 1.0 - (h.until - now) / h.duration if h.duration > 0 else 1.0
                self._mpos = [s + (t - s) * f for s, t in zip(h.start, home)]
        if self._hold == "decel" and now >= self._hold_until:
            move_dt = max(dt - (now - self._hold_until), 0.0)
            self._advance(move_dt)
            dt = 0.0
            self._hold = "held"
            seg = self._seg or (self._queue[0] if self._queue else None)
            if seg is not None and seg.jog:          # a held jog is cancelled
                self._seg = None
                self._queue.clear()
                self._parser_mpos = list(self._mpos)
                self._hold = None
        if self._hold != "held" and self._homing is None:
            self._advance(dt)
        if self._deferred is not None and self._deferred.ready():
            d, self._deferred = self._deferred, None
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
            left = seg.length - seg.done
            need = left / seg.speed if seg.speed > 0 else 0.0
            if need <= dt:
                dt -= need
                seg.done = seg.length
                self._mpos = list(seg.target)
                self._seg = None
            else:
                seg.done += seg.speed * dt
                self._mpos = seg.at()
                dt = 0.0

    def _report(self) -> None:
        self._tick(time.monotonic())
        wco = self._wco()
        pos = [round(p * self._steps(i)) / self._steps(i) if self._steps(i) > 0 else p
               for i, p in enumerate(self._mpos)]
        wpos_mode = int(self.settings.get(10, 1)) & 1 == 0
        if wpos_mode:
            pos = [p - w for p, w in zip(pos, wco)]
        feed = (self._seg.speed * 60.0 if self._seg is not None and self._hold is None else 0.0)
        fields = [self._state_text(), ("WPos:" if wpos_mode else "MPos:") + ",".join(f"{p:.3f}" for p in pos),
                  f"FS:{feed:.0f},0"]
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

    # ------------------------------------------------------------------ commands

    @staticmethod
    def _clean(text: str) -> str:
        """Upper case, no spaces, no comments: what GRBL's parser sees."""
        text = re.sub(r"\([^)]*\)", "", text)
        text = text.split(";", 1)[0]
        return "".join(text.split()).upper()

    @staticmethod
    def _words(line: str) -> list[tuple[str, float]] | int:
        words: list[tuple[str, float]] = []
        pos = 0
        while pos < len(line):
            letter = line[pos]
            if not ("A" <= letter <= "Z"):
                return 1                               # expected command letter
            m = _NUM_RE.match(line, pos + 1)
            if not m:
                return 2                               # bad number format
            words.append((letter, float(m.group(0))))
            pos = m.end()
        return words

    def _error_for(self, line: str) -> int | None:
        for key, code in self.error_on.items():
            if key.startswith("$") or not key[:1].isalpha():
                if line.startswith(key):
                    return code
                continue
            kw = self._words(key)
            lw = self._words(line)
            if isinstance(kw, int) or isinstance(lw, int):
                if line.startswith(key):
                    return code
                continue
            if all(w in lw for w in kw):
                return code
        return None

    def _execute(self, text: str) -> int | None:
        """Run one line: an error code (0 = ok), or None when the answer is deferred."""
        line = self._clean(text)
        if not line:
            return 0
        forced = self._error_for(line)
        if forced is not None:
            return forced
        if self._sleep:
            return 9 if not line.startswith("$") else 8
        if line.startswith("$"):
            return self._system(line)
        if self._alarm:
            return 9
        if self._homing is not None:
            return 9
        return self._gcode(line)

    def _idle_or_alarm(self) -> bool:
        return not self._moving() and self._homing is None and self._hold is None

    def _system(self, line: str) -> int | None:
        if line == "$":
            self._out("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]")
            return 0
        if line == "$$":
            if self._moving():
                return 8
            for k in sorted(self.settings):
                v = self.settings[k]
                self._out(f"${k}={int(v)}" if k in _INT_SETTINGS else f"${k}={v:.3f}")
            return 0
        if line == "$G":
            mode = {0: "G0", 1: "G1", None: "G80"}[self._motion_mode]
            self._out(f"[GC:{mode} G54 G17 {'G20' if self._inches else 'G21'} {'G90' if self._absolute else 'G91'} "
                      f"G94 M5 M9 T0 F{(self._feed or 0):g} S0]")
            return 0
        if line == "$X":
            if self._alarm:
                self._alarm = False
                self._out("[MSG:Caution: Unlocked]")
            return 0
        if line == "$C":
            if self._check:
                self._out("[MSG:Disabled]")
                self._reply(0)
                self._soft_reset()
                return None
            if not self._idle_or_alarm() or self._alarm:
                return 8
            self._check = True
            self._out("[MSG:Enabled]")
            return 0
        if line.startswith("$J="):
            return self._jog(line[3:])
        if not self._idle_or_alarm():
            return 8
        if line == "$#":
            wco = self._g92
            zero = "0.000,0.000,0.000"
            for g in ("G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30"):
                self._out(f"[{g}:{zero}]")
            self._out("[G92:" + ",".join(f"{v:.3f}" for v in wco) + "]")
            self._out("[TLO:0.000]")
            self._out(f"[PRB:{zero}:0]")
            return 0
        if line == "$I":
            self._out("[VER:1.1h.20190825:]")
            self._out("[OPT:V,15,128]")
            return 0
        if line == "$N":
            self._out("$N0=")
            self._out("$N1=")
            return 0
        if line == "$SLP":
            self._sleep = True
            self._out("[MSG:Sleeping]")
            return 0
        if line == "$H":
            if not int(self.settings.get(22, 0)):
                return 5
            start = list(self._mpos)
            now = time.monotonic()
            self._homing = _Homing(start, now + self.homing_s, self.homing_s)
            self._deferred = _Deferred(lambda: self._homing is None and not self._alarm)
            return None
        m = re.fullmatch(r"\$(\d+)=([-+]?(?:\d+\.?\d*|\.\d+))", line)
        if m:
            key, val = int(m.group(1)), float(m.group(2))
            if key not in self.settings:
                return 3
            if val < 0:
                return 4
            self.settings[key] = float(int(val)) if key in _INT_SETTINGS else val
            return 0
        return 3

    def _jog(self, body: str) -> int | None:
        words = self._words(body)
        if isinstance(words, int):
            return words
        absolute, inches, g53, axes, feed = self._absolute, self._inches, False, {}, None
        for letter, v in words:
            if letter == "G":
                if v in (90, 91):
                    absolute = v == 90
                elif v in (20, 21):
                    inches = v == 20
                elif v == 53:
                    g53 = True
                else:
                    return 16
            elif letter in "XYZ":
                axes["XYZ".index(letter)] = v
            elif letter == "F":
                feed = v
            elif letter != "N":
                return 16
        if feed is None or not axes:
            return 16
        if self._alarm:
            return 9
        if self._moving() and not (self._seg or self._queue[0]).jog:
            return 8
        scale = 25.4 if inches else 1.0
        return self._enqueue(axes, scale, absolute, g53, min(feed * scale / 60.0, math.inf), jog=True)

    def _gcode(self, line: str) -> int | None:
        words = self._words(line)
        if isinstance(words, int):
            return words
        gs: list[float] = []
        ms: list[float] = []
        axes: dict[int, float] = {}
        feed = dwell = None
        for letter, v in words:
            if letter == "G":
                gs.append(v)
            elif letter == "M":
                ms.append(v)
            elif letter in "XYZ":
                i = "XYZ".index(letter)
                if i in axes:
                    return 25
                axes[i] = v
            elif letter == "F":
                if feed is not None:
                    return 25
                feed = v
            elif letter == "P":
                dwell = v
            elif letter in "NST":
                pass
            else:
                return 20
        motion = nonmodal = None
        g53 = False
        absolute, inches = self._absolute, self._inches
        for g in gs:
            if g in (0, 1):
                if motion is not None:
                    return 21
                motion = int(g)
            elif g == 80:
                if motion is not None:
                    return 21
                motion = -1
            elif g in (4, 92):
                if nonmodal is not None:
                    return 21
                nonmodal = int(g)
            elif g == 53:
                g53 = True
            elif g in (90, 91):
                absolute = g == 90
            elif g in (20, 21):
                inches = g == 20
            elif g in (17, 18, 19, 94, 40, 49, 61) or g in (54, 55, 56, 57, 58, 59):
                pass
            else:
                return 20
        for m in ms:
            if m not in (0, 1, 2, 30, 3, 4, 5, 7, 8, 9):
                return 20
        if feed is not None:
            if feed < 0:
                return 4
            self._feed = feed * (25.4 if inches else 1.0)
        self._absolute, self._inches = absolute, inches
        scale = 25.4 if inches else 1.0
        if motion is not None:
            self._motion_mode = None if motion == -1 else motion
        if nonmodal == 4:
            if dwell is None:
                return 28
            if dwell < 0:
                return 4
            box: dict = {}

            def dwell_done() -> bool:
                if self._moving():
                    return False
                box.setdefault("until", time.monotonic() + dwell)
                return time.monotonic() >= box["until"]
            self._deferred = _Deferred(dwell_done)
            return None
        if nonmodal == 92:
            if not axes:
                return 26
            for i, v in axes.items():
                self._g92[i] = self._parser_mpos[i] - v * scale
            self._wco_counter = 0
            return 0
        if axes:
            mode = self._motion_mode
            if mode is None:
                return 31
            if g53 and mode not in (0, 1):
                return 30
            if mode == 1 and not self._feed:
                return 22
            speed = math.inf if mode == 0 else self._feed / 60.0
            return self._enqueue(axes, scale, absolute, g53, speed)
        return 0

    def _enqueue(self, axes: dict[int, float], scale: float, absolute: bool, g53: bool, speed: float,
                 jog: bool = False) -> int | None:
        target = list(self._parser_mpos)
        wco = self._wco()
        for i, v in axes.items():
            v *= scale
            if g53:
                target[i] = v
            elif absolute:
                target[i] = v + wco[i]
            else:
                target[i] += v
        start = list(self._parser_mpos)
        delta = [abs(t - s) for s, t in zip(start, target)]
        length = math.sqrt(sum(d * d for d in delta))
        if length <= 0:
            return 0
        for i, d in enumerate(delta):                # no axis faster than its max rate
            if d > 0:
                speed = min(speed, self._max_rate(i) * length / d)
        self._parser_mpos = target
        if self._check:
            return 0
        seg = _Segment(start, target, speed, jog)
        if len(self._queue) < PLANNER_BLOCKS:
            self._queue.append(seg)
            return 0

        def room() -> bool:
            if len(self._queue) >= PLANNER_BLOCKS:
                return False
            self._queue.append(seg)
            return True
        self._deferred = _Deferred(room)
        return None


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Run an emulated GRBL 1.1 controller on a pseudo-terminal.")
    p.add_argument("--speed", type=float, default=360.0, help="max rate, units per second")
    p.add_argument("--start-alarm", type=int, default=None,
                   help="start in alarm: 0 = homing lock, 1..9 = ALARM:N pending")
    p.add_argument("--no-homing", action="store_true", help="homing disabled ($22=0)")
    p.add_argument("--homing-s", type=float, default=2.0)
    a = p.parse_args(argv)
    emu = GrblEmulator(a.start_alarm, speed_units_per_s=a.speed, homing_enabled=not a.no_homing,
                       homing_s=a.homing_s).start()
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
