"""A UR5 controller emulated at the protocol level on 127.0.0.1, for tests of the real ur_rtde library.

The real ``rtde_control`` / ``rtde_receive`` 1.6.5 talk to it over sockets exactly as to a robot:

* **RTDE** (port 30004): protocol version 2 (``V``), controller version (``v``: a CB3 on
  PolyScope 3.15), output recipes (``O``: a frequency and variable names, answered with a recipe id
  and the types; an unknown name is ``NOT_FOUND``), input recipes (``I``), start / pause (``S`` /
  ``P``), data packages (``U``) both ways: the controller sends every started client a package at
  125 Hz (``timestamp``, ``actual_q``, ``actual_qd``, ``actual_TCP_pose``, ``robot_mode``,
  ``safety_mode``, ``safety_status_bits``, ``runtime_state``, the output registers, ...); a
  client's packages write the input registers of its recipe.
* **the script port** (30003): receives ur_rtde's uploaded control script. The emulator checks that
  the text holds the register protocol it implements (below) and then "runs" it, in Python: each
  controller cycle is one ``sync()`` of the script's main loop; motions run in emulated script
  threads (``move_thread``, ``stop_thread``) as in the script.
* **the dashboard server** (29999): ``PolyscopeVersion``, ``robotmode``, ``safetymode``,
  ``safetystatus``, ``programState``, ``running``, ``power on``/``power off``, ``brake release``,
  ``unlock protective stop`` (refused for 5 s after the stop, as PolyScope does), ``close safety
  popup``, ``close popup``, ``stop``, ``get robot model``, ``is in remote control`` (an e-Series
  command: a CB3 does not understand it), ``quit``.

ur_rtde's register protocol (from the script it uploads, ``rtde_control.script`` in the ur_rtde
sources): the command id is in ``input_int_register_0`` and its arguments in
``input_double_register_0..7`` (and ``input_int_register_1`` for ``async``); the script's state is in
``output_int_register_0``: 1 = ready for a command (``signal_ready``), 2 = done with it
(``signal_done_with_cmd``); the client then clears the command (id 0) and the script answers ready
again. Query results come back in ``output_int_register_1`` / ``output_double_register_0..5``; the
progress of an asynchronous move in ``output_int_register_2`` (bit 15 running, bits 16-22 a write
counter, bits 24-30 the operation id). Commands served: 0 (none), 1 moveJ (sync/async), 31 protective
stop, 33/34 stopL/stopJ (sync/async), 36/37 pose/joints within safety limits, 40 TCP offset, 43/44
forward kinematics, 47 isSteady, 255 stop script; any other id is acknowledged without effect and
recorded in ``unsupported``.

The arm: standard UR5 DH kinematics; moveJ moves every joint on one straight line in joint space
with a trapezoidal profile of the leading axis (the speed and acceleration the client gave);
stopJ decelerates at its rate. Faults to inject: :meth:`protective_stop`, :meth:`emergency_stop`
(and :meth:`release_emergency_stop`), :meth:`drop` (every connection reset, the controller up),
:meth:`freeze` (no more data packages, sockets open), :attr:`stalled` (the joints do not move),
``robot_mode=`` POWER_OFF / IDLE (brakes on) and ``silent=True`` (accepts, never answers).

ur_rtde binds fixed ports, so one emulator at a time per machine: tests using it live in one file
(run by one xdist worker with ``--dist loadfile``), on 127.0.0.1 only.
"""

from __future__ import annotations

import json
import math
import re
import socket
import struct
import threading
import time
from typing import Callable, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

HOST = "127.0.0.1"
RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
PERIOD = 1.0 / 125.0           # a CB3 controller cycle

# UR5 standard DH (metres, radians)
DH_D = (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823)
DH_A = (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)

# robot modes, safety modes, runtime states (RTDE)
POWER_OFF, IDLE, RUNNING = 3, 5, 7
ROBOT_MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
                    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING"}
NORMAL, PROTECTIVE_STOP, ROBOT_EMERGENCY_STOP = 1, 3, 7
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                     6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}
STOPPED, PLAYING = 1, 2
UNLOCK_DELAY_S = 5.0           # PolyScope refuses to unlock a protective stop sooner

# the RTDE types of the variables ur_rtde knows (robot_state.cpp), as the controller names them
_V6 = ("target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_qdd actual_current "
       "actual_moment joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose "
       "target_TCP_speed joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia "
       "external_force_torque").split()
_DOUBLE = ("timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
           "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
           "standard_analog_output0 standard_analog_output1 payload").split()
