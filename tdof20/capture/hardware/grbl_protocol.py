"""GRBL's side of the conversation, in words: alarm and error codes, status reports, the errors
the turntable driver (:mod:`tdof20.capture.hardware.grbl`) raises.

GRBL 1.1 status reports read ``<Idle|MPos:12.000,0.000,0.000|FS:0,0>`` (``WPos`` instead of ``MPos``
when ``$10=0``; ``WCO`` from time to time). GRBL 0.9 and older, still on many boards, send
``<Idle,MPos:12.000,0.000,0.000,WPos:12.000,0.000,0.000>`` and answer errors in words: they are
parsed (``GrblStatus.legacy``) only so that the driver can name the version and refuse it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from tdof20.capture.hardware.interfaces import HardwareError

#: GRBL 1.1 alarm codes (``ALARM:N``), in words. 10+ are grblHAL's extensions.
ALARM_CODES: dict[int, str] = {
    1: "hard limit: a limit switch was triggered; the position is likely lost",
    2: "soft limit: the motion target exceeds the machine travel ($130-$132); the position is kept",
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

#: ALARM:1 and ALARM:2 lock GRBL 1.1 until a soft reset: it ignores "?" and $X meanwhile.
LOCKING_ALARMS = (1, 2)

_BANNER_RE = re.compile(r"^Grbl(HAL)?\s+(\S+)\s+\[", re.I)


def describe_alarm(code: int | None) -> str:
    """``ALARM:N`` in words (``None``: the code-less power-up lock)."""
    if code is None:
        return HOMING_REQUIRED
    return ALARM_CODES.get(code, f"unknown alarm {code} (see the controller's documentation)")


def describe_error(code: int) -> str:
    """``error:N`` in words; unknown codes keep their number."""
    return ERROR_CODES.get(code, f"unknown error {code} (see the controller's documentation)")


def banner_version(line: str) -> str | None:
    """The version in GRBL's welcome line (``Grbl 1.1h ['$' for help]`` -> ``1.1h``); ``None`` if the
    line is not a banner."""
    m = _BANNER_RE.match(line.strip())
    return m.group(2) if m else None


class GrblError(HardwareError):
    """GRBL rejected a command with ``error:N`` (``code``). Not retryable: the same line fails again."""

    def __init__(self, device: str, command: str, code: int):
        self.code = code
        self.command = command
        super().__init__(device, f"GRBL rejected {command!r}: error:{code} ({describe_error(code)})",
                         retryable=False)


class GrblAlarm(HardwareError):
    """GRBL is in an alarm (``code`` None: the power-up homing lock). A person must act.

    ``locked``: GRBL is locked until a soft reset (``ALARM:1``/``2``), so the message says to reset
    it rather than to unlock it. ``what``: replaces the description of a code-less alarm; ``todo``:
    what to do, where the usual advice would mislead."""

    def __init__(self, device: str, code: int | None, context: str = "", *, locked: bool = False,
                 what: str | None = None, todo: str | None = None):
        self.code = code
        self.locked = locked
        if code is not None:
            head = f"ALARM:{code} ({describe_alarm(code)})"
        else:
            head = f"ALARM ({what or describe_alarm(None)})"
        if todo is not None:
            pass
        elif locked:
            todo = ("GRBL is locked until it is reset and ignores '?' and $X: clear the cause, then reset and "
                    "home the table (home() and [turntable] home = true do both; by hand: ctrl-x, then $H)")
        else:
            todo = ("clear the cause, then home the table ($H, or home() / [turntable] home = true) "
                    "or unlock it with $X after checking it turns freely")
        super().__init__(device, f"{head}; " + (f"{context}; " if context else "") + todo, retryable=False)


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
    legacy: bool = False                         # GRBL 0.9's comma format
    pins: str = ""                               # Pn: the active input pins (X, Y, Z limits; P, D, H, R, S)

    def limit_pins(self) -> str:
        """The pressed limit switches among the pins (``"X"``, ``"XZ"``, ``""``)."""
        return "".join(c for c in self.pins if c in "XYZABC")


def parse_status(line: str) -> GrblStatus | None:
    """Parse ``<Idle|MPos:12.000,0.000,0.000|FS:0,0>`` (or GRBL 0.9's ``<Idle,MPos:…,WPos:…>``, with
    ``legacy`` set); ``None`` if the line is not a report."""
    line = line.strip()
    if not (line.startswith("<") and line.endswith(">")) or len(line) < 3:
        return None
    body = line[1:-1]
    legacy = "|" not in body and "," in body.split(":", 1)[0]
    if legacy:                                   # <Idle,MPos:1,2,3,WPos:1,2,3,Buf:0>
        fields: list[str] = []
        for tok in body.split(","):
            if ":" in tok or not fields:
                fields.append(tok)
            else:
                fields[-1] += "," + tok
    else:
        fields = body.split("|")
    state, _, sub = fields[0].partition(":")
    if not state or not state.isalpha():
        return None
    try:
        substate = int(sub) if sub else None
    except ValueError:
        substate = None
    values: dict = {}
    pins = ""
    for f in fields[1:]:
        key, _, val = f.partition(":")
        if key == "Pn":
            pins = val
            continue
        if key in ("MPos", "WPos", "WCO", "FS", "F"):
            try:
                values[key] = tuple(float(v) for v in val.split(","))
            except ValueError:
                return None
    feed = values.get("FS", values.get("F", (None,)))[0]
    return GrblStatus(state, substate, values.get("MPos"), values.get("WPos"), values.get("WCO"), feed, line,
                      legacy, pins)
