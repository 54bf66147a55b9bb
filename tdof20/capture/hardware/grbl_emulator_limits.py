"""Limit switches and the homing cycle of the GRBL 1.1 emulator
(:mod:`tdof20.capture.hardware.grbl_emulator`), after GRBL 1.1h's ``limits.c``, ``motion_control.c``
and ``protocol.c``:

* A switch is an input: pressed while its axis stands in the switch's window (from its trigger point
  ``at`` over ``width`` units in the homing direction, positive as with ``$23=0``; every ``period``
  units on a rotary axis), or held / broken by hand (:meth:`GrblLimits.set_switch`). The status
  report's ``Pn:`` field lists the pressed ones (``Pn:XZ``), with or without hard limits.
* Hard limits (``$21=1``): GRBL's pin-change interrupt fires on *any* change of a limit pin (the
  default build has no ``HARD_LIMIT_FORCE_STATE_CHECK``), outside the alarm state: a switch that
  triggers *or releases* (moving off it) stops everything at once and raises ``ALARM:1``. At a reset
  (``CHECK_LIMITS_AT_INIT``) a pressed switch prints ``[MSG:Check Limits]`` and starts GRBL locked;
  ``$X`` unlocks it silently, and the first step off the switch trips ``ALARM:1`` again.
* ``$H`` runs the build's cycles in order (default ``("Z", "XY")``, GRBL's ``HOMING_CYCLE_0/1``; a
  turntable firmware built for X only: ``("X",)``) with hard limits disabled meanwhile. Per cycle:
  search at ``$25`` over 1.5 × the largest ``$130``-``$132`` of its axes (each axis stops dead at its
  switch; one not found: ``ALARM:9``), pull-off ``$27`` at ``$25`` (still pressed: ``ALARM:8``), locate at
  ``$24`` over 5 × ``$27`` (``ALARM:9``), pull-off; ``$26`` ms of debounce after each phase; then the
  cycle's axes stand at ``-$27``. A reset during the cycle: ``ALARM:6``; the safety-door byte (0x84):
  ``ALARM:7``. Rates are clamped to ``$110``-``$112``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from tdof20.capture.hardware.grbl_emulator_commands import _Deferred
from tdof20.capture.hardware.grbl_timing import HOMING_LOCATE_SCALAR, HOMING_SEARCH_SCALAR, contact_time, move_time

AXIS_LETTERS = "XYZ"


@dataclass(frozen=True)
class LimitSwitch:
    """A limit (or home) switch on one axis. ``at``: its trigger point, units ahead (in the homing
    direction, +) of where the axis stood at ``start()``; ``width``: how far beyond it the switch stays
    pressed (``inf``: to the end of travel, a limit switch); ``period``: a rotary axis whose home flag
    passes the sensor every ``period`` units (a turntable at 1 unit/degree: 360)."""

    at: float
    width: float = math.inf
    period: float | None = None

    def __post_init__(self) -> None:
        if not (self.width > 0):
            raise ValueError(f"LimitSwitch width must be > 0, got {self.width!r}")
        if self.period is not None and not (self.period > 0 and math.isfinite(self.width) and self.width < self.period):
            raise ValueError(f"LimitSwitch period must be > 0 and longer than its width, got {self.period!r}")

    def pressed(self, p: float) -> bool:
        q = p - self.at
        if self.period is not None:
            q = math.fmod(q, self.period)
            q = q + self.period if q < 0 else q
        return 0.0 <= q < self.width - 1e-9

    def ahead(self, p: float) -> float | None:
        """Distance in the homing direction to the point where the switch triggers (0 if pressed);
        ``None``: it never does (behind a linear axis's switch)."""
        if self.pressed(p):
            return 0.0
        if self.period is not None:
            q = math.fmod(self.at - p, self.period)
            return q + self.period if q < 0 else q
        return self.at - p if p < self.at else None


#: The emulator's switches unless told otherwise: the turntable's home flag on X (2 units wide,
#: once per 360 units), limit switches at the ends of Y and Z; each 2 units ahead of the start.
DEFAULT_SWITCHES: dict[str, LimitSwitch] = {"X": LimitSwitch(2.0, 2.0, 360.0), "Y": LimitSwitch(2.0),
                                            "Z": LimitSwitch(2.0)}
DEFAULT_HOMING_CYCLES = ("Z", "XY")


@dataclass
class HomingPhase:
    """One phase of a homing cycle: from ``start`` (machine position, with ``phys0`` the physical
    position of machine zero) the axes in ``moves`` cover (signed distance, seconds); the phase lasts
    ``seconds``."""

    phys0: list[float]
    start: list[float]
    moves: dict[int, tuple[float, float]]
    seconds: float

    def at(self, t: float) -> list[float]:
        pos = list(self.start)
        for i, (d, s) in self.moves.items():
            pos[i] += d * (min(max(t / s, 0.0), 1.0) if s > 0 else 1.0)
        return pos

    def end(self) -> list[float]:
        return self.at(math.inf)


@dataclass
class Homing:
    """A running ``$H``: its phases from ``began``; then ``alarm`` (``None``: homed, the machine position
    ``final`` with ``final_phys0``)."""

    began: float
    phases: list[HomingPhase]
    alarm: int | None
    final: list[float]
    final_phys0: list[float]

    @property
    def until(self) -> float:
        return self.began + sum(p.seconds for p in self.phases)

    def state_at(self, now: float) -> tuple[list[float], list[float]]:
        """(machine position, physical zero) at ``now``."""
        t = now - self.began
        for p in self.phases:
            if t < p.seconds:
                return p.at(t), list(p.phys0)
            t -= p.seconds
        if self.phases:
            return self.phases[-1].end(), list(self.phases[-1].phys0)
        return list(self.final), list(self.final_phys0)


class GrblLimits:
    """Switch inputs, hard limits and the homing cycle (a mixin of the emulator, which holds the
    machine state: ``_mpos``, ``_phys0``, ``settings``, ``switches``, ``homing_cycles``)."""

    # ------------------------------------------------------------------ the inputs

    def set_switch(self, axis: str, state: bool | None) -> None:
        """Hold a switch pressed (``True``: a hand on it, a stuck or shorted switch), keep it released
        (``False``: broken, unplugged) or let it follow the axis (``None``). A change of the pin with
        hard limits on is a hard limit alarm, as on the firmware."""
        i = AXIS_LETTERS.index(axis.upper())
        with self._lock:
            self._tick(self._now())
            if state is None:
                self._forced.pop(i, None)
            else:
                self._forced[i] = bool(state)
            self._check_pins()

    def _pressed(self, i: int, mpos: list[float] | None = None, phys0: list[float] | None = None) -> bool:
        if i in self._forced:
            return self._forced[i]
        sw = self.switches.get(AXIS_LETTERS[i])
        if sw is None:
            return False
        pos = self._mpos if mpos is None else mpos
        zero = self._phys0 if phys0 is None else phys0
        return sw.pressed(zero[i] + pos[i])

    def _pins(self, mpos: list[float] | None = None) -> str:
        """The pressed limit pins, as ``Pn:`` lists them (``"XZ"``)."""
        return "".join(a for i, a in enumerate(AXIS_LETTERS) if self._pressed(i, mpos))

    def _hard_limits(self) -> bool:
        return bool(int(self.settings.get(21, 0)))

    def _check_pins(self) -> None:
        """A pin that changed since the last look: ``ALARM:1`` with hard limits on, outside the alarm
        state and homing (the interrupt is off then)."""
        pins = self._pins()
        changed = pins != self._pins_seen
        self._pins_seen = pins
        if changed and self._hard_limits() and not self._alarm and not self._critical \
                and self._homing is None and self._pause_until is None and self._boot_until is None:
            self._enter_alarm(1)

    def _limits_at_init(self) -> bool:
        """GRBL's ``CHECK_LIMITS_AT_INIT``: with hard limits on, a pressed switch at a reset locks it."""
        self._pins_seen = self._pins()
        return self._hard_limits() and bool(self._pins_seen)

    def _first_pin_change(self, start: list[float], end: list[float]) -> float | None:
        """The fraction of the straight move ``start`` -> ``end`` at which a limit pin first changes
        (``None``: none does)."""
        if not self._hard_limits() or not self.switches:
            return None
        before = self._pins(start)
        length = math.dist(start, end)
        if length <= 0:
            return None
        widths = [s.width for s in self.switches.values()] + \
                 [s.period - s.width for s in self.switches.values() if s.period is not None]
        step = max(min(min(widths) / 4.0, 0.25), 1e-3)
        n = max(int(math.ceil(length / step)), 1)

        def at(f: float) -> list[float]:
            return [a + (b - a) * f for a, b in zip(start, end)]
        lo = 0.0
        for k in range(1, n + 1):
            hi = k / n
            if self._pins(at(hi)) != before:
                for _ in range(30):
                    mid = 0.5 * (lo + hi)
                    if self._pins(at(mid)) != before:
                        hi = mid
                    else:
                        lo = mid
                return hi
            lo = hi
        return None

    # ------------------------------------------------------------------ homing

    def _plan_homing(self, now: float) -> Homing:
        """GRBL's ``mc_homing_cycle``: each cycle of the build in order, from the switches' geometry."""
        s = self.settings
        mpos, phys0 = list(self._mpos), list(self._phys0)
        pulloff = s.get(27, 1.0)
        debounce = s.get(26, 250.0) / 1000.0
        phases: list[HomingPhase] = []
        for cycle in self.homing_cycles:
            axes = [AXIS_LETTERS.index(a) for a in cycle]
            search = HOMING_SEARCH_SCALAR * max(s.get(130 + i, 200.0) for i in axes)
            for approach, travel, rate_key in ((True, search, 25), (False, pulloff, 25),
                                               (True, HOMING_LOCATE_SCALAR * pulloff, 24), (False, pulloff, 25)):
                for i in axes:                 # GRBL zeroes the cycle's axes before each phase
                    phys0[i] += mpos[i]
                    mpos[i] = 0.0
                moves: dict[int, tuple[float, float]] = {}
                missing = False
                for i in axes:
                    rate = min(max(s.get(rate_key, 500.0), 1e-6), s.get(110 + i, 500.0)) / 60.0
                    accel = max(s.get(120 + i, 10.0), 1e-6)
                    if approach:
                        d = self._switch_ahead(i, mpos, phys0)
                        if d is None or d > travel:
                            missing = True
                            moves[i] = (travel, move_time(travel, rate, accel))   # the whole block
                        else:
                            moves[i] = (d, contact_time(d, rate, accel))
                    else:
                        moves[i] = (-travel, move_time(travel, rate, accel))
                phase = HomingPhase(list(phys0), list(mpos), moves, max(t for _, t in moves.values()))
                mpos = phase.end()
                alarm = None
                if missing:
                    alarm = 9
                elif not approach and any(self._pressed(i, mpos, phys0) for i in axes):
                    alarm = 8
                if alarm is not None:          # no debounce: GRBL resets at once
                    phases.append(phase)
                    return Homing(now, phases, alarm, mpos, phys0)
                phase.seconds += debounce
                phases.append(phase)
            for i in axes:                     # the homed axes stand at -$27 ($23=0, no force-origin)
                phys0[i] += mpos[i] + pulloff
                mpos[i] = -pulloff
        return Homing(now, phases, None, mpos, phys0)

    def _switch_ahead(self, i: int, mpos: list[float], phys0: list[float]) -> float | None:
        if i in self._forced:
            return 0.0 if self._forced[i] else None
        sw = self.switches.get(AXIS_LETTERS[i])
        return None if sw is None else sw.ahead(phys0[i] + mpos[i])

    def _start_homing(self) -> None:
        """``$H``: the cycle runs in the I/O thread's ticks; its ``ok`` when it ends."""
        self._homing = self._plan_homing(self._now())
        self._deferred = _Deferred(lambda: self._homing is None and not self._alarm)

    def _homing_tick(self, now: float) -> None:
        h = self._homing
        if now < h.until:
            self._mpos, self._phys0 = h.state_at(now)
            return
        self._homing = None
        if h.alarm is not None:
            self._mpos, self._phys0 = h.state_at(now)
            self._pins_seen = self._pins()
            self._enter_alarm(h.alarm)
            return
        self._mpos, self._phys0 = list(h.final), list(h.final_phys0)
        self._parser_mpos = list(self._mpos)
        self._pins_seen = self._pins()     # limits_init() again: the pull-off left the switches
        self._alarm = False
        if self._report_asked:                 # the one report GRBL owes, sent as the cycle ends
            self._report_asked = False
            self._report(tick=False, state="Home")
