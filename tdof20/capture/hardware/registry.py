"""Which class drives each device of a rig, by the config's ``backend``: one line per vendor.

A vendor is one module of :mod:`tdof20.capture.hardware` (ur_rtde, GRBL, depthai OAK-D) and one
:class:`Vendor` line in :data:`VENDORS`: its backend name, the class (named by module and class,
so that the module — and the vendor library it drives — is imported only when a rig uses it:
``tdof20 --help`` and a simulated rig import none of them), and how the class is made from the
config's section. ``"sim"`` is not a vendor: the simulated rig's devices share one world and
are assembled together (:mod:`tdof20.capture.rig`).

To add a vendor: write its module (a :class:`~tdof20.capture.hardware.interfaces.Robot`,
``Turntable`` or ``RGBDCamera``), and add its line below.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable

SIM = "sim"
DEVICES = ("robot", "turntable", "camera")


@dataclass(frozen=True)
class Vendor:
    """A device class for one backend: ``target`` "module:Class", imported on :meth:`make`;
    ``build(cls, section)`` makes the device from the config's section (e.g. ``cfg.robot``)."""

    device: str
    backend: str
    target: str
    build: Callable[[type, Any], Any]

    def load(self) -> type:
        """The device class (its module is imported now)."""
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)

    def make(self, section: Any) -> Any:
        """The device for a config section whose ``backend`` is this vendor's (nothing connects yet)."""
        return self.build(self.load(), section)


def _ur(cls: type, r: Any) -> Any:
    return cls(r.host, connect_timeout_s=r.connect_timeout_s, joint_tolerance_rad=r.joint_tolerance_rad,
               stop_deceleration=r.stop_deceleration)


def _grbl(cls: type, t: Any) -> Any:
    return cls(t.port, baudrate=t.baudrate, axis=t.axis, units_per_degree=t.units_per_degree,
               feed_deg_per_s=t.feed_deg_per_s, timeout_s=t.timeout_s, home=t.home)


def _oakd(cls: type, c: Any) -> Any:
    return cls(width=c.width, height=c.height, fps=c.fps, device_id=c.device_id or None)


VENDORS: tuple[Vendor, ...] = (
    Vendor("robot", "ur_rtde", "tdof20.capture.hardware.ur:URRobot", _ur),
    Vendor("turntable", "grbl", "tdof20.capture.hardware.grbl:GrblTurntable", _grbl),
    Vendor("camera", "oakd", "tdof20.capture.hardware.oakd:OakDCamera", _oakd),
)


def backends(device: str) -> tuple[str, ...]:
    """The backend names a config may give ``device``: "sim" and each vendor's."""
    return (SIM, *(v.backend for v in VENDORS if v.device == device))


def vendor(device: str, backend: str) -> Vendor:
    """The vendor line of ``device`` with this ``backend`` (KeyError if none: the config check
    refuses an unknown backend before a rig is built)."""
    for v in VENDORS:
        if v.device == device and v.backend == backend:
            return v
    raise KeyError(f"no {device} backend {backend!r} (valid: {', '.join(backends(device))})")


__all__ = ["Vendor", "VENDORS", "DEVICES", "SIM", "backends", "vendor"]
