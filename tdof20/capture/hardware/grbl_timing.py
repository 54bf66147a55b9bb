"""How long GRBL 1.1 takes to move and to home, from its settings: shared by the turntable driver
(its homing wait) and the emulator (its motion).

GRBL plans every block with a trapezoidal speed profile: it accelerates at the axis's ``$120``-
``$122`` (units/s²) up to the feed (clamped to ``$110``-``$112``, units/min), cruises, and
decelerates to stop at the end of the block (the driver sends one move at a time and waits for it,
so there is no junction blending). A feed hold decelerates at the same rate.

A homing cycle (``$H``, GRBL 1.1h's ``limits_go_home``) per group of axes: a search towards the
switches at the seek rate ``$25`` over at most 1.5 × the max travel ``$130``-``$132`` (an axis stops
dead when its switch triggers; no switch by then: ``ALARM:9``), a pull-off of ``$27`` at the seek rate
(the switch still pressed after it: ``ALARM:8``), a slow locate at the feed rate ``$24`` over at most
5 × ``$27``, and a last pull-off; each phase ends with the debounce delay ``$26`` (ms). The default
build homes Z first, then X and Y together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: GRBL's homing constants (config.h): search over 1.5 × max travel, locate over 5 × pull-off.
HOMING_SEARCH_SCALAR = 1.5
HOMING_LOCATE_SCALAR = 5.0

# GRBL 1.1's defaults for settings that a controller did not report
_DEFAULTS = {24: 25.0, 25: 500.0, 26: 250.0, 27: 1.0, 120: 10.0, 121: 10.0, 122: 10.0,
             130: 200.0, 131: 200.0, 132: 200.0}


def move_time(distance: float, rate: float, accel: float) -> float:
    """Seconds for a block of ``distance`` units from rest to rest at up to ``rate`` units/s with
    ``accel`` units/s² (a trapezoid, or a triangle when the block is too short to reach the rate)."""
    distance = abs(float(distance))
    if distance <= 0:
        return 0.0
    if not (accel > 0 and math.isfinite(accel)):
        return distance / rate
    ramp = rate * rate / accel                    # accelerating plus decelerating distance
    if distance <= ramp:
        return 2.0 * math.sqrt(distance / accel)
    return 2.0 * rate / accel + (distance - ramp) / rate


def contact_time(distance: float, rate: float, accel: float) -> float:
    """Seconds from rest until a move towards a switch ``distance`` units away reaches it, accelerating
    to ``rate`` and never slowing down (GRBL stops the axis dead when its switch triggers)."""
    distance = abs(float(distance))
    if distance <= 0:
        return 0.0
    if not (accel > 0 and math.isfinite(accel)):
        return distance / rate
    ramp = rate * rate / (2.0 * accel)            # distance to reach the rate
    if distance <= ramp:
        return math.sqrt(2.0 * distance / accel)
    return rate / accel + (distance - ramp) / rate


def homing_worst_case_s(settings: dict[int, float], axes: int = 3) -> float:
    """The longest a ``$H`` can take before GRBL itself ends it (homed, or ``ALARM:8``/``9``): the
    whole search, pull-offs and the whole locate distance, for each of the first ``axes`` axes
    homed one after the other (GRBL 1.1 homes Z, then X and Y by default: this bounds any order)."""
    s = {**_DEFAULTS, **settings}
    seek, feed = max(s[25], 1e-6) / 60.0, max(s[24], 1e-6) / 60.0
    pulloff, debounce = s[27], s[26] / 1000.0
    total = 0.0
    for i in range(axes):
        accel = max(s[120 + i], 1e-6)
        total += (move_time(HOMING_SEARCH_SCALAR * s[130 + i], seek, accel)
                  + 2 * move_time(pulloff, seek, accel)
                  + move_time(HOMING_LOCATE_SCALAR * pulloff, feed, accel) + 4 * debounce)
    return total


@dataclass
class Segment:
    """One planned block moving from rest to rest along a straight line: ``advance`` moves it on by
    some time (accelerating, cruising at ``speed``, decelerating in time to stop at the target; or,
    in a feed hold, decelerating to a stop)."""

    start: list[float]
    target: list[float]
    speed: float                          # cruise speed along the path, units/s
    accel: float                          # units/s² along the path
    jog: bool = False
    length: float = 0.0
    done: float = 0.0
    v: float = 0.0                        # current speed, units/s

    def __post_init__(self) -> None:
        self.length = math.dist(self.start, self.target)

    @property
    def finished(self) -> bool:
        return self.done >= self.length

    def at(self) -> list[float]:
        if self.length <= 0:
            return list(self.target)
        f = min(self.done / self.length, 1.0)
        return [s + (t - s) * f for s, t in zip(self.start, self.target)]

    def advance(self, dt: float, hold: bool = False) -> float:
        """Move on by ``dt`` seconds; returns the time left over once the block finished (0 if not,
        and always 0 in a hold, which ends at rest short of the target)."""
        a = self.accel
        while dt > 1e-12:
            r = self.length - self.done
            if hold:
                if self.v <= 0:
                    return 0.0
                t = min(dt, self.v / a)
                self.done = min(self.done + self.v * t - 0.5 * a * t * t, self.length)
                self.v = 0.0 if t >= self.v / a else self.v - a * t
                return 0.0
            if r <= 1e-9:
                self.done, self.v = self.length, 0.0
                return dt
            if self.v * self.v / (2 * a) >= r - 1e-9:          # decelerate into the target
                t_end = self.v / a
                if t_end <= dt:
                    self.done, self.v = self.length, 0.0
                    return dt - t_end
                self.done += self.v * dt - 0.5 * a * dt * dt
                self.v -= a * dt
                return 0.0
            peak = min(self.speed, math.sqrt(a * r + self.v * self.v / 2))
            if self.v < peak - 1e-9:                             # accelerate
                t = min(dt, (peak - self.v) / a)
                self.done += self.v * t + 0.5 * a * t * t
                self.v = min(self.v + a * t, peak)
                dt -= t
                continue
            t = min(dt, (r - self.v * self.v / (2 * a)) / self.v)   # cruise
            self.done += self.v * t
            dt -= t
            if t <= 1e-12:
                self.done = self.length - self.v * self.v / (2 * a)
        return 0.0
