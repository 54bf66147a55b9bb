"""A Universal Robots UR5 through ur_rtde (``rtde_control`` / ``rtde_receive``).

Units at this interface: joints in radians, ``T_base_tcp`` in millimetres (ur_rtde reports the TCP
pose in metres with an axis-angle rotation vector; it is converted here). Every call to the
library runs under a timeout (:func:`call_with_timeout`); failures become a one-line
:class:`HardwareError`, stops a person must clear become :class:`SafetyStop`.

Two facts about ur_rtde 1.6 shape this module:

* its Python constructors hold the GIL while they connect, so a constructor blocked on a peer that
  never answers also blocks the thread that should time it out. Before constructing the real
  interfaces, :func:`probe_rtde` therefore talks to the RTDE port in pure Python (socket timeouts)
  and fails fast; the constructors still run under :func:`call_with_timeout` (which works for
  library versions and fakes that release the GIL).
* its methods (``moveJ``, the getters, ``reconnect`` ...) release the GIL, so a blocking ``moveJ``
  runs in a worker thread while this thread watches the safety state and the deadline.

Manual smoke test on the rig (moves the last joint by a small step and back)::

    python -m tdof20.capture.hardware.ur --host 192.168.1.10 [--move 0.05]
"""

from __future__ import annotations

import logging
import math
import re
import socket
import struct
import threading
import time
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from tdof20.capture.hardware.interfaces import (
    HardwareError,
    Robot,
    RobotState,
    SafetyStop,
    call_with_timeout,
)
from tdof20.errors import TdofError

log = logging.getLogger(__name__)

RTDE_PORT = 30004
_RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'

CONNECT_HINT = "check the IP, that the robot is powered and in remote control mode"

# UR safety modes (RTDE ``safety_mode``), with what the operator has to do.
SAFETY_NORMAL = 1
SAFETY_REDUCED = 2
SAFETY_MODES: dict[int, str] = {
    1: "normal",
    2: "reduced",
    3: "protective stop: clear it on the teach pendant, then resume",
    4: "recovery mode: a joint is beyond its safety limits; jog it back inside the limits on the teach pendant",
    5: "safeguard stop: a safeguard input (door, light curtain) is open; close it, then resume on the teach pendant",
    6: "system emergency stop: an external emergency-stop input is active; release it and reset the robot on the teach pendant",
    7: "emergency stop: an emergency-stop button is pressed; release it, then power on and release the brakes on the teach pendant",
    8: "safety violation: the safety system stopped the robot; read the log on the teach pendant and restart the safety system",
    9: "safety fault: the safety system reports a fault; read the log on the teach pendant and restart the controller",
    10: "joint ID validation mode: finish the joint validation on the teach pendant",
    11: "undefined safety mode: check the robot on the teach pendant",
    12: "automatic-mode safeguard stop: an automatic-mode safeguard input is open; close it, then resume",
    13: "three-position enabling stop: the enabling device was released; hold it in the middle position, then resume",
}

# RTDE robot modes (``robot_mode``).
ROBOT_MODE_RUNNING = 7
ROBOT_MODES: dict[int, str] = {
    -1: "no controller", 0: "disconnected", 1: "confirm safety", 2: "booting", 3: "power off",
    4: "power on", 5: "idle (brakes on)", 6: "backdrive", 7: "running", 8: "updating firmware",
}

# Limits of moveJ in ur_rtde (leading axis).
MAX_JOINT_SPEED = 3.14      # rad/s
MAX_JOINT_ACCEL = 40.0      # rad/s^2


class JointTargetError(TdofError, ValueError):
    """A joint target, speed or acceleration that cannot be sent to the robot (caller's mistake)."""


def safety_mode_text(mode: int) -> str:
    return SAFETY_MODES.get(int(mode), f"unknown safety mode {mode}: check the robot on the teach pendant")


def _recv_exact(sock: socket.socket, n: int, deadline: float) -> bytes:
    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout()
        sock.settimeout(left)
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("the peer closed the connection")
        data += chunk
    return data


def probe_rtde(host: str, timeout_s: float, port: int = RTDE_PORT, device: str | None = None) -> None:
    """Ask the RTDE server at ``host:port`` for its protocol version, in pure Python, within
    ``timeout_s``: HardwareError if nothing listens or the peer does not answer like an RTDE server.
    (ur_rtde's constructors would block forever, holding the GIL, against a silent peer.)"""
    device = device or f"UR5 at {host}"
    deadline = time.monotonic() + timeout_s
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.sendall(struct.pack(">HBH", 5, _RTDE_REQUEST_PROTOCOL_VERSION, 2))
            size, ptype = struct.unpack(">HB", _recv_exact(sock, 3, deadline))
            if size >= 3:
                _recv_exact(sock, size - 3, deadline)
            if ptype != _RTDE_REQUEST_PROTOCOL_VERSION:
                raise HardwareError(device, f"{host}:{port} answered, but not as a UR RTDE server "
                                            f"(packet type {ptype}); {CONNECT_HINT}", retryable=False)
    except HardwareError:
        raise
    except socket.timeout:
        raise HardwareError(device, f"the robot at {host} did not answer on the RTDE port {port} within "
                                    f"{timeout_s:g} s; {CONNECT_HINT}") from None
    except (OSError, ConnectionError) as e:
        reason = getattr(e, "strerror", None) or str(e) or type(e).__name__
        raise HardwareError(device, f"cannot reach the robot at {host}:{port} ({reason}); {CONNECT_HINT}") from None


