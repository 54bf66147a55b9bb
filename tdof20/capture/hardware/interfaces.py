"""The small interfaces every rig backend implements: Robot, Turntable, RGBDCamera.

One module per vendor implements them (``ur.py`` for a UR5 through ur_rtde, ``grbl.py`` for a
GRBL-controlled stepper turntable on a serial port, ``oakd.py`` for an OAK-D through depthai v3,
``sim.py`` for the simulated rig). Every call that talks to hardware takes or has a timeout and
raises :class:`HardwareError` (a one-line, human message) when the device fails; the capture
runner decides about retries. Units: millimetres, radians for joints, degrees for the table.
"""

from __future__ import annotations

import abc
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, TypeVar

import numpy as np

T = TypeVar("T")


class HardwareError(Exception):
    """A device failed or misbehaved. ``retryable`` says whether trying again may help (a timeout,
    a dropped frame) or not (a protective stop, an alarm: a person must act first)."""

    def __init__(self, device: str, message: str, retryable: bool = True):
        self.device = device
        self.retryable = retryable
        super().__init__(f"{device}: {' '.join(str(message).split())}")


class SafetyStop(HardwareError):
    """The robot is in a protective or emergency stop, or its safety mode changed: a person must
    clear it on the teach pendant before the capture goes on."""

    def __init__(self, device: str, message: str):
        super().__init__(device, message, retryable=False)


def call_with_timeout(fn: Callable[[], T], timeout_s: float, device: str, what: str) -> T:
    """Run ``fn`` in a daemon thread and wait at most ``timeout_s``. For library calls that can
    block forever (ur_rtde's constructors against a peer that never answers): on timeout the
    thread is abandoned and a HardwareError is raised."""
    box: dict = {}

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the caller
            box["error"] = e

    th = threading.Thread(target=target, name=f"{device}:{what}", daemon=True)
    th.start()
    th.join(timeout_s)
    if th.is_alive():
        raise HardwareError(device, f"{what} did not answer within {timeout_s:g} s")
    if "error" in box:
        err = box["error"]
        if isinstance(err, HardwareError):
            raise err
        raise HardwareError(device, f"{what} failed: {type(err).__name__}: {err}") from err
    return box["value"]


def wait_until(predicate: Callable[[], bool], timeout_s: float, device: str, what: str,
               poll_s: float = 0.01) -> None:
    """Poll ``predicate`` until it is true or ``timeout_s`` passes (then HardwareError)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise HardwareError(device, f"{what} did not happen within {timeout_s:g} s")
        time.sleep(poll_s)


@dataclass
class RobotState:
    """What the robot reports back: joints (rad) and T_base_tcp (4,4, mm)."""

    q: np.ndarray
    T_base_tcp: np.ndarray


@dataclass
class RGBDFrame:
    """A synchronised colour + depth pair from the camera."""

    rgb: np.ndarray                  # (H,W,3) uint8 RGB
    depth: np.ndarray                # (H,W) uint16, depth_scale mm per unit, 0 = no depth
    t_rgb: float                     # device timestamps, seconds
    t_depth: float
    meta: dict = field(default_factory=dict)


class Robot(abc.ABC):
    """A 6-joint arm carrying the camera."""

    name = "robot"

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the connection (with the backend's connect timeout)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection; never raises."""

    @abc.abstractmethod
    def move_joints(self, q: np.ndarray, speed: float, acceleration: float, timeout_s: float) -> None:
        """moveJ to ``q`` (rad) with ``speed`` (rad/s) and ``acceleration`` (rad/s^2); returns when
        the motion ended. Raises SafetyStop on a protective stop or safety-mode change."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """Actual joints and TCP pose, read back from the controller."""

    @abc.abstractmethod
    def check_safety(self) -> None:
        """Raise SafetyStop if the robot is not in normal safety mode."""

    def stop(self) -> None:
        """Stop any motion now (best effort, never raises)."""

    def resume(self) -> None:
        """After a person cleared a safety stop: make the robot ready to move again (a backend may
        unlock the stop, restart its program ...), or raise SafetyStop saying what still stops it.
        The default only checks the safety state."""
        self.check_safety()


class Turntable(abc.ABC):
    """A motorised turntable with absolute positioning in degrees (counter-clockwise from above)."""

    name = "turntable"

    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def home(self, timeout_s: float) -> None:
        """Find the reference position; afterwards the angle is 0."""

    @abc.abstractmethod
    def move_to(self, angle_deg: float, timeout_s: float) -> float:
        """Turn to the absolute ``angle_deg`` and wait until the table has stopped; returns the
        angle the controller reports."""

    @abc.abstractmethod
    def angle(self) -> float:
        """The current angle in degrees, as the controller reports it."""

    def stop(self) -> None:
        """Stop any motion now (best effort, never raises)."""


class RGBDCamera(abc.ABC):
    """A camera delivering synchronised colour and depth, depth aligned to colour."""

    name = "camera"

    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def intrinsics(self) -> dict:
        """{"K": [9], "width", "height", "depth_scale"} of the colour camera (depth aligned to it)."""

    @abc.abstractmethod
    def grab(self, timeout_s: float) -> RGBDFrame:
        """The next synchronised pair captured after this call started."""
