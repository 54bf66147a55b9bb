"""What the GRBL tests share: emulators on real pseudo-terminals (stopped after each test) and a
driver connected to one, with the tests' speeds (faster than a real table's, same ratios)."""

from __future__ import annotations

import pytest

from tdof20.capture.hardware.grbl import GrblTurntable
from tdof20.capture.hardware.grbl_emulator import GrblEmulator

SPEED = 360.0          # emulator max rate, units/s
ACCEL = 3600.0         # emulator acceleration, units/s² (GRBL's own default ratio would be 432)


@pytest.fixture
def emu_factory():
    made: list[GrblEmulator] = []

    def make(**kw) -> GrblEmulator:
        kw.setdefault("speed_units_per_s", SPEED)
        kw.setdefault("accel_units_per_s2", ACCEL)
        kw.setdefault("homing_s", 0.1)
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