DASHBOARD_PORT = 29999
RUNTIME_PLAYING = 2
# safety_status_bits (RTDE)
BIT_PROTECTIVE_STOPPED = 1 << 2
BIT_EMERGENCY_STOPPED = 1 << 7
SAFETY_MODE_BY_NAME = {"NORMAL": 1, "REDUCED": 2, "PROTECTIVE_STOP": 3, "RECOVERY": 4, "SAFEGUARD_STOP": 5,
                       "SYSTEM_EMERGENCY_STOP": 6, "ROBOT_EMERGENCY_STOP": 7, "VIOLATION": 8, "FAULT": 9,
                       "VALIDATE_JOINT_ID": 10, "UNDEFINED_SAFETY_MODE": 11,
                       "AUTOMATIC_MODE_SAFEGUARD_STOP": 12, "SYSTEM_THREE_POSITION_ENABLING_STOP": 13}
ROBOT_MODE_BY_NAME = {"NO_CONTROLLER": -1, "DISCONNECTED": 0, "CONFIRM_SAFETY": 1, "BOOTING": 2, "POWER_OFF": 3,
                      "POWER_ON": 4, "IDLE": 5, "BACKDRIVE": 6, "RUNNING": 7, "UPDATING_FIRMWARE": 8}
# what the operator does when the arm is not running (robot mode), in the pendant's words
NOT_RUNNING_HINT = {
    -1: "the controller reports no arm: check the cable between the arm and the control box",
    0: "the arm is disconnected from the controller: check the cable between the arm and the control box",
    1: "the robot waits for its safety configuration to be confirmed: confirm it on the teach pendant",
    2: "the arm is still booting: wait until the teach pendant shows it ready",
    3: "the arm is powered off: power it on and release the brakes on the teach pendant (ON, then START)",
    4: "the arm is powering on: wait, then release the brakes on the teach pendant (START)",
    5: "the arm's brakes are on: release them on the teach pendant (START)",
    6: "the arm is in backdrive mode: leave it on the teach pendant",
    8: "the controller is updating the joint firmware: wait until it has finished",
}
MOVING_RAD_S = 1e-3     # a joint faster than this is moving


def not_running_text(mode: int) -> str:
    name = next((k for k, v in ROBOT_MODE_BY_NAME.items() if v == mode), str(mode))
    return f"{NOT_RUNNING_HINT.get(mode, 'the arm is not ready to move: check the teach pendant')} (robot mode {name})"


class Dashboard:
    """UR's dashboard server (port 29999) in pure Python, every exchange under a socket timeout.

    Used before the RTDE interfaces are opened (ur_rtde's constructors block, holding the GIL, until
    the control script runs: a powered-off arm or a protective stop would cost their fixed 5 s and
    give the library's words), and to unlock a protective stop, power the arm on and release its
    brakes when the operator resumes."""

    WELCOME = "Connected: Universal Robots Dashboard Server"

    def __init__(self, host: str, device: str, port: int = DASHBOARD_PORT, timeout_s: float = 2.0):
        self.host, self.device, self.port, self.timeout_s = host, device, int(port), float(timeout_s)
        self._sock: socket.socket | None = None
        self._buf = b""

    def _line(self, deadline: float) -> str:
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise socket.timeout()
            self._sock.settimeout(left)
            chunk = self._sock.recv(4096)
            if not chunk:
                raise ConnectionError("the dashboard server closed the connection")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("utf-8", "replace").strip()

    def connect(self, timeout_s: float | None = None) -> None:
        timeout_s = self.timeout_s if timeout_s is None else max(float(timeout_s), 0.05)
        self.close()
        deadline = time.monotonic() + timeout_s
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
            welcome = self._line(deadline)
        except socket.timeout:
            self.close()
            raise HardwareError(self.device, f"the robot at {self.host} did not answer on its dashboard port "
                                             f"{self.port} within {timeout_s:g} s; {CONNECT_HINT}") from None
        except (OSError, ConnectionError) as e:
            self.close()
            reason = getattr(e, "strerror", None) or str(e) or type(e).__name__
            raise HardwareError(self.device, f"cannot reach the robot's dashboard server at {self.host}:{self.port} "
                                             f"({reason}); {CONNECT_HINT}") from None
        if not welcome.startswith("Connected"):
            self.close()
            raise HardwareError(self.device, f"{self.host}:{self.port} answered {welcome!r}, not as a UR dashboard "
                                             f"server; {CONNECT_HINT}", retryable=False)

    def ask(self, command: str, timeout_s: float | None = None) -> str:
        """Send one command, return its one-line answer (one reconnect if the link was lost)."""
        timeout_s = self.timeout_s if timeout_s is None else float(timeout_s)
        for attempt in (1, 2):
            if self._sock is None:
                self.connect(timeout_s)
            try:
                self._sock.sendall(command.encode() + b"\n")
                return self._line(time.monotonic() + timeout_s)
            except socket.timeout:
                self.close()
                raise HardwareError(self.device, f"the dashboard server did not answer {command!r} within "
                                                 f"{timeout_s:g} s; {CONNECT_HINT}") from None
            except (OSError, ConnectionError):
                self.close()
                if attempt == 2:
                    raise HardwareError(self.device, f"lost the dashboard connection to {self.host} while asking "
                                                     f"{command!r}; {CONNECT_HINT}") from None
        raise AssertionError("unreachable")

    def robot_mode(self) -> int:
        ans = self.ask("robotmode")   # "Robotmode: RUNNING"
        return ROBOT_MODE_BY_NAME.get(ans.split(":")[-1].strip().upper(), -1)

    def safety_mode(self) -> int:
        ans = self.ask("safetystatus")
        if ans.lower().startswith("could not understand"):   # a CB3 before 3.11: safetymode only
            ans = self.ask("safetymode")
        return SAFETY_MODE_BY_NAME.get(ans.split(":")[-1].strip().upper(), 11)

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock, self._buf = None, b""