TYPES: dict[str, str] = {n: "VECTOR6D" for n in _V6}
TYPES.update({n: "DOUBLE" for n in _DOUBLE})
TYPES.update({n: "VECTOR3D" for n in ("actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity")})
TYPES.update({n: "UINT64" for n in ("actual_digital_input_bits", "actual_digital_output_bits")})
TYPES.update({n: "UINT32" for n in ("runtime_state", "robot_status_bits", "safety_status_bits",
                                    "output_bit_registers0_to_31", "output_bit_registers32_to_63")})
TYPES.update({"robot_mode": "INT32", "safety_mode": "INT32", "joint_mode": "VECTOR6INT32"})
for _i in range(48):
    TYPES[f"output_int_register_{_i}"] = TYPES[f"input_int_register_{_i}"] = "INT32"
    TYPES[f"output_double_register_{_i}"] = TYPES[f"input_double_register_{_i}"] = "DOUBLE"
FORMATS = {"DOUBLE": "d", "UINT32": "I", "INT32": "i", "UINT64": "Q", "VECTOR6D": "6d", "VECTOR3D": "3d",
           "VECTOR6INT32": "6i", "UINT8": "B", "BOOL": "?"}
INPUT_NAMES = {n for n in TYPES if n.startswith("input_")} | {"external_force_torque"}

#: what the uploaded control script must contain for this emulation to be faithful to it
SCRIPT_PROTOCOL = (
    "def signal_ready():\n        write_output_integer_reg(0, 1)",
    "def signal_done_with_cmd():\n        write_output_integer_reg(0, 2)",
    "def rtde_cmd():\n      cmd = read_input_integer_reg(0)",
    "global reg_offset_int = # int register offset\n0",    # ur_rtde injects the offset 0 after the comment
    "if cmd == 1:",
    "q = q_from_input_float_registers(0)",
    "velocity = read_input_float_reg(6)",
    "acceleration = read_input_float_reg(7)",
    "async = read_input_integer_reg(1)",
    "move_thrd = run move_thread()",
    "movej(q, a=acceleration, v=velocity)",
    "elif cmd == 34:",
    "exec_stopl_stopj(cmd,",
    "deceleration_rate = read_input_float_reg(0)",
    "elif cmd == 37:",
    "elif cmd == 255:",
    "write_output_integer_reg(2, reg_value)",
    "if cmd == 0:\n                    executing_cmd = False\n                    signal_ready()",
)
_END = re.compile(r"\nend[ \t]*\n")
DEFAULT_Q0 = (0.0, -1.2, 1.4, -1.77, -1.5708, 0.0)
REALTIME_CMDS = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}


def ur5_fk_pose(q) -> list[float]:
    """UR5 DH forward kinematics -> ur_rtde's TCP pose (metres, rotation vector)."""
    T = np.eye(4)
    for th, d, a, al in zip(np.asarray(q, float), DH_D, DH_A, DH_ALPHA):
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]])
    return [*T[:3, 3].tolist(), *Rotation.from_matrix(T[:3, :3]).as_rotvec().tolist()]


class _Motion:
    """One joint-space motion: a straight line from ``q0`` to ``target`` along which the leading
    axis moves with a trapezoidal profile; or a stop (decelerate along the current line)."""

    def __init__(self, q0: np.ndarray, target: np.ndarray, v: float, a: float, s0: float = 0.0,
                 direction: np.ndarray | None = None):
        self.q0 = q0.copy()
        self.target = target.copy()
        delta = target - q0
        self.length = float(np.abs(delta).max())
        self.u = delta / self.length if self.length > 0 else (np.zeros(6) if direction is None else direction)
        self.v, self.a = float(v), float(a)
        self.p = 0.0                  # leading-axis distance covered
        self.s = float(s0)            # leading-axis speed
        self.stopping = False
        self.done = self.length == 0

    def stop(self, dec: float) -> None:
        self.stopping = True
        self.a = float(dec)

    def step(self, dt: float) -> None:
        n = max(1, int(round(dt / 0.0005)))
        h = dt / n
        for _ in range(n):
            if self.done:
                return
            if self.stopping:
                self.s = max(self.s - self.a * h, 0.0)
                self.p += self.s * h
                if self.s <= 0.0:
                    self.done = True
            else:
                left = self.length - self.p
                if self.s * self.s / (2 * self.a) >= left:
                    self.s = max(self.s - self.a * h, 0.5 * self.a * h)
                else:
                    self.s = min(self.s + self.a * h, self.v)
                self.p += self.s * h
            if not self.stopping and self.p >= self.length:
                self.p, self.s, self.done = self.length, 0.0, True

    @property
    def q(self) -> np.ndarray:
        if self.done and not self.stopping:
            return self.target.copy()
        return self.q0 + self.u * self.p

    @property
    def qd(self) -> np.ndarray:
        return self.u * self.s


