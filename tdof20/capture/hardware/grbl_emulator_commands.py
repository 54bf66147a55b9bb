"""The line interpreter of the GRBL 1.1 emulator (:mod:`tdof20.capture.hardware.grbl_emulator`):
what each command line does and how it is answered.

G-code: ``G0``/``G1`` with X/Y/Z and F (``error:22`` without a feed), ``G4 P``, ``G20``/``G21``,
``G90``/``G91``, ``G92``, ``G53``, ``G54``-``G59``, ``G17``-``G19``, ``G94``, ``M0``-``M9``/``M30``
(no-ops); other G-codes give ``error:20``; G-code during an alarm ``error:9``. System commands:
``$``, ``$$``, ``$#``, ``$G``, ``$I``, ``$N``, ``$H`` (homing), ``$X`` (unlock), ``$C`` (check mode),
``$SLP``, ``$J=`` (jog), ``$N=value`` (``$10`` switches MPos/WPos reports, ``$20`` soft limits,
``$22`` homing, ``$24``-``$27`` the homing cycle, ``$100``-``$102`` steps/unit, which quantise
reported positions, ``$110``-``$112`` max rates, units/min, ``$120``-``$122`` accelerations,
units/s², ``$130``-``$132`` max travel).
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field
from typing import Callable

from tdof20.capture.hardware.grbl_timing import Segment

PLANNER_BLOCKS = 15
_NUM_RE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")

#: GRBL 1.1h's default settings (``$$``) as the emulator starts with them.
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0, 22: 1,
    23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0, 100: 250.0, 101: 250.0, 102: 250.0,
    110: 500.0, 111: 500.0, 112: 500.0, 120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}
_INT_SETTINGS = {0, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}


@dataclass
class _Deferred:
    """A line whose answer waits (homing, dwell, a full planner)."""

    ready: Callable[[], bool]             # True once the line is done (may act, then answers ok)
    reply: bool = True
    extra: dict = field(default_factory=dict)


class GrblCommands:
    """The command lines of :class:`~tdof20.capture.hardware.grbl_emulator.GrblEmulator` (a mixin:
    the machine state, ``_out``/``_reply`` and the motion live there)."""

    LINE_BUFFER = 80

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
            self._start_homing()
            return None
        m = re.fullmatch(r"\$(\d+)=([-+]?(?:\d+\.?\d*|\.\d+))", line)
        if m:
            key, val = int(m.group(1)), float(m.group(2))
            if key not in self.settings:
                return 3
            if val < 0:
                return 4
            if key == 20 and val and not int(self.settings.get(22, 0)):
                return 10                              # soft limits need homing
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
        if self._soft_limit_hit(target):
            if jog:
                return 15                              # travel exceeded: the jog is ignored
            self._parser_mpos = target
            self._soft_limit_alarm()
            return None                                # its "ok" comes after the reset
        self._parser_mpos = target
        if self._check:
            return 0
        accel = math.inf
        for i, d in enumerate(delta):                # nor accelerating faster than it can
            if d > 0:
                accel = min(accel, self._max_accel(i) * length / d)
        seg = Segment(start, target, speed, accel, jog)
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