class _Snapshot:
    """One consistent reading of the receive interface: all from the same data package."""

    __slots__ = ("ts", "q", "qd", "pose", "bits", "mode", "robot_mode", "runtime", "connected")

    def __init__(self, ts, q, qd, pose, bits, mode, robot_mode, runtime, connected):
        self.ts, self.q, self.qd, self.pose = float(ts), q, qd, pose
        self.bits, self.mode, self.robot_mode, self.runtime = int(bits), int(mode), int(robot_mode), int(runtime)
        self.connected = bool(connected)

    @property
    def speed(self) -> float:
        return float(np.abs(self.qd).max()) if self.qd.shape == (6,) else float("inf")


class URRobot(Robot):
    """A UR5 (CB3 or e-Series) driven through ur_rtde.

    ``control_factory`` / ``receive_factory`` default to ``rtde_control.RTDEControlInterface`` and
    ``rtde_receive.RTDEReceiveInterface`` and are called as ``factory(host, frequency)``; tests
    inject fakes with the library's method names. ``preflight`` (default: only with the real
    library) asks the dashboard server (29999) and the RTDE port in pure Python before
    constructing the interfaces. Moves run asynchronously (moveJ with ``asynchronous=True``) and
    are watched here, so that a stop or a timeout stops the arm at once (stopJ at
    ``stop_deceleration``) and is confirmed by the controller's reported joint speeds; every state
    used comes from a data package newer than the call (``stale_s``: the longest the controller's
    timestamp may stand still).
    """

    name = "ur5"

    def __init__(self, host: str, connect_timeout_s: float = 5.0, frequency: float = 125.0,
                 control_factory: Callable[..., Any] | None = None,
                 receive_factory: Callable[..., Any] | None = None,
                 reconnect_attempts: int = 2, *,
                 joint_tolerance_rad: float = 0.002,
                 call_timeout_s: float = 2.0,
                 settle_timeout_s: float = 0.5,
                 poll_s: float = 0.01,
                 stale_s: float = 0.25,
                 stop_deceleration: float = 2.0,
                 resume_timeout_s: float = 20.0,
                 preflight: bool | None = None,
                 rtde_port: int = RTDE_PORT,
                 dashboard_port: int = DASHBOARD_PORT):
        self.host = str(host)
        self.device = f"UR5 at {self.host}"
        self.connect_timeout_s = float(connect_timeout_s)
        self.frequency = float(frequency)
        self.reconnect_attempts = int(reconnect_attempts)
        self.joint_tolerance_rad = float(joint_tolerance_rad)
        self.call_timeout_s = float(call_timeout_s)
        self.settle_timeout_s = float(settle_timeout_s)
        self.poll_s = float(poll_s)
        self.stale_s = float(stale_s)
        self.stop_deceleration = float(stop_deceleration)
        if not (0 < self.stop_deceleration <= MAX_JOINT_ACCEL):   # robot.stop_deceleration, checked in the config too
            raise ValueError(f"stop_deceleration must be in (0, {MAX_JOINT_ACCEL:g}] rad/s^2, got {stop_deceleration!r}")
        self.resume_timeout_s = float(resume_timeout_s)
        self.rtde_port = int(rtde_port)
        self.dashboard_port = int(dashboard_port)
        self._control_factory = control_factory
        self._receive_factory = receive_factory
        self._preflight = (control_factory is None and receive_factory is None) if preflight is None else bool(preflight)
        self._ctl: Any = None
        self._rcv: Any = None
        self._db: Dashboard | None = None
        self._last_mode: int | None = None
        self._last_ts: tuple[float, float] | None = None   # (controller timestamp, monotonic time it was first seen)

    # ------------------------------------------------------------------ connection

    def _factories(self) -> tuple[Callable[..., Any], Callable[..., Any]]:
        ctl_f, rcv_f = self._control_factory, self._receive_factory
        if ctl_f is None or rcv_f is None:
            try:
                import rtde_control
                import rtde_receive
            except ImportError as e:
                raise HardwareError(self.device, "the ur_rtde package is not installed (pip install ur-rtde)",
                                    retryable=False) from e
            ctl_f = ctl_f or rtde_control.RTDEControlInterface
            rcv_f = rcv_f or rtde_receive.RTDEReceiveInterface
        return ctl_f, rcv_f

    def _construct(self, factory: Callable[..., Any], timeout_s: float, which: str) -> Any:
        try:
            return call_with_timeout(lambda: factory(self.host, self.frequency), max(timeout_s, 0.01),
                                     self.device, f"opening the RTDE {which} interface")
        except HardwareError as e:
            cause = e.__cause__
            if cause is None:  # timed out
                raise HardwareError(self.device, f"the robot at {self.host} did not answer within "
                                                 f"{self.connect_timeout_s:g} s (RTDE {which} interface); "
                                                 f"{CONNECT_HINT}") from None
            raise HardwareError(self.device, f"could not open the RTDE {which} interface to {self.host} "
                                             f"({type(cause).__name__}: {cause}); {CONNECT_HINT}") from cause

    def _dashboard_check(self, deadline: float) -> None:
        """Ask the dashboard server, before any RTDE interface is opened, whether the arm can run
        a program: SafetyStop for a protective or emergency stop, HardwareError (not retryable)
        for an arm powered off, with its brakes on, or in local control."""
        db = Dashboard(self.host, self.device, self.dashboard_port, timeout_s=min(2.0, self.connect_timeout_s))
        db.connect()
        try:
            mode = db.safety_mode()
            if mode not in (SAFETY_NORMAL, SAFETY_REDUCED):
                raise SafetyStop(self.device, f"{safety_mode_text(mode)} (found at connect, before any motion)")
            rmode = db.robot_mode()
            if rmode != ROBOT_MODE_RUNNING:
                raise HardwareError(self.device, f"{not_running_text(rmode)}; then run again (found at connect, "
                                                 f"before any motion)", retryable=False)
            version = db.ask("PolyscopeVersion")
            m = re.search(r"(\d+)\.(\d+)\.\d+", version)
            major_minor = (int(m[1]), int(m[2])) if m else (0, 0)
            if tuple(major_minor) >= (5, 6) and db.ask("is in remote control").strip().lower() != "true":
                raise HardwareError(self.device, "the robot is in local control: switch it to remote control on the "
                                                 "teach pendant, then run again", retryable=False)
        except BaseException:
            db.close()
            raise
        self._db = db

    def connect(self) -> None:
        """Within ``connect_timeout_s`` in all: ask the dashboard whether the arm can run (powered,
        brakes released, no protective or emergency stop), probe the RTDE port, then open the
        receive and the control interface (which uploads ur_rtde's control script)."""
        if self._ctl is not None and self._rcv is not None:
            self.check_safety()
            return
        ctl_f, rcv_f = self._factories()
        deadline = time.monotonic() + self.connect_timeout_s
        if self._preflight:
            self._dashboard_check(deadline)
            probe_rtde(self.host, max(deadline - time.monotonic(), 0.05), self.rtde_port, self.device)
        try:
            rcv = self._construct(rcv_f, deadline - time.monotonic(), "receive")
            try:
                ctl = self._construct(ctl_f, deadline - time.monotonic(), "control")
            except BaseException:
                _best_effort(lambda: rcv.disconnect(), 1.0, self.device, "disconnect")
                raise
        except BaseException:
            if self._db is not None:
                self._db.close()
                self._db = None
            raise
        self._rcv, self._ctl = rcv, ctl
        self._last_mode = None
        self._last_ts = None
        log.info("%s: connected (RTDE %g Hz)", self.device, self.frequency)
        self._warn_tcp_offset()
        self.check_safety()

    def _warn_tcp_offset(self) -> None:
        get = getattr(self._ctl, "getTCPOffset", None)
        if get is None:
            return
        try:
            off = np.asarray(call_with_timeout(get, self.call_timeout_s, self.device, "getTCPOffset"), float)
        except HardwareError:
            return
        if off.shape == (6,) and np.abs(off).max() > 1e-6:
            log.warning("%s: the controller has a TCP offset %s (m, rotvec); T_base_tcp is reported for that "
                        "TCP, so the hand-eye calibration must use the same one", self.device,
                        np.round(off, 4).tolist())

    def close(self) -> None:
        """Stop the control script and disconnect both interfaces; never raises."""
        ctl, rcv, db = self._ctl, self._rcv, self._db
        self._ctl = self._rcv = self._db = None
        if ctl is not None:
            _best_effort(lambda: ctl.stopScript(), 2.0, self.device, "stopScript")
            _best_effort(lambda: ctl.disconnect(), 2.0, self.device, "disconnect control")
        if rcv is not None:
            _best_effort(lambda: rcv.disconnect(), 2.0, self.device, "disconnect receive")
        if db is not None:
            db.close()

    def stop(self) -> None:
        """Decelerate the joints to zero (stopJ at ``stop_deceleration``) and wait until the
        controller reports them still; best effort, never raises."""
        if self._ctl is None or self._rcv is None:
            return
        try:
            self._stop_and_confirm(1.0)
        except BaseException as e:  # noqa: BLE001 - best effort by contract
            log.warning("%s: stop: %s", self.device, e)

    def __enter__(self) -> "URRobot":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _require(self) -> None:
        if self._ctl is None or self._rcv is None:
            raise HardwareError(self.device, "not connected: call connect() first", retryable=False)

    def _call(self, fn: Callable[[], Any], what: str, timeout_s: float | None = None) -> Any:
        return call_with_timeout(fn, self.call_timeout_s if timeout_s is None else timeout_s, self.device, what)

    def _is_connected(self) -> bool:
        ctl, rcv = self._ctl, self._rcv
        return bool(self._call(lambda: rcv.isConnected() and ctl.isConnected(), "isConnected"))

    def _ensure_connection(self) -> None:
        """If the RTDE connection dropped, try ``reconnect()`` up to ``reconnect_attempts`` times."""
        self._require()
        if self._is_connected():
            return
        self._reconnect()

    def _reconnect(self) -> None:
        ctl, rcv = self._ctl, self._rcv
        last = "reconnect() returned False"
        for attempt in range(1, self.reconnect_attempts + 1):
            log.warning("%s: RTDE connection lost, reconnecting (attempt %d of %d)", self.device, attempt,
                        self.reconnect_attempts)
            try:
                for iface, which in ((rcv, "receive"), (ctl, "control")):
                    if not self._call(iface.isConnected, f"isConnected ({which})"):
                        if not self._call(iface.reconnect, f"reconnect ({which})", self.connect_timeout_s):
                            raise HardwareError(self.device, f"reconnect() of the {which} interface returned False")
                if self._is_connected():
                    log.info("%s: reconnected", self.device)
                    self._last_ts = None
                    return
            except HardwareError as e:
                last = str(e)
            time.sleep(min(0.2 * attempt, 1.0))
        raise HardwareError(self.device, f"lost the RTDE connection to {self.host} and could not reconnect after "
                                         f"{self.reconnect_attempts} attempt(s) ({last}); check the network cable "
                                         f"and that the robot is on and in remote control mode")

    # ------------------------------------------------------------------ fresh state

    def _snapshot(self) -> _Snapshot:
        """One reading of the receive interface whose values all come from one data package (the
        controller timestamp read before and after them is the same)."""
        rcv = self._rcv

        def read() -> _Snapshot:
            for _ in range(5):
                ts = rcv.getTimestamp()
                snap = _Snapshot(ts, np.asarray(rcv.getActualQ(), float), np.asarray(rcv.getActualQd(), float),
                                 np.asarray(rcv.getActualTCPPose(), float), rcv.getSafetyStatusBits(),
                                 rcv.getSafetyMode(), rcv.getRobotMode(), rcv.getRuntimeState(), rcv.isConnected())
                if rcv.getTimestamp() == ts:
                    return snap
            return snap

        snap = self._call(read, "reading the robot state")
        now = time.monotonic()
        if self._last_ts is None or snap.ts != self._last_ts[0]:
            self._last_ts = (snap.ts, now)
        return snap

    def _stale_for(self) -> float:
        return time.monotonic() - self._last_ts[1] if self._last_ts is not None else 0.0

    def _frozen_error(self, after: str) -> HardwareError:
        return HardwareError(self.device, f"no new state from the controller for {self._stale_for():.2f} s "
                                          f"{after}(its RTDE data stream stopped while the connection stays "
                                          f"open): check the network and the controller; no stale pose is used")

    def _fresh(self, after_ts: float | None = None, timeout_s: float | None = None) -> _Snapshot:
        """A snapshot from a data package newer than ``after_ts`` (default: the newest seen when
        called); HardwareError if none comes within ``stale_s`` (the stream froze)."""
        first = self._snapshot()
        if after_ts is None:
            after_ts = first.ts
        deadline = time.monotonic() + (self.stale_s if timeout_s is None else timeout_s)
        snap = first
        while snap.ts <= after_ts:
            if not snap.connected:
                self._reconnect()
                return self._fresh(None, timeout_s)
            if time.monotonic() > deadline:
                raise self._frozen_error("")
            time.sleep(min(self.poll_s, 0.004))
            snap = self._snapshot()
        return snap

    # ------------------------------------------------------------------ state and safety

    def state(self) -> RobotState:
        """Actual joints (rad) and T_base_tcp (4,4, mm) from a data package the controller sent
        after this call began (HardwareError if the stream is frozen)."""
        self._ensure_connection()
        snap = self._fresh()
        q, pose = snap.q, snap.pose
        if q.shape != (6,) or pose.shape != (6,) or not (np.isfinite(q).all() and np.isfinite(pose).all()):
            raise HardwareError(self.device, f"the controller sent an invalid state (q {q.tolist()}, "
                                             f"TCP pose {pose.tolist()})")
        return RobotState(q=q, T_base_tcp=tcp_pose_to_T(pose))

    def _safety_problem(self, snap: _Snapshot) -> str | None:
        mode = snap.mode
        if mode != self._last_mode:
            if mode == SAFETY_REDUCED:
                log.warning("%s: the robot is in reduced mode (slower, limited motion)", self.device)
            elif self._last_mode is not None:
                log.info("%s: safety mode %s -> %s", self.device, self._last_mode, mode)
            self._last_mode = mode
        if snap.bits & BIT_EMERGENCY_STOPPED or mode in (6, 7):
            return safety_mode_text(mode if mode in (6, 7) else 7)
        if snap.bits & BIT_PROTECTIVE_STOPPED or mode == 3:
            return SAFETY_MODES[3]
        if mode not in (SAFETY_NORMAL, SAFETY_REDUCED):
            return safety_mode_text(mode)
        return None

    def check_safety(self) -> None:
        """SafetyStop (a message saying what to do) unless the safety mode is normal or reduced."""
        self._require()
        problem = self._safety_problem(self._fresh())
        if problem:
            raise SafetyStop(self.device, problem)

    def _check_running(self, snap: _Snapshot) -> None:
        if snap.robot_mode != ROBOT_MODE_RUNNING:
            raise HardwareError(self.device, f"{not_running_text(snap.robot_mode)}; then resume", retryable=False)

    def _program_running(self) -> bool:
        return bool(self._call(self._ctl.isProgramRunning, "isProgramRunning"))

    def _restart_program(self, deadline: float) -> None:
        """Upload ur_rtde's control script again (reuploadScript) and wait until it runs."""
        ctl = self._ctl
        log.warning("%s: the control script is not running; uploading it again", self.device)
        if not self._call(ctl.reuploadScript, "reuploadScript", max(deadline - time.monotonic(), 0.5)):
            raise HardwareError(self.device, "could not upload the control script again (reuploadScript returned "
                                             "False); check the robot on the teach pendant", retryable=False)
        while not self._program_running():
            if time.monotonic() > deadline:
                raise HardwareError(self.device, "the control script did not start again after it was re-uploaded: "
                                                 "check the teach pendant for a popup or an error, then resume",
                                    retryable=False)
            time.sleep(0.02)

    def resume(self, timeout_s: float | None = None) -> None:
        """After the operator cleared a stop (and pressed Enter): unlock a protective stop through
        the dashboard once PolyScope allows it (5 s after the stop), power the arm on and release
        its brakes if the stop left them so, upload the control script again and check that it
        runs. SafetyStop if a stop is still active (an emergency-stop button still pressed)."""
        self._require()
        deadline = time.monotonic() + (self.resume_timeout_s if timeout_s is None else float(timeout_s))
        self._ensure_connection()
        snap = self._fresh()
        db = self._db
        if (snap.bits & BIT_PROTECTIVE_STOPPED or snap.mode == 3) and db is not None:
            while True:
                answer = db.ask("unlock protective stop")
                if answer.lower().startswith("protective stop releasing"):
                    log.info("%s: protective stop unlocked through the dashboard", self.device)
                    break
                if time.monotonic() > deadline:
                    raise SafetyStop(self.device, f"the protective stop could not be unlocked ({answer}); clear it "
                                                  f"on the teach pendant, then resume")
                log.info("%s: dashboard: %s; trying again", self.device, answer)
                time.sleep(0.25)
            db.ask("close safety popup")
        snap = self._wait_state(lambda s: self._safety_problem(s) is None, deadline, 1.0)
        problem = self._safety_problem(snap)
        if problem:
            raise SafetyStop(self.device, f"still stopped: {problem}")
        if snap.robot_mode != ROBOT_MODE_RUNNING and db is not None:
            if snap.robot_mode in (3, 4):
                log.warning("%s: powering the arm on (dashboard)", self.device)
                db.ask("power on")
                snap = self._wait_state(lambda s: s.robot_mode == 5, deadline, 10.0)
            if snap.robot_mode == 5:
                log.warning("%s: releasing the brakes (dashboard)", self.device)
                db.ask("brake release")
                snap = self._wait_state(lambda s: s.robot_mode == ROBOT_MODE_RUNNING, deadline, 10.0)
        self._check_running(snap)
        if not self._program_running():
            self._restart_program(deadline)

    def _wait_state(self, ok: Callable[[_Snapshot], bool], deadline: float, at_most_s: float) -> _Snapshot:
        end = min(deadline, time.monotonic() + at_most_s)
        snap = self._fresh()
        while not ok(snap) and time.monotonic() < end:
            time.sleep(0.02)
            snap = self._fresh()
        return snap

    # ------------------------------------------------------------------ motion

    def _validate(self, q: Any, speed: float, acceleration: float, timeout_s: float) -> np.ndarray:
        try:
            target = np.asarray(q, dtype=float)
        except (TypeError, ValueError):
            raise JointTargetError(f"{self.device}: the joint target must be 6 numbers in radians, got {q!r}") from None
        if target.shape != (6,) or not np.isfinite(target).all():
            raise JointTargetError(f"{self.device}: the joint target must be 6 finite numbers in radians, "
                                   f"got shape {target.shape} {np.ravel(target)[:8].tolist()}")
        if np.abs(target).max() > 2 * math.pi + 1e-9:
            raise JointTargetError(f"{self.device}: joint targets must lie in [-2pi, 2pi] rad, got {target.tolist()}")
        if not (0 < speed <= MAX_JOINT_SPEED):
            raise JointTargetError(f"{self.device}: joint speed must be in (0, {MAX_JOINT_SPEED}] rad/s, got {speed}")
        if not (0 < acceleration <= MAX_JOINT_ACCEL):
            raise JointTargetError(f"{self.device}: joint acceleration must be in (0, {MAX_JOINT_ACCEL}] rad/s^2, "
                                   f"got {acceleration}")
        if not (timeout_s > 0):
            raise JointTargetError(f"{self.device}: the move timeout must be positive, got {timeout_s}")
        return target

    def move_joints(self, q: np.ndarray, speed: float = 1.05, acceleration: float = 1.4,
                    timeout_s: float = 60.0) -> None:
        """moveJ to ``q`` (rad), run asynchronously on the controller and watched here; returns once
        the arm stands at ``q`` (within ``joint_tolerance_rad``, read from a fresh data package).
        SafetyStop on a protective/emergency stop or a safety-mode change (also during the move);
        HardwareError when the move times out (the arm is stopped, and that is confirmed), the arm
        did not arrive, the data stream froze, or the connection is lost for good."""
        target = self._validate(q, speed, acceleration, timeout_s)
        deadline = time.monotonic() + timeout_s
        self._ensure_connection()
        snap = self._fresh()
        problem = self._safety_problem(snap)
        if problem:
            raise SafetyStop(self.device, problem)
        self._check_running(snap)
        if not self._program_running():
            self._restart_program(min(deadline, time.monotonic() + 5.0))
        within = getattr(self._ctl, "isJointsWithinSafetyLimits", None)
        if within is not None and not self._call(lambda: within(target.tolist()), "isJointsWithinSafetyLimits"):
            if not self._program_running():
                raise HardwareError(self.device, "the control script stopped running on the controller (it answered "
                                                 "no command): check the teach pendant, then resume")
            raise HardwareError(self.device, f"the joint target {np.round(target, 4).tolist()} rad is outside the "
                                             f"robot's safety limits", retryable=False)
        reissued = False
        while True:
            outcome = self._run_move(target, speed, acceleration, deadline, timeout_s)
            if outcome == "done":
                break
            # outcome == "lost": the connection dropped during the move
            self._reconnect()
            self.check_safety()
            if reissued:
                raise HardwareError(self.device, "the RTDE connection dropped twice during one move")
            reissued = True
            log.warning("%s: re-issuing the move after reconnecting", self.device)
        self._check_arrived(target)

    def _async_op(self) -> tuple[int, bool]:
        st = self._call(self._ctl.getAsyncOperationProgressEx, "getAsyncOperationProgressEx")
        return int(st.operationId()), bool(st.isAsyncOperationRunning())

    def _run_move(self, target: np.ndarray, speed: float, acceleration: float, deadline: float,
                  timeout_s: float) -> str:
        """Start an asynchronous moveJ and watch it: returns "done" (the controller finished the
        operation and reports the joints still) or "lost" (connection dropped); raises otherwise."""
        ctl = self._ctl
        op0, _ = self._async_op()
        t_cmd = self._snapshot().ts
        ok = self._call(lambda: ctl.moveJ(target.tolist(), float(speed), float(acceleration), True), "moveJ")
        if not ok:
            snap = self._fresh()
            problem = self._safety_problem(snap)
            if problem:
                raise SafetyStop(self.device, f"{problem} (the controller refused the move)")
            if not snap.connected or not self._is_connected():
                return "lost"
            if not self._program_running():
                raise HardwareError(self.device, "the controller did not take the move: the control script is not "
                                                 "running; check the teach pendant, then resume")
            raise HardwareError(self.device, "the controller did not take the move (moveJ returned False): check the "
                                             "teach pendant, then resume")
        started = False
        while True:
            time.sleep(self.poll_s)
            snap = self._snapshot()
            if not snap.connected:
                return "lost"
            problem = self._safety_problem(snap)
            if problem:
                raise SafetyStop(self.device, f"{problem} (the controller stopped the arm during the move, at joints "
                                              f"{np.round(snap.q, 4).tolist()} rad)")
            if self._stale_for() > self.stale_s:
                raise HardwareError(self.device, f"{self._frozen_error('during a move ')}; {self._stop_words()}")
            if snap.runtime != RUNTIME_PLAYING:
                raise HardwareError(self.device, f"the control program stopped during the move (someone pressed stop "
                                                 f"on the teach pendant?); {self._stop_words()}")
            if time.monotonic() > deadline:
                raise HardwareError(self.device, f"the move did not finish within {timeout_s:g} s; "
                                                 f"{self._stop_words(target)}")
            op, running = self._async_op()
            started = started or op != op0
            if started and not running and snap.ts > t_cmd and snap.speed < MOVING_RAD_S:
                return "done"

    def _stop_and_confirm(self, extra_s: float = 1.0) -> tuple[bool, _Snapshot | None, float]:
        """stopJ at ``stop_deceleration``, then wait for fresh states until the joints stand still.
        Returns (stopped, last fresh snapshot or None, seconds it took)."""
        t0 = time.monotonic()
        before = None
        try:
            before = self._fresh()
        except HardwareError:
            pass
        v0 = before.speed if before is not None else MAX_JOINT_SPEED
        budget = v0 / self.stop_deceleration + extra_s
        ctl = self._ctl
        _best_effort(lambda: ctl.stopJ(self.stop_deceleration, False), budget + self.call_timeout_s, self.device,
                     "stopJ")
        snap = None
        end = t0 + budget + self.call_timeout_s
        while True:
            try:
                snap = self._fresh()
            except HardwareError:
                return False, snap, time.monotonic() - t0
            if snap.speed < MOVING_RAD_S:
                return True, snap, time.monotonic() - t0
            if time.monotonic() > end:
                return False, snap, time.monotonic() - t0
            time.sleep(self.poll_s)

    def _stop_words(self, target: np.ndarray | None = None) -> str:
        """Stop the arm and say what it did."""
        stopped, snap, took = self._stop_and_confirm()
        dec = f"stopJ at {self.stop_deceleration:g} rad/s^2"
        if stopped and snap is not None:
            where = f"it stands still at joints {np.round(snap.q, 4).tolist()} rad"
            if target is not None:
                where += f", {float(np.abs(snap.q - target).max()):.3f} rad from the target"
            return f"the arm was stopped ({dec}, {took:.2f} s): {where}"
        if snap is None:
            return (f"the arm was told to stop ({dec}) but the controller sends no state to confirm it: "
                    f"check that the arm stands still, press the emergency stop if not")
        return (f"the arm was told to stop ({dec}) but still moves at {snap.speed:.3f} rad/s after {took:.2f} s: "
                f"press the emergency stop")

    def _check_arrived(self, target: np.ndarray) -> None:
        settle = time.monotonic() + self.settle_timeout_s
        while True:
            snap = self._fresh()
            actual = snap.q
            err = np.abs(actual - target) if actual.shape == (6,) else np.full(6, np.inf)
            if err.max() <= self.joint_tolerance_rad:
                return
            if time.monotonic() > settle:
                j = int(np.argmax(err))
                raise HardwareError(self.device, f"the arm did not arrive: joint {j + 1} is {err[j]:.4f} rad from "
                                                 f"the target (tolerance {self.joint_tolerance_rad:g} rad)")
            time.sleep(self.poll_s)