class _Conn:
    """One client connection: its socket and a lock for writes from two threads."""

    def __init__(self, sock: socket.socket, kind: str):
        self.sock = sock
        self.kind = kind
        self.lock = threading.Lock()
        self.closed = False
        self.out_recipe: tuple[int, list[str], float] | None = None
        self.in_recipes: dict[int, list[str]] = {}
        self.started = False
        self.next_period = 0.0

    def send(self, data: bytes) -> None:
        with self.lock:
            if not self.closed:
                try:
                    self.sock.sendall(data)
                except OSError:
                    self.close()

    def close(self) -> None:
        self.closed = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        try:
            self.sock.close()
        except OSError:
            pass


class URControllerEmulator:
    """A UR5 (CB3, PolyScope 3.15.7) on 127.0.0.1: start(), then connect ur_rtde to 127.0.0.1."""

    def __init__(self, q0=None, *, robot_mode: int = RUNNING, safety_mode: int = NORMAL, silent: bool = False,
                 version: tuple[int, int, int, int] = (3, 15, 7, 106331), host: str = HOST,
                 unlock_delay_s: float = UNLOCK_DELAY_S):
        self.host = host
        self.version = tuple(version)
        self.unlock_delay_s = float(unlock_delay_s)
        self.lock = threading.RLock()
        self.q = np.array(DEFAULT_Q0 if q0 is None else q0, dtype=float)
        self.qd = np.zeros(6)
        self.robot_mode = int(robot_mode)
        self.safety_mode = int(safety_mode)
        self.silent = bool(silent)
        self.stalled = False
        self.frozen = False
        self.refusing = False          # new connections are reset at once (the network is down)
        self.tcp_offset = [0.0] * 6
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.runtime_state = STOPPED
        self.timestamp = 0.0
        self.stop_time: float | None = None       # controller time of the last protective stop
        self.estop_pressed = self.safety_mode == ROBOT_EMERGENCY_STOP
        # what the emulator saw (for tests)
        self.scripts: list[str] = []
        self.script_errors: list[str] = []
        self.commands: list[tuple[float, int]] = []   # (controller time, command id) as the script took them
        self.dashboard_log: list[str] = []
        self.unsupported: set[int] = set()
        self.history: list[tuple[float, np.ndarray, float]] = []  # (t, q, leading speed) every cycle
        self.stops: list[tuple[float, float]] = []    # (controller time, deceleration) of each stopl/stopj taken
        # the emulated program
        self._main: Iterator | None = None
        self._threads: dict[str, Iterator] = {}
        self._motion: _Motion | None = None
        self._motion_owner: str | None = None
        self._async_wr_count = 0
        self._async_op_id = 0
        self._executing_cmd = False
        # sockets
        self._listeners: list[socket.socket] = []
        self._conns: list[_Conn] = []
        self._threads_os: list[threading.Thread] = []
        self._stop = threading.Event()

    # ------------------------------------------------------------------ life cycle

    def start(self) -> "URControllerEmulator":
        for port, kind in ((RTDE_PORT, "rtde"), (DASHBOARD_PORT, "dashboard"), (SCRIPT_PORT, "script")):
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            deadline = time.monotonic() + 5.0
            while True:
                try:
                    srv.bind((self.host, port))
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        srv.close()
                        self.stop()
                        raise
                    time.sleep(0.05)
            srv.listen(16)
            srv.settimeout(0.1)
            self._listeners.append(srv)
            self._spawn(self._accept_loop, srv, kind)
        self._spawn(self._tick_loop)
        return self

    def stop(self) -> None:
        self._stop.set()
        for srv in self._listeners:
            try:
                srv.close()
            except OSError:
                pass
        for c in list(self._conns):
            c.close()
        for th in self._threads_os:
            if th is not threading.current_thread():
                th.join(2.0)
        self._listeners.clear()

    def __enter__(self) -> "URControllerEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _spawn(self, fn: Callable, *args) -> None:
        th = threading.Thread(target=fn, args=args, daemon=True, name=f"ur-emulator:{fn.__name__}")
        self._threads_os.append(th)
        th.start()

    # ------------------------------------------------------------------ faults

    def protective_stop(self) -> None:
        """The arm bumped into something: it stops (fast), the program stops, PolyScope shows a
        protective stop that can be unlocked 5 s later."""
        with self.lock:
            self.safety_mode = PROTECTIVE_STOP
            self.stop_time = self.timestamp
            self._halt_program(dec=20.0)

    def emergency_stop(self) -> None:
        """Someone pressed the emergency-stop button: the arm stops, power goes off, the program stops."""
        with self.lock:
            self.safety_mode = ROBOT_EMERGENCY_STOP
            self.estop_pressed = True
            self._halt_program(dec=20.0)
            self.robot_mode = POWER_OFF

    def release_emergency_stop(self) -> None:
        """The button is twisted out: the safety system is normal again; the arm stays powered off."""
        with self.lock:
            self.estop_pressed = False
            self.safety_mode = NORMAL

    def operator_clears_protective_stop(self) -> None:
        """What an operator's 'Enable robot' on the teach pendant does."""
        with self.lock:
            if self.safety_mode == PROTECTIVE_STOP:
                self.safety_mode = NORMAL

    def drop(self, down_s: float = 0.0) -> None:
        """The network drops: every client connection is reset; for ``down_s`` seconds new
        connections are reset too. The controller (and the running program) stays up."""
        with self.lock:
            self.refusing = down_s > 0
            conns = list(self._conns)
        for c in conns:
            c.close()
        if down_s > 0:
            threading.Timer(down_s, self._network_up).start()

    def _network_up(self) -> None:
        self.refusing = False

    def freeze(self, frozen: bool = True) -> None:
        """The data stream stops (or resumes) while every socket stays open."""
        self.frozen = bool(frozen)

    # ------------------------------------------------------------------ the arm

    @property
    def safety_status_bits(self) -> int:
        m = self.safety_mode
        bits = {1: 1 << 0, 2: 1 << 1, 3: 1 << 2, 4: 1 << 3, 5: 1 << 4, 6: (1 << 5) | (1 << 7),
                7: (1 << 6) | (1 << 7), 8: 1 << 8, 9: 1 << 9}.get(m, 0)
        if m in (3, 5, 6, 7, 8, 9):
            bits |= 1 << 10
        return bits

    @property
    def robot_status_bits(self) -> int:
        return (1 if self.robot_mode >= 4 else 0) | (2 if self.runtime_state == PLAYING else 0)

    def _halt_program(self, dec: float) -> None:
        if self._motion is not None and not self._motion.done:
            self._motion.stop(dec)
        self._motion_owner = None
        self._main = None
        self._threads.clear()
        self.runtime_state = STOPPED

    def _start_motion(self, target, v: float, a: float, owner: str) -> _Motion:
        m = _Motion(self.q, np.asarray(target, float), v, a)
        self._motion, self._motion_owner = m, owner
        return m

    def _physics(self, dt: float) -> None:
        m = self._motion
        if m is not None and self.stalled:      # the joints do not move: a stop is over at once
            self.qd = np.zeros(6)
            if m.stopping:
                self._motion = None
            return
        if m is None:
            self.qd = np.zeros(6)
            return
        m.step(dt)
        self.q, self.qd = m.q, m.qd
        if m.done:
            self._motion = None
            self.qd = np.zeros(6)

    def leading_speed(self) -> float:
        return float(np.abs(self.qd).max())

    # ------------------------------------------------------------------ the emulated control script

    def _load_script(self, text: str) -> None:
        self.scripts.append(text)
        if "def rtde_control():" not in text:
            return                      # another script (a custom function): not emulated
        missing = [m for m in SCRIPT_PROTOCOL if m not in text]
        with self.lock:
            if missing:
                self.script_errors.append(f"the uploaded control script lacks {missing!r}: the emulated "
                                          f"register protocol no longer matches ur_rtde's")
                return
            if self.robot_mode != RUNNING or self.safety_mode not in (1, 2):
                # a real controller: the program cannot start; PolyScope shows why
                self.script_errors.append(f"program not started: robot mode {ROBOT_MODE_NAMES.get(self.robot_mode)}, "
                                          f"safety mode {SAFETY_MODE_NAMES.get(self.safety_mode)}")
                return
            self._threads.clear()
            self._main = self._main_loop()
            self.runtime_state = PLAYING

    def _write_async(self, value: int) -> None:
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[2] = reg

    def _main_loop(self) -> Iterator[None]:
        self._write_async(-1)           # reset_async_progress()
        self.out_int[0] = 1             # signal_ready()
        self._executing_cmd = False
        while True:
            cmd = self.in_int[0]
            if cmd in REALTIME_CMDS:
                self.unsupported.add(cmd)
                self.out_int[0] = 1
            elif cmd == 0:
                self._executing_cmd = False
                self.out_int[0] = 1
            else:
                if not self._executing_cmd:
                    self._executing_cmd = True
                    self.commands.append((self.timestamp, cmd))
                    keep = yield from self._process(cmd)
                    if not keep:
                        break
            yield                       # sync()
        self.runtime_state = STOPPED
        self._main = None

    def _stop_async_move(self) -> None:
        if "move" in self._threads:
            del self._threads["move"]   # kill move_thrd
            self._write_async(-1)
            if self._motion is not None and self._motion_owner == "move":
                self._motion_owner = None

    def _move_thread(self, target, v: float, a: float) -> Iterator[None]:
        self._write_async(0)            # signal_async_operation_started()
        m = self._start_motion(target, v, a, "move")
        while self._motion is m:
            yield
        self._threads.pop("move", None)
        self._write_async(-1)

    def _stop_thread(self, dec: float) -> Iterator[None]:
        self._write_async(0)
        if self._motion is not None:
            self._motion.stop(dec)
        while self._motion is not None:
            yield
        self._threads.pop("stop", None)
        self._write_async(-1)

    def _process(self, cmd: int) -> Iterator[None]:
        d, i = self.in_double, self.in_int
        if cmd == 1:                                    # movej
            q, v, a, asynchronous = list(d[0:6]), d[6], d[7], i[1]
            self._stop_async_move()
            if asynchronous == 1:
                th = self._move_thread(q, v, a)
                self._threads["move"] = th
                next(th)                                # a thread runs up to its first sync
            else:
                m = self._start_motion(q, v, a, "main")
                while self._motion is m:
                    yield                               # blocked in movej: reads no register
        elif cmd == 31:                                 # protective_stop()
            self.protective_stop()
            return True
        elif cmd in (33, 34):                           # stopl / stopj
            dec, asynchronous = d[0], i[1]
            self.stops.append((self.timestamp, float(dec)))
            stop_move = True
            if "stop" in self._threads:
                stop_move = False
                del self._threads["stop"]
                self._write_async(-1)
            if stop_move:
                self._stop_async_move()
            if asynchronous == 1:
                th = self._stop_thread(dec)
                self._threads["stop"] = th
                next(th)
            else:
                if self._motion is not None:
                    self._motion.stop(dec)
                    self._motion_owner = "main"
                while self._motion is not None:
                    yield
        elif cmd in (36, 37):                           # is_within_safety_limits(pose / q)
            if cmd == 37:
                ok = all(abs(x) <= 2 * math.pi for x in d[0:6])
            else:
                ok = math.dist(d[0:3], (0.0, 0.0, 0.0)) <= 0.85 + 0.1
            self.out_int[1] = 1 if ok else 0
        elif cmd == 40:                                 # get_tcp_offset()
            self.out_double[0:6] = list(self.tcp_offset)
        elif cmd == 43:
            self.out_double[0:6] = ur5_fk_pose(self.q)
        elif cmd == 44:
            self.out_double[0:6] = ur5_fk_pose(d[0:6])
        elif cmd == 47:                                 # is_steady()
            self.out_int[1] = 1 if self.leading_speed() < 1e-6 else 0
        elif cmd == 255:                                # stop script
            return False
        else:
            self.unsupported.add(cmd)
        self.out_int[0] = 2                             # signal_done_with_cmd()
        return True

    # ------------------------------------------------------------------ the controller cycle

    def _tick_loop(self) -> None:
        t_next = time.monotonic()
        while not self._stop.is_set():
            t_next += PERIOD
            with self.lock:
                self.timestamp += PERIOD
                self._physics(PERIOD)
                if self._main is not None:
                    try:
                        next(self._main)
                    except StopIteration:
                        self._main = None
                for name, th in list(self._threads.items()):
                    if self._threads.get(name) is th:
                        try:
                            next(th)
                        except StopIteration:
                            self._threads.pop(name, None)
                self.history.append((self.timestamp, self.q.copy(), self.leading_speed()))
                if len(self.history) > 20000:
                    del self.history[:10000]
                conns = [c for c in self._conns if c.kind == "rtde" and c.started and not c.closed]
                packages = [] if self.frozen else [(c, self._data_package(c)) for c in conns]
            for c, pkg in packages:
                if pkg is not None:
                    c.send(pkg)
            left = t_next - time.monotonic()
            if left > 0:
                time.sleep(left)
            elif left < -0.5:
                t_next = time.monotonic()

    def _value(self, name: str):
        if name == "timestamp":
            return self.timestamp
        if name in ("actual_q", "target_q"):
            return self.q.tolist()
        if name in ("actual_qd", "target_qd"):
            return self.qd.tolist()
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return ur5_fk_pose(self.q)
        if name == "robot_mode":
            return self.robot_mode
        if name == "safety_mode":
            return self.safety_mode
        if name == "safety_status_bits":
            return self.safety_status_bits
        if name == "robot_status_bits":
            return self.robot_status_bits
        if name == "runtime_state":
            return self.runtime_state
        if name == "speed_scaling" or name == "target_speed_fraction":
            return 1.0
        if name == "joint_mode":
            return [253 if self.robot_mode == RUNNING else 229] * 6
        if name.startswith("output_int_register_"):
            return self.out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self.out_double[int(name.rsplit("_", 1)[1])]
        t = TYPES[name]
        return {"VECTOR6D": [0.0] * 6, "VECTOR3D": [0.0] * 3, "VECTOR6INT32": [0] * 6, "DOUBLE": 0.0}.get(t, 0)

    def _data_package(self, c: _Conn) -> bytes | None:
        rid, names, freq = c.out_recipe
        if freq < 125.0:                # a lower frequency: every n-th cycle
            if self.timestamp + 1e-9 < c.next_period:
                return None
            c.next_period = self.timestamp + 1.0 / freq
        body = bytearray(struct.pack(">B", rid))
        for n in names:
            v = self._value(n)
            fmt = FORMATS[TYPES[n]]
            body += struct.pack(">" + fmt, *(v if isinstance(v, list) else [v]))
        return struct.pack(">HB", len(body) + 3, ord("U")) + bytes(body)

    # ------------------------------------------------------------------ sockets

    def _accept_loop(self, srv: socket.socket, kind: str) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = srv.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            if self.refusing:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                sock.close()
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c = _Conn(sock, kind)
            with self.lock:
                self._conns.append(c)
            self._spawn({"rtde": self._serve_rtde, "dashboard": self._serve_dashboard,
                         "script": self._serve_script}[kind], c)

    def _recv(self, c: _Conn, n: int) -> bytes | None:
        data = b""
        while len(data) < n:
            try:
                chunk = c.sock.recv(n - len(data))
            except OSError:
                return None
            if not chunk:
                return None
            data += chunk
        return data

    def _forget(self, c: _Conn) -> None:
        c.close()
        with self.lock:
            if c in self._conns:
                self._conns.remove(c)

    def _serve_rtde(self, c: _Conn) -> None:
        try:
            while not self._stop.is_set():
                head = self._recv(c, 3)
                if head is None:
                    return
                size, ptype = struct.unpack(">HB", head)
                body = self._recv(c, size - 3) if size > 3 else b""
                if body is None:
                    return
                if self.silent:
                    continue
                self._rtde_packet(c, chr(ptype), body)
        finally:
            self._forget(c)

    def _reply(self, c: _Conn, ptype: str, body: bytes) -> None:
        c.send(struct.pack(">HB", len(body) + 3, ord(ptype)) + body)

    def _rtde_packet(self, c: _Conn, ptype: str, body: bytes) -> None:
        if ptype == "V":
            (version,) = struct.unpack(">H", body[:2])
            self._reply(c, "V", struct.pack(">B", 1 if version in (1, 2) else 0))
        elif ptype == "v":
            self._reply(c, "v", struct.pack(">IIII", *self.version))
        elif ptype == "O":
            (freq,) = struct.unpack(">d", body[:8])
            names = [n for n in body[8:].decode().split(",") if n]
            types = [TYPES.get(n, "NOT_FOUND") if not n.startswith("input_") else TYPES.get(n, "NOT_FOUND")
                     for n in names]
            rid = 1
            if "NOT_FOUND" not in types and freq > 0:
                c.out_recipe = (rid, names, min(float(freq), 125.0))
            self._reply(c, "O", struct.pack(">B", rid if c.out_recipe else 0) + ",".join(types).encode())
        elif ptype == "I":
            names = [n for n in body.decode().split(",") if n]
            types = [TYPES[n] if n in INPUT_NAMES else "NOT_FOUND" for n in names]
            rid = 0
            if "NOT_FOUND" not in types:
                rid = len(c.in_recipes) + 1
                c.in_recipes[rid] = names
            self._reply(c, "I", struct.pack(">B", rid) + ",".join(types).encode())
        elif ptype == "S":
            ok = c.out_recipe is not None or bool(c.in_recipes)
            c.started = ok
            self._reply(c, "S", struct.pack(">B", 1 if ok else 0))
        elif ptype == "P":
            c.started = False
            self._reply(c, "P", struct.pack(">B", 1))
        elif ptype == "U":
            rid = body[0]
            names = c.in_recipes.get(rid)
            if names is None:
                return
            off = 1
            with self.lock:
                for n in names:
                    fmt = ">" + FORMATS[TYPES[n]]
                    k = struct.calcsize(fmt)
                    vals = struct.unpack(fmt, body[off:off + k])
                    off += k
                    if n.startswith("input_int_register_"):
                        self.in_int[int(n.rsplit("_", 1)[1])] = vals[0]
                    elif n.startswith("input_double_register_"):
                        self.in_double[int(n.rsplit("_", 1)[1])] = vals[0]

    def _serve_script(self, c: _Conn) -> None:
        buf = ""
        try:
            while not self._stop.is_set():
                try:
                    chunk = c.sock.recv(65536)
                except OSError:
                    return
                if not chunk:
                    return
                if self.silent:
                    continue
                buf += chunk.decode("utf-8", "replace")
                while True:             # a program is complete when its top-level 'end' arrives
                    start = buf.find("def ")
                    m = _END.search(buf, max(start, 0)) if start >= 0 else None
                    if m is None:
                        break
                    self._load_script(buf[start:m.end()])
                    buf = buf[m.end():]
        finally:
            self._forget(c)

    # the dashboard server

    def _dashboard_answer(self, cmd: str) -> str:
        low = cmd.strip().lower()
        with self.lock:
            if low == "polyscopeversion":
                return "URSoftware %d.%d.%d.%d (Mar 01 2023)" % self.version
            if low == "robotmode":
                return f"Robotmode: {ROBOT_MODE_NAMES.get(self.robot_mode, self.robot_mode)}"
            if low == "safetymode":
                return f"Safetymode: {SAFETY_MODE_NAMES.get(self.safety_mode, self.safety_mode)}"
            if low == "safetystatus":
                return f"Safetystatus: {SAFETY_MODE_NAMES.get(self.safety_mode, self.safety_mode)}"
            if low == "programstate":
                return ("PLAYING rtde_control" if self.runtime_state == PLAYING else "STOPPED <unnamed>")
            if low == "running":
                return f"Program running: {'true' if self.runtime_state == PLAYING else 'false'}"
            if low == "get robot model":
                return "UR5"
            if low == "power on":
                if self.safety_mode in (1, 2) and self.robot_mode == POWER_OFF:
                    self.robot_mode = IDLE
                return "Powering on"
            if low == "power off":
                self._halt_program(dec=20.0)
                self.robot_mode = POWER_OFF
                return "Powering off"
            if low == "brake release":
                if self.safety_mode in (1, 2) and self.robot_mode == IDLE:
                    self.robot_mode = RUNNING
                return "Brake releasing"
            if low == "unlock protective stop":
                if self.safety_mode != PROTECTIVE_STOP:
                    return "Protective stop releasing"
                if self.stop_time is not None and self.timestamp - self.stop_time < self.unlock_delay_s:
                    return ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause of "
                            "protective stop before unlocking")
                self.safety_mode = NORMAL
                return "Protective stop releasing"
            if low == "close safety popup":
                return "closing safety popup"
            if low == "close popup":
                return "closing popup"
            if low == "restart safety":
                if self.estop_pressed:
                    return "Restarting safety"
                self.safety_mode = NORMAL
                self.robot_mode = POWER_OFF
                return "Restarting safety"
            if low == "stop":           # PolyScope answers so whether or not a program ran
                if self.runtime_state == PLAYING:
                    self._halt_program(dec=4.0)
                return "Stopped"
            if low == "quit":
                return "Disconnected"
        return f"could not understand: '{cmd.strip()}'"

    def _serve_dashboard(self, c: _Conn) -> None:
        try:
            if not self.silent:
                c.send(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while not self._stop.is_set():
                try:
                    chunk = c.sock.recv(4096)
                except OSError:
                    return
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    cmd = line.decode("utf-8", "replace")
                    self.dashboard_log.append(cmd.strip())
                    if self.silent:
                        continue
                    answer = self._dashboard_answer(cmd)
                    c.send(answer.encode() + b"\n")
                    if answer == "Disconnected":
                        return
        finally:
            self._forget(c)


# ---------------------------------------------------------------------- a process of its own

class EmulatedController:
    """The emulator in a child process, driven from the test.

    ur_rtde's constructors hold the GIL while they wait for the controller's answers (a
    constructor that waits for the control program blocks every Python thread of its process for
    5 s), so the controller cannot run in threads of the process under test: it runs in its own
    process, and this proxy forwards the faults and queries over a local pipe. ``get(name)``
    returns an attribute of :class:`URControllerEmulator` (``q``, ``qd``, ``commands``,
    ``history``, ``script_errors``, ``dashboard_log``, ``robot_mode``, ...); ``set(**attrs)``
    changes them; the fault methods are forwarded.
    """

    def __init__(self, **options):
        import os
        import secrets
        import subprocess
        import sys
        from multiprocessing.connection import Listener

        key = secrets.token_bytes(16)
        self._listener = Listener(("127.0.0.1", 0), authkey=key)
        port = self._listener.address[1]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (os.path.dirname(__file__),
                                                                      os.environ.get("PYTHONPATH")) if p))
        self._proc = subprocess.Popen([sys.executable, __file__, str(port), key.hex(),
                                       json.dumps(options, default=lambda x: np.asarray(x).tolist())], env=env)
        self._listener._listener._socket.settimeout(15.0)
        try:
            self._conn = self._listener.accept()
        except Exception:
            self._proc.kill()
            raise RuntimeError("the emulated UR controller did not start")
        status = self._conn.recv()
        if status != "ready":
            self.close()
            raise RuntimeError(f"the emulated UR controller failed to start: {status}")

    def _rpc(self, *msg):
        self._conn.send(msg)
        ok, value = self._conn.recv()
        if not ok:
            raise RuntimeError(f"emulated controller: {value}")
        return value

    def get(self, name: str):
        return self._rpc("get", name)

    def set(self, **attrs) -> None:
        self._rpc("set", attrs)

    def call(self, name: str, *args):
        return self._rpc("call", name, args)

    def protective_stop(self) -> None:
        self.call("protective_stop")

    def emergency_stop(self) -> None:
        self.call("emergency_stop")

    def release_emergency_stop(self) -> None:
        self.call("release_emergency_stop")

    def operator_clears_protective_stop(self) -> None:
        self.call("operator_clears_protective_stop")

    def drop(self, down_s: float = 0.0) -> None:
        self.call("drop", down_s)

    def freeze(self, frozen: bool = True) -> None:
        self.call("freeze", frozen)

    def wait_until(self, expr: str, timeout_s: float = 5.0) -> float:
        """Wait until ``expr`` (a Python expression over the emulator ``e``) is true in the
        controller; returns the controller time when it was. TimeoutError otherwise."""
        return self._rpc("wait", expr, timeout_s)

    def close(self) -> None:
        try:
            self._conn.send(("quit",))
            self._conn.recv()
        except Exception:  # noqa: BLE001 - the child may be gone already
            pass
        try:
            self._proc.wait(5.0)
        except Exception:  # noqa: BLE001
            self._proc.kill()
            self._proc.wait(5.0)
        self._listener.close()

    def __enter__(self) -> "EmulatedController":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve(port: int, key: bytes, options: dict) -> None:
    from multiprocessing.connection import Client

    conn = Client(("127.0.0.1", port), authkey=key)
    try:
        emu = URControllerEmulator(**options).start()
    except Exception as e:  # noqa: BLE001 - reported to the parent
        conn.send(f"{type(e).__name__}: {e}")
        return
    conn.send("ready")
    try:
        while True:
            try:
                msg = conn.recv()
            except EOFError:
                return
            if msg[0] == "quit":
                conn.send((True, None))
                return
            try:
                if msg[0] == "get":
                    with emu.lock:
                        v = getattr(emu, msg[1])
                        v = v() if callable(v) else v
                        v = [tuple(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, list) else v
                        import copy
                        v = copy.deepcopy(v)
                elif msg[0] == "set":
                    with emu.lock:
                        for k, val in msg[1].items():
                            if not hasattr(emu, k):
                                raise AttributeError(k)
                            setattr(emu, k, np.asarray(val, float) if k in ("q", "qd") else val)
                    v = None
                elif msg[0] == "call":
                    v = getattr(emu, msg[1])(*msg[2])
                elif msg[0] == "wait":
                    deadline = time.monotonic() + msg[2]
                    while True:
                        with emu.lock:
                            if eval(msg[1], {"np": np}, {"e": emu}):
                                v = emu.timestamp
                                break
                        if time.monotonic() > deadline:
                            raise TimeoutError(f"{msg[1]} not true within {msg[2]} s")
                        time.sleep(0.002)
                else:
                    raise ValueError(msg[0])
                conn.send((True, v))
            except Exception as e:  # noqa: BLE001 - reported to the parent
                conn.send((False, f"{type(e).__name__}: {e}"))
    finally:
        emu.stop()


if __name__ == "__main__":
    import sys

    _serve(int(sys.argv[1]), bytes.fromhex(sys.argv[2]), json.loads(sys.argv[3]))
