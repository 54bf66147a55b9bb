"""Fakes of ur_rtde's ``RTDEControlInterface`` / ``RTDEReceiveInterface`` for tests.

Both fakes have the library's constructor signature and method names and share one
:class:`FakeURController` (the simulated controller: joints, TCP pose from ``ur5_fk`` in metres +
rotation vector, safety mode, protective/emergency stop flags, connection flag). Inject them as::

    ctl = FakeURController(protective_stop_during_move=True)
    robot = URRobot("10.0.0.5", control_factory=ctl.control, receive_factory=ctl.receive)

Knobs (constructor keywords of FakeURController):
  hang_on_connect          True / "receive" / "control": that constructor blocks forever (on an
                           Event nobody sets; the waiting thread is the caller's daemon thread)
  refuse_connect           the constructors raise RuntimeError (nothing listens)
  protective_stop_during_move / emergency_stop_during_move
                           halfway through the next move the robot stops; moveJ returns False
  moveJ_returns_false      moveJ refuses (returns False) without moving
  drop_connection_once     halfway through the first move the connection drops (moveJ raises
                           RuntimeError); reconnect() succeeds
  drop_connection_for_good the same, and reconnect() always fails
  arrive_offset            (6,) rad added to where the arm ends up (it "does not arrive")
  motion_time_s            how long a move takes
  raise_on_stop            stopJ / stopScript / disconnect raise RuntimeError
Initial state: q0, safety_mode, protective_stopped, emergency_stopped, robot_mode.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation

from tdof20.sim.rig import UR5_HOME, ur5_fk

FLAG_UPLOAD_SCRIPT = 1


class FakeURController:
    """The simulated UR controller shared by the fake interfaces."""

    def __init__(self, q0=UR5_HOME, *, hang_on_connect=False, refuse_connect=False,
                 protective_stop_during_move=False, emergency_stop_during_move=False,
                 moveJ_returns_false=False, drop_connection_once=False, drop_connection_for_good=False,
                 arrive_offset=None, motion_time_s=0.05, raise_on_stop=False,
                 safety_mode=1, protective_stopped=False, emergency_stopped=False, robot_mode=7):
        self.lock = threading.RLock()
        self.q = np.array(q0, dtype=float)
        self.safety_mode = int(safety_mode)
        self.protective_stopped = bool(protective_stopped or safety_mode == 3)
        self.emergency_stopped = bool(emergency_stopped or safety_mode in (6, 7))
        self.robot_mode = int(robot_mode)
        self.connected = True
        self.reconnect_ok = True
        self.hang_on_connect = hang_on_connect
        self.refuse_connect = refuse_connect
        self.protective_stop_during_move = protective_stop_during_move
        self.emergency_stop_during_move = emergency_stop_during_move
        self.moveJ_returns_false = moveJ_returns_false
        self.drop_connection_once = drop_connection_once
        self.drop_connection_for_good = drop_connection_for_good
        self.arrive_offset = np.zeros(6) if arrive_offset is None else np.asarray(arrive_offset, dtype=float)
        self.motion_time_s = float(motion_time_s)
        self.raise_on_stop = raise_on_stop
        self.tcp_offset = [0.0] * 6
        # what the fakes saw
        self.constructed: list[tuple[str, str, float]] = []   # (which, hostname, frequency)
        self.moveJ_calls: list[tuple[list, float, float, bool]] = []
        self.calls: list[str] = []
        self.reconnects = 0
        self.stops = 0
        self.t0 = time.monotonic()
        self.frozen = False               # the timestamp stands still (a frozen data stream)
        self.program_running = not (self.protective_stopped or self.emergency_stopped)
        self.op_id = 0
        self.op_running = False
        self.qd = np.zeros(6)
        self.reuploads = 0
        self._never = threading.Event()   # never set while a test runs: a constructor that hangs
        self._stop_motion = threading.Event()
        self._dropped = False

    # factories with the library's constructor signatures
    def control(self, hostname, frequency=-1.0, flags=FLAG_UPLOAD_SCRIPT, ur_cap_port=50002, rt_priority=0):
        return FakeRTDEControl(hostname, frequency, flags, ur_cap_port, rt_priority, controller=self)

    def receive(self, hostname, frequency=-1.0, variables=(), verbose=False, use_upper_range_registers=False,
                rt_priority=0):
        return FakeRTDEReceive(hostname, frequency, list(variables), verbose, use_upper_range_registers,
                               rt_priority, controller=self)

    def release(self) -> None:
        """Let hanging constructors return (test teardown)."""
        self._never.set()

    # simulated controller
    def _construct(self, which: str, hostname: str, frequency: float) -> None:
        if self.hang_on_connect is True or self.hang_on_connect == which:
            self._never.wait()
        if self.refuse_connect:
            raise RuntimeError("connect: Connection refused")
        self.constructed.append((which, hostname, frequency))

    def tcp_pose(self) -> list[float]:
        with self.lock:
            T = ur5_fk(self.q)
        return [*(T[:3, 3] / 1000.0).tolist(), *Rotation.from_matrix(T[:3, :3]).as_rotvec().tolist()]

    def timestamp(self) -> float:
        """Controller time: advances in 8 ms packages unless frozen."""
        if self.frozen:
            return getattr(self, "_frozen_at", 0.0)
        self._frozen_at = round((time.monotonic() - self.t0) / 0.008) * 0.008
        return self._frozen_at

    def safety_status_bits(self) -> int:
        bits = 1 if self.safety_mode == 1 else (2 if self.safety_mode == 2 else 0)
        if self.protective_stopped:
            bits |= 1 << 2
        if self.emergency_stopped:
            bits |= (1 << 6) | (1 << 7)
        return bits

    def trigger_protective_stop(self) -> None:
        with self.lock:
            self.protective_stopped = True
            self.safety_mode = 3
            self.program_running = False
            self._stop_motion.set()

    def trigger_emergency_stop(self) -> None:
        with self.lock:
            self.emergency_stopped = True
            self.safety_mode = 7
            self.robot_mode = 3
            self.program_running = False
            self._stop_motion.set()

    def drop(self, for_good: bool = False) -> None:
        with self.lock:
            self.connected = False
            if for_good:
                self.reconnect_ok = False

    def reconnect(self) -> bool:
        time.sleep(0.01)
        with self.lock:
            self.reconnects += 1
            if self.reconnect_ok:
                self.connected = True
            return self.connected

    def move(self, q, speed, acceleration, asynchronous) -> bool:
        with self.lock:
            self.moveJ_calls.append((list(q), speed, acceleration, asynchronous))
            if not self.connected or self.protective_stopped or self.emergency_stopped or not self.program_running:
                return False
            if self.moveJ_returns_false:
                return False
            self._stop_motion.clear()
        if not asynchronous:
            return self._motion(q)
        with self.lock:
            self.op_id = (self.op_id + 1) % 128
            self.op_running = True

        def run():
            try:
                self._motion(q)
            except RuntimeError:
                pass
            finally:
                with self.lock:
                    self.op_running = False
                    self.qd = np.zeros(6)

        threading.Thread(target=run, daemon=True).start()
        return True

    def _motion(self, q) -> bool:
        with self.lock:
            q0 = self.q.copy()
        target = np.asarray(q, dtype=float)
        self.qd = (target - q0) / self.motion_time_s
        n = max(2, int(self.motion_time_s / 0.005))
        for i in range(1, n + 1):
            if self._stop_motion.wait(self.motion_time_s / n):
                self.qd = np.zeros(6)
                return False
            with self.lock:
                self.q = q0 + (target - q0) * (i / n)
                if i == n // 2:
                    if self.protective_stop_during_move:
                        self.protective_stop_during_move = False
                        self.trigger_protective_stop()
                        return False
                    if self.emergency_stop_during_move:
                        self.emergency_stop_during_move = False
                        self.trigger_emergency_stop()
                        return False
                    if self.drop_connection_for_good:
                        self.drop(for_good=True)
                        raise RuntimeError("ur_rtde: lost the connection to the controller")
                    if self.drop_connection_once and not self._dropped:
                        self._dropped = True
                        self.drop()
                        raise RuntimeError("ur_rtde: lost the connection to the controller")
        with self.lock:
            self.q = target + self.arrive_offset
            self.qd = np.zeros(6)
        return True


class _FakeInterface:
    which = "?"

    def __init__(self, hostname: str, frequency: float, controller: FakeURController):
        self._c = controller
        self._closed = False
        controller._construct(self.which, hostname, frequency)
        self.hostname = hostname
        self.frequency = frequency

    def _log(self, name: str) -> None:
        self._c.calls.append(f"{self.which}.{name}")

    def isConnected(self) -> bool:
        return self._c.connected and not self._closed

    def reconnect(self) -> bool:
        self._log("reconnect")
        ok = self._c.reconnect()
        if ok:
            self._closed = False
        return ok

    def disconnect(self) -> None:
        self._log("disconnect")
        if self._c.raise_on_stop:
            raise RuntimeError("fake: disconnect failed")
        self._closed = True


class FakeRTDEControl(_FakeInterface):
    """Fake ``rtde_control.RTDEControlInterface``."""

    which = "control"

    def __init__(self, hostname, frequency=-1.0, flags=FLAG_UPLOAD_SCRIPT, ur_cap_port=50002, rt_priority=0, *,
                 controller: FakeURController):
        super().__init__(hostname, frequency, controller)

    def moveJ(self, q, speed=1.05, acceleration=1.4, asynchronous=False) -> bool:
        self._log("moveJ")
        if self._closed:
            raise RuntimeError("RTDE control script is not running!")
        return self._c.move(q, speed, acceleration, asynchronous)

    def stopJ(self, a=2.0, asynchronous=False) -> None:
        self._log("stopJ")
        self._c.stops += 1
        if self._c.raise_on_stop:
            raise RuntimeError("fake: stopJ failed")
        self._c._stop_motion.set()
        time.sleep(0.01)

    def stopScript(self) -> None:
        self._log("stopScript")
        if self._c.raise_on_stop:
            raise RuntimeError("fake: stopScript failed")

    def isSteady(self) -> bool:
        return True

    def isProgramRunning(self) -> bool:
        return self._c.connected and self._c.program_running

    def reuploadScript(self) -> bool:
        self._log("reuploadScript")
        c = self._c
        c.reuploads += 1
        c.program_running = c.safety_mode in (1, 2) and c.robot_mode == 7
        return True

    def isJointsWithinSafetyLimits(self, q) -> bool:
        return len(q) == 6 and all(abs(v) <= 2 * np.pi for v in q)

    def getTCPOffset(self) -> list[float]:
        return list(self._c.tcp_offset)

    def getAsyncOperationProgress(self) -> int:
        return 0 if self._c.op_running else -1

    def getAsyncOperationProgressEx(self) -> "FakeAsyncStatus":
        return FakeAsyncStatus(self._c.op_id, self._c.op_running)


class FakeAsyncStatus:
    """Fake ``rtde_control.AsyncOperationStatus``."""

    def __init__(self, op_id: int, running: bool):
        self._id, self._running = op_id, running

    def operationId(self) -> int:
        return self._id

    def isAsyncOperationRunning(self) -> bool:
        return self._running


class FakeRTDEReceive(_FakeInterface):
    """Fake ``rtde_receive.RTDEReceiveInterface``."""

    which = "receive"

    def __init__(self, hostname, frequency=-1.0, variables=(), verbose=False, use_upper_range_registers=False,
                 rt_priority=0, *, controller: FakeURController):
        super().__init__(hostname, frequency, controller)

    def getTimestamp(self) -> float:
        return self._c.timestamp()

    def getActualQ(self) -> list[float]:
        with self._c.lock:
            return self._c.q.tolist()

    def getActualQd(self) -> list[float]:
        with self._c.lock:
            return self._c.qd.tolist()

    def getSafetyStatusBits(self) -> int:
        return self._c.safety_status_bits()

    def getRuntimeState(self) -> int:
        return 2 if self._c.program_running else 1

    def getActualTCPPose(self) -> list[float]:
        return self._c.tcp_pose()

    def isProtectiveStopped(self) -> bool:
        return self._c.protective_stopped

    def isEmergencyStopped(self) -> bool:
        return self._c.emergency_stopped

    def getSafetyMode(self) -> int:
        return self._c.safety_mode

    def getRobotMode(self) -> int:
        return self._c.robot_mode