def tcp_pose_to_T(pose: Any) -> np.ndarray:
    """ur_rtde TCP pose (x, y, z in metres, rx, ry, rz rotation vector) -> (4,4) transform in mm."""
    pose = np.asarray(pose, dtype=float).reshape(6)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:]).as_matrix()
    T[:3, 3] = 1000.0 * pose[:3]
    return T


def T_to_tcp_pose(T: np.ndarray) -> list[float]:
    """(4,4) transform in mm -> ur_rtde TCP pose (metres + rotation vector)."""
    T = np.asarray(T, dtype=float)
    return [*(T[:3, 3] / 1000.0).tolist(), *Rotation.from_matrix(T[:3, :3]).as_rotvec().tolist()]


def _best_effort(fn: Callable[[], Any], timeout_s: float, device: str, what: str) -> None:
    try:
        call_with_timeout(fn, timeout_s, device, what)
    except BaseException as e:  # noqa: BLE001 - best effort by contract
        log.debug("%s: %s failed (ignored): %s", device, what, e)


def main(argv: list[str] | None = None) -> int:
    """Manual smoke test on the real robot: connect, print the state, optionally move a little."""
    import argparse

    ap = argparse.ArgumentParser(description="UR5 / ur_rtde smoke test")
    ap.add_argument("--host", required=True, help="robot IP address")
    ap.add_argument("--move", type=float, default=0.0, metavar="RAD",
                    help="move the last joint by this many radians and back (0 = no motion; keep it small)")
    ap.add_argument("--speed", type=float, default=0.2, help="joint speed, rad/s")
    ap.add_argument("--acceleration", type=float, default=0.5, help="joint acceleration, rad/s^2")
    ap.add_argument("--timeout", type=float, default=30.0, help="move timeout, s")
    ap.add_argument("--connect-timeout", type=float, default=5.0, help="connect timeout, s")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    np.set_printoptions(precision=4, suppress=True)
    robot = URRobot(args.host, connect_timeout_s=args.connect_timeout)
    try:
        robot.connect()
        st = robot.state()
        print("q (rad):", st.q)
        print("q (deg):", np.degrees(st.q))
        print("T_base_tcp (mm):\n", st.T_base_tcp)
        if abs(args.move) > 0:
            if abs(args.move) > 0.5:
                print("refusing to move more than 0.5 rad in a smoke test")
                return 2
            q0 = st.q.copy()
            q1 = q0.copy()
            q1[5] += args.move
            t0 = time.monotonic()
            robot.move_joints(q1, args.speed, args.acceleration, args.timeout)
            print(f"moved joint 6 by {args.move:+g} rad in {time.monotonic() - t0:.2f} s:", robot.state().q)
            robot.move_joints(q0, args.speed, args.acceleration, args.timeout)
            print("back at:", robot.state().q)
        return 0
    except (HardwareError, TdofError) as e:
        print(f"error: {e}")
        return 1
    except KeyboardInterrupt:
        robot.stop()
        print("interrupted: stopped the arm")
        return 130
    finally:
        robot.close()


if __name__ == "__main__":
    raise SystemExit(main())
