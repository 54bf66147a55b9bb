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


class URRobot(Robot):
    """A UR5 (CB3 or e-Series) driven through ur_rtde.

    ``control_factory`` / ``receive_factory`` default to ``rtde_control.RTDEControlInterface`` and
    ``rtde_receive.RTDEReceiveInterface`` and are called as ``factory(host, frequency)``; tests
    inject fakes with the library's method names. ``preflight`` (default: only with the real
    library) runs :func:`probe_rtde` before constructing the interfaces.
    """

    name = "ur5"

    def __init__(self, host: str, connect_timeout_s: float = 5.0, frequency: float = 125.0,
                 control_factory: Callable[..., Any] | None = None,
                 receive_factory: Callable[..., Any] | None = None,
                 reconnect_attempts: int = 2, *,
                 joint_tolerance_rad: float = 0.002,
                 call_timeout_s: float = 2.0,
                 settle_timeout_s: float = 0.5,
                 poll_s: float = 0.02,
                 preflight: bool | None = None,
                 rtde_port: int = RTDE_PORT):
        self.host = str(host)
        self.device = f"UR5 at {self.host}"
        self.connect_timeout_s = float(connect_timeout_s)
        self.frequency = float(frequency)
        self.reconnect_attempts = int(reconnect_attempts)
        self.joint_tolerance_rad = float(joint_tolerance_rad)
        self.call_timeout_s = float(call_timeout_s)
        self.settle_timeout_s = float(settle_timeout_s)
        self.poll_s = float(poll_s)
        self.rtde_port = int(rtde_port)
        self._control_factory = control_factory
        self._receive_factory = receive_factory
        self._preflight = (control_factory is None and receive_factory is None) if preflight is None else bool(preflight)
        self._ctl: Any = None
        self._rcv: Any = None
        self._last_mode: int | None = None

    # ------------------------------------------------------------------ connection

    def _factories(self) -> tuple[Callable[..., Any], Callable[..., Any]]:
        ctl_f, rcv_f = self._control_factory, self._receive_factory
        if ctl_f is None:
            try:
                import rtde_control
            except ImportError as e:
                raise HardwareError(self.device, "the ur_rtde package is not installed (pip install ur-rtde)",
                                    retryable=False) from e
            ctl_f = rtde_control.RTDEControlInterface
        if rcv_f is None:
            try:
                import rtde_receive
            except ImportError as e:
                raise HardwareError(self.device, "the ur_rtde package is not installed (pip install ur-rtde)",
                                    retryable=False) from e
            rcv_f = rtde_receive.RTDEReceiveInterface
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

    def connect(self) -> None:
        """Open the receive then the control interface within ``connect_timeout_s`` in all, then
        check the safety state (SafetyStop if the robot is stopped)."""
        if self._ctl is not None and self._rcv is not None:
            self.check_safety()
            return
        ctl_f, rcv_f = self._factories()
        deadline = time.monotonic() + self.connect_timeout_s
        if self._preflight:
            probe_rtde(self.host, self.connect_timeout_s, self.rtde_port, self.device)
        rcv = self._construct(rcv_f, deadline - time.monotonic(), "receive")
        try:
            ctl = self._construct(ctl_f, deadline - time.monotonic(), "control")
        except BaseException:
            _best_effort(lambda: rcv.disconnect(), 1.0, self.device, "disconnect")
            raise
        self._rcv, self._ctl = rcv, ctl
        self._last_mode = None
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
        ctl, rcv = self._ctl, self._rcv
        self._ctl = self._rcv = None
        if ctl is not None:
            _best_effort(lambda: ctl.stopScript(), 2.0, self.device, "stopScript")
            _best_effort(lambda: ctl.disconnect(), 2.0, self.device, "disconnect control")
        if rcv is not None:
            _best_effort(lambda: rcv.disconnect(), 2.0, self.device, "disconnect receive")

    def stop(self) -> None:
        """Decelerate the joints to zero (stopJ 2 rad/s^2); best effort, never raises."""
        ctl = self._ctl
        if ctl is not None:
            _best_effort(lambda: ctl.stopJ(2.0), 2.0, self.device, "stopJ")

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
                    return
            except HardwareError as e:
                last = str(e)
            time.sleep(min(0.2 * attempt, 1.0))
        raise HardwareError(self.device, f"lost the RTDE connection to {self.host} and could not reconnect after "
                                         f"{self.reconnect_attempts} attempt(s) ({last}); check the network cable "
                                         f"and that the robot is on and in remote control mode")

    # ------------------------------------------------------------------ state and safety

    def state(self) -> RobotState:
        """Actual joints (rad) and T_base_tcp (4,4, mm) from the controller."""
        self._ensure_connection()
        rcv = self._rcv
        q = np.asarray(self._call(rcv.getActualQ, "getActualQ"), dtype=float)
        pose = np.asarray(self._call(rcv.getActualTCPPose, "getActualTCPPose"), dtype=float)
        if q.shape != (6,) or pose.shape != (6,) or not (np.isfinite(q).all() and np.isfinite(pose).all()):
            raise HardwareError(self.device, f"the controller sent an invalid state (q {q.tolist()}, "
                                             f"TCP pose {pose.tolist()})")
        return RobotState(q=q, T_base_tcp=tcp_pose_to_T(pose))

    def _safety_snapshot(self) -> tuple[bool, bool, int, bool]:
        """(emergency stopped, protective stopped, safety mode, connected) in one guarded call."""
        rcv = self._rcv

        def read() -> tuple[bool, bool, int, bool]:
            return (bool(rcv.isEmergencyStopped()), bool(rcv.isProtectiveStopped()), int(rcv.getSafetyMode()),
                    bool(rcv.isConnected()))

        return self._call(read, "reading the safety state")

    def _safety_problem(self, snap: tuple[bool, bool, int, bool]) -> str | None:
        estop, pstop, mode, _ = snap
        if mode != self._last_mode:
            if mode == SAFETY_REDUCED:
                log.warning("%s: the robot is in reduced mode (slower, limited motion)", self.device)
            elif self._last_mode is not None:
                log.info("%s: safety mode %s -> %s", self.device, self._last_mode, mode)
            self._last_mode = mode
        if estop:
            return SAFETY_MODES[7] if mode not in (6, 7) else safety_mode_text(mode)
        if pstop:
            return SAFETY_MODES[3]
        if mode not in (SAFETY_NORMAL, SAFETY_REDUCED):
            return safety_mode_text(mode)
        return None

    def check_safety(self) -> None:
        """SafetyStop (a message saying what to do) unless the safety mode is normal or reduced."""
        self._require()
        problem = self._safety_problem(self._safety_snapshot())
        if problem:
            raise SafetyStop(self.device, problem)

    def _check_running(self) -> None:
        mode = int(self._call(self._rcv.getRobotMode, "getRobotMode"))
        if mode != ROBOT_MODE_RUNNING:
            raise HardwareError(self.device, f"the arm is not ready to move (robot mode: "
                                             f"{ROBOT_MODES.get(mode, mode)}); power it on and release the "
                                             f"brakes on the teach pendant", retryable=False)

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
        """Blocking moveJ to ``q`` (rad); returns once the arm stands at ``q`` (within
        ``joint_tolerance_rad``). SafetyStop on a protective/emergency stop or a safety-mode change
        (also during the move, or when the controller refuses the move); HardwareError when the move
        times out, the arm did not arrive, or the connection is lost for good."""
        target = self._validate(q, speed, acceleration, timeout_s)
        deadline = time.monotonic() + timeout_s
        self._ensure_connection()
        self.check_safety()
        self._check_running()
        within = getattr(self._ctl, "isJointsWithinSafetyLimits", None)
        if within is not None and not self._call(lambda: within(target.tolist()), "isJointsWithinSafetyLimits"):
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
        self._ensure_connection()  # the read-back below must come from a live connection
        self.check_safety()
        self._check_arrived(target)

    def _run_move(self, target: np.ndarray, speed: float, acceleration: float, deadline: float,
                  timeout_s: float) -> str:
        """Run the blocking moveJ in a worker thread and watch safety + deadline here.
        Returns "done" or "lost" (connection dropped); raises otherwise."""
        ctl = self._ctl
        box: dict = {}
        done = threading.Event()

        def worker() -> None:
            try:
                box["value"] = ctl.moveJ(target.tolist(), float(speed), float(acceleration))
            except BaseException as e:  # noqa: BLE001 - handed to the caller
                box["error"] = e
            finally:
                done.set()

        threading.Thread(target=worker, name=f"{self.device}:moveJ", daemon=True).start()
        while not done.wait(self.poll_s):
            if time.monotonic() > deadline:
                self.stop()
                raise HardwareError(self.device, f"the move did not finish within {timeout_s:g} s; the arm was "
                                                 f"told to stop")
            snap = self._safety_snapshot()
            problem = self._safety_problem(snap)
            if problem:
                self.stop()
                raise SafetyStop(self.device, f"{problem} (the robot stopped during a move)")
            if not snap[3]:
                # connection dropped: give the library a moment to return from moveJ
                if not done.wait(min(1.0, max(deadline - time.monotonic(), 0.0))):
                    raise HardwareError(self.device, "lost the RTDE connection during a move and moveJ did not "
                                                     "return; check the network and the robot")
                break
        # moveJ returned (or raised)
        if "error" not in box and box.get("value", False):
            return "done"
        snap = self._safety_snapshot()
        problem = self._safety_problem(snap)
        if problem:
            raise SafetyStop(self.device, f"{problem} (the robot stopped during a move)")
        if not snap[3] or not self._is_connected():
            return "lost"
        if "error" in box:
            err = box["error"]
            raise HardwareError(self.device, f"moveJ failed: {type(err).__name__}: {err}") from err
        raise SafetyStop(self.device, "the controller did not complete the move (moveJ returned False): is the "
                                      "target within the joint and safety limits, and is the robot program still "
                                      "running? check the teach pendant, then resume")

    def _check_arrived(self, target: np.ndarray) -> None:
        rcv = self._rcv
        settle = time.monotonic() + self.settle_timeout_s
        while True:
            actual = np.asarray(self._call(rcv.getActualQ, "getActualQ"), dtype=float)
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
