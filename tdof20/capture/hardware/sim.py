"""The simulated rig behind the same interfaces as the hardware: a UR5 that moves instantly to
its targets, a turntable, and a camera that ray-casts what it sees from the robot's actual pose.

The three devices share one :class:`SimWorld` (robot joints, table angle, which objects stand on
the table: glass or opaque twins). The turntable reports the angle it was told (an open-loop
stepper does); where it physically stands — turned the other way, off by a step-angle error — is
the world's :class:`~tdof20.sim.lab.TableMotion`, and the camera renders that.

``faults`` inject failures for tests and drills: ``{"camera_timeouts": n}`` makes the next n
grabs time out, ``{"turntable_timeouts": n}`` the next n moves, ``{"protective_stop_on_move": k}``
puts the robot in a protective stop on its k-th move (1-based) until
:meth:`SimWorld.clear_protective_stop`.
"""

from __future__ import annotations

import time

import numpy as np

from tdof20.capture.hardware.interfaces import (HardwareError, RGBDCamera, RGBDFrame, Robot, RobotState,
                                                SafetyStop, Turntable)
from tdof20.sim.lab import TableMotion
from tdof20.sim.render import SimRenderer
from tdof20.sim.rig import UR5_HOME, ur5_fk


class SimWorld:
    """State shared by the simulated devices."""

    def __init__(self, renderer: SimRenderer, arm_qs: list[np.ndarray], faults: dict | None = None,
                 table: TableMotion | None = None):
        self.renderer = renderer
        self.table = table or TableMotion()
        self.arm_qs = [np.asarray(q, float) for q in arm_qs]
        self.q = UR5_HOME.copy()
        self.angle = 0.0
        self.phase = "transparent"
        self.faults = dict(faults or {})
        self.protective_stop = False
        self.moves = 0

    def arm_index(self) -> int:
        d = [np.abs(self.q - q).max() for q in self.arm_qs]
        i = int(np.argmin(d))
        if d[i] > 1e-6:
            raise HardwareError("sim camera", "the arm is not at one of the session's arm positions")
        return i

    def physical_angle(self) -> float:
        """Where the table really stands (deg, counter-clockwise from above) for the angle it
        was told, at the current phase and arm position."""
        if self.table.is_nominal:
            return self.angle
        return self.table.actual(self.phase, self.arm_index(), self.angle)

    def take_fault(self, name: str) -> bool:
        n = self.faults.get(name, 0)
        if n > 0:
            self.faults[name] = n - 1
            return True
        return False

    def clear_protective_stop(self) -> None:
        self.protective_stop = False


class _OnWorld:
    """A simulated device: it acts on the shared :class:`SimWorld`; nothing to connect or close."""

    def __init__(self, world: SimWorld):
        self.world = world

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass


class SimRobot(_OnWorld, Robot):
    name = "sim robot"

    def check_safety(self) -> None:
        if self.world.protective_stop:
            raise SafetyStop(self.name, "protective stop: clear it on the teach pendant, then resume")

    def move_joints(self, q, speed, acceleration, timeout_s) -> None:
        q = np.asarray(q, float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise HardwareError(self.name, f"moveJ needs 6 finite joint angles, got {q.tolist()}", retryable=False)
        self.check_safety()
        self.world.moves += 1
        if self.world.faults.get("protective_stop_on_move") == self.world.moves:
            self.world.protective_stop = True
            raise SafetyStop(self.name, "protective stop during moveJ: clear it on the teach pendant, then resume")
        self.world.q = q.copy()

    def state(self) -> RobotState:
        return RobotState(self.world.q.copy(), ur5_fk(self.world.q))

    def stop(self) -> None:
        pass


class SimTurntable(_OnWorld, Turntable):
    name = "sim turntable"

    def home(self, timeout_s: float) -> None:
        self.world.angle = 0.0

    def move_to(self, angle_deg: float, timeout_s: float) -> float:
        if self.world.take_fault("turntable_timeouts"):
            raise HardwareError(self.name, f"the table did not report Idle within {timeout_s:g} s")
        self.world.angle = float(angle_deg)
        return self.world.angle

    def angle(self) -> float:
        return self.world.angle


class SimCamera(_OnWorld, RGBDCamera):
    name = "sim camera"

    def intrinsics(self) -> dict:
        return self.world.renderer.camera.to_dict()

    def grab(self, timeout_s: float) -> RGBDFrame:
        if self.world.take_fault("camera_timeouts"):
            raise HardwareError(self.name, f"no synchronised colour+depth pair within {timeout_s:g} s")
        w = self.world
        f = w.renderer.render(w.arm_index(), w.physical_angle(), w.phase)
        t = time.time()
        return RGBDFrame(f.rgb, f.depth, t, t)
