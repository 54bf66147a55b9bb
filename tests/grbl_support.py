"""What the GRBL tests share: emulators on real pseudo-terminals (stopped after each test) and a
driver connected to one, with the tests' speeds (faster than a real table's, same ratios).

The emulator's defaults are the firmware's (no reset when the port opens, the homing lock at
power-up with ``$22=1``, Z-then-XY homing at GRBL's own rates: 5-11 s); the fixture only makes the
homing cycle fast (``FAST_HOMING``: seek and locate at 100 and 50 units/s, 10 ms of debounce, about
0.35 s for both cycles) and starts the controller unlocked (``start_alarm=None``, as after a ``$X``
or a homing before the test) unless a test asks for the power-up lock."""

from __future__ import annotations

import time

import pytest
import serial

from tdof20.capture.hardware.grbl import GrblTurntable
from tdof20.capture.hardware.grbl_emulator import GrblEmulator

SPEED = 360.0          # emulator max rate, units/s
ACCEL = 3600.0         # emulator acceleration, units/s² (GRBL's own default ratio would be 432)
FAST_HOMING = {24: 3000.0, 25: 6000.0, 26: 10}     # $24 locate, $25 seek (units/min), $26 debounce (ms)
SLOW_HOMING = {24: 60.0, 25: 600.0, 26: 10}        # locate at 1 unit/s: about 1.4 s per cycle, 2.9 s for both


@pytest.fixture
def emu_factory():
    made: list[GrblEmulator] = []

    def make(**kw) -> GrblEmulator:
        kw.setdefault("speed_units_per_s", SPEED)
        kw.setdefault("accel_units_per_s2", ACCEL)
        kw.setdefault("start_alarm", None)
        kw["settings"] = {**FAST_HOMING, **kw.get("settings", {})}
        emu = GrblEmulator(**kw).start()
        made.append(emu)
        return emu

    yield make
    for emu in made:
        emu.stop()


def table_for(emu: GrblEmulator, timeout_s: float = 1.0, **kw) -> GrblTurntable:
    """A driver on ``emu``'s port (feed 360 °/s, status polled every 20 ms)."""
    kw.setdefault("feed_deg_per_s", 360.0)
    kw.setdefault("poll_s", 0.02)
    return GrblTurntable(emu.port, timeout_s=timeout_s, **kw)


class Link:
    """A raw serial conversation with the emulator, with the arrival time of every line."""

    def __init__(self, port: str):
        self.ser = serial.Serial(port, 115200, timeout=0.02)
        self.buf = bytearray()

    def lines(self, seconds: float, until=None) -> list[tuple[float, str]]:
        got, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            self.buf.extend(self.ser.read(256))
            while b"\n" in self.buf:
                line, _, rest = bytes(self.buf).partition(b"\n")
                self.buf[:] = rest
                if line.strip():
                    got.append((time.monotonic(), line.strip().decode()))
                    if until is not None and until(got[-1][1]):
                        return got
        return got

    def send(self, data: bytes) -> None:
        self.ser.write(data)

    def ask(self, line: str) -> list[str]:
        self.send(line.encode() + b"\n")
        return [s for _, s in self.lines(1.0, lambda s: s == "ok" or s.startswith("error:"))]

    def close(self) -> None:
        self.ser.close()
