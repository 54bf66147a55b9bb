"""Run a capture session: sequence the arm and the turntable, grab RGB-D pairs, journal them.

The journal is the truth. A frame is written (both PNGs, atomically), then its journal line is
appended and fsync'ed; a run on a folder holding part of the same session resumes exactly where
it stopped, taking again every planned frame that is not journalled or whose files are missing or
fail their checksum. A device failure after the configured retries, Ctrl-C or SIGTERM stop the run
cleanly: motion stopped, journal consistent, a message saying what failed and the command that
resumes. A kill -9 at any moment loses at most the frame in flight: the torn journal line or the
temporary files it may leave are cleaned up by the resume. The output folder is checked (a folder,
writable) before any device connects.
"""

from __future__ import annotations

import logging
import os
import signal
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, TypeVar

import numpy as np
from rich.markup import escape

from tdof20.capture.config import CaptureConfig
from tdof20.capture.hardware.interfaces import HardwareError, SafetyStop
from tdof20.capture.plan import check_workspace, session_info
from tdof20.capture.rig import Rig, build_rig
from tdof20.errors import TdofError
from tdof20.formats import RawSession, SessionInfo, read_session, write_frame, write_session
from tdof20.formats.io import TEMP_FILE_RE, stale_temp_files
from tdof20.formats.session import SESSION_FILE, depth_units_problem
from tdof20.progress import console, progress

T = TypeVar("T")
LOG_FILE = "capture.log"
PROBE_PREFIX = ".write-check."  # check_output's test file (removed at once; a kill may leave it)


class CaptureInterrupted(Exception):
    """Ctrl-C or SIGTERM."""


@dataclass
class CaptureSummary:
    out: Path
    planned: int = 0
    present_before: int = 0
    captured: int = 0
    retaken: int = 0
    retries: int = 0
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def complete(self) -> bool:
        return self.present_before + self.captured >= self.planned

    def lines(self) -> list[str]:
        fps = self.captured / self.seconds if self.seconds > 0 else 0.0
        out = [f"frames: {self.captured} captured now ({fps:.1f}/s), {self.present_before} already there, "
               f"{self.planned} planned" + (f", {self.retaken} taken again (missing or bad files)" if self.retaken else ""),
               f"time: {self.seconds:.1f} s; device retries: {self.retries}; warnings: {len(self.warnings)}"]
        out += [f"warning: {w}" for w in self.warnings[:10]]
        return out


@contextmanager
def _signals_raise() -> Iterator[None]:
    """Turn SIGTERM (and SIGINT) into CaptureInterrupted in the main thread while capturing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise CaptureInterrupted(signal.Signals(signum).name)

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _logger(out: Path) -> logging.Logger:
    log = logging.getLogger(f"tdof20.capture.{out.resolve()}")
    log.setLevel(logging.INFO)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
    fh = logging.FileHandler(out / LOG_FILE)
    fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(fh)
    return log


def check_output(out: Path) -> None:
    """Refuse an output folder that cannot hold a session, before any device connects or moves:
    ``out`` (or a folder above it) is a file, or the folder cannot be created or written. Creates
    the folder when it does not exist."""
    if out.exists() and not out.is_dir():
        raise TdofError("--out is a file, not a folder: choose a folder for the session", out)
    above = out.parent
    while not above.exists() and above != above.parent:
        above = above.parent
    if above.exists() and not above.is_dir():
        raise TdofError(f"cannot create the session folder: {above} is a file, not a folder", out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        # a real write, not a permission-bit check: the bits do not stop root, a read-only mount does
        fd, probe = tempfile.mkstemp(prefix=PROBE_PREFIX, suffix=".tmp", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise TdofError(f"cannot write the session folder ({e.strerror or type(e).__name__}): "
                        f"choose a folder you can write to", out) from None


def _is_first_write_leftover(p: Path) -> bool:
    """What an interrupted first run leaves in a folder before session.json is there: its log, a
    temporary file of session.json or of the write check."""
    n = p.name
    return n == LOG_FILE or (n.startswith((f".{SESSION_FILE}.", PROBE_PREFIX)) and bool(TEMP_FILE_RE.match(n)))


def prepare_output(out: Path, info: SessionInfo) -> None:
    """Write session.json into a new or empty folder, or check that the folder holds this same
    session. Never touches the frames of another session. A folder that holds only what an
    interrupted first run left (its log, a temporary file of session.json) counts as empty."""
    if (out / "session.json").exists():
        existing = read_session(out)
        if existing.to_dict() != info.to_dict():
            a, b = existing.to_dict(), info.to_dict()
            diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            raise TdofError(f"holds a different session (differs in: {', '.join(diff)}); choose another --out",
                            out / "session.json")
    elif out.exists() and not all(_is_first_write_leftover(p) for p in out.iterdir()):
        raise TdofError("folder is not empty and holds no session.json; choose another --out", out)
    else:
        for p in out.glob(".*.tmp") if out.exists() else ():
            if _is_first_write_leftover(p):
                p.unlink()
        write_session(out, info)


class _Runner:
    def __init__(self, cfg: CaptureConfig, rig: Rig, out: Path, yes: bool, prompt: Callable[[str], str],
                 show_progress: bool, summary: CaptureSummary, log: logging.Logger):
        self.cfg, self.rig, self.out, self.yes, self.prompt = cfg, rig, out, yes, prompt
        self.show_progress, self.summary, self.log = show_progress, summary, log

    def retry(self, what: str, fn: Callable[[], T]) -> T:
        """Call ``fn``; retry retryable device errors ``session.retries`` times; on a safety stop
        ask the operator to clear it (interactive runs) and go on."""
        attempts = self.cfg.session.retries + 1
        n = 0
        while True:
            try:
                return fn()
            except SafetyStop as e:
                self.log.warning("%s: %s", what, e)
                if self.yes:
                    raise
                console.print(f"[bold yellow]paused:[/bold yellow] {escape(str(e))}")
                for ask in range(3):
                    self.prompt("Clear the stop on the teach pendant, then press Enter to go on (Ctrl-C stops) ")
                    try:
                        self.rig.robot.resume()  # unlock, restart the robot's program where the backend can
                        break
                    except SafetyStop as still:
                        self.log.warning("%s: %s", what, still)
                        if ask == 2:
                            raise
                        console.print(f"[bold yellow]still stopped:[/bold yellow] {escape(str(still))}")
                self.summary.warnings.append(f"safety stop during {what}, cleared by the operator")
            except HardwareError as e:
                n += 1
                self.log.warning("%s failed (attempt %d of %d): %s", what, n, attempts, e)
                if not e.retryable or n >= attempts:
                    raise
                self.summary.retries += 1
                time.sleep(min(0.2 * n, 1.0) if not self.cfg.is_sim else 0.0)

    def run(self, targets: list[np.ndarray], info: SessionInfo) -> None:
        cfg, rig = self.cfg, self.rig
        for tmp in stale_temp_files(self.out):  # a write cut short by a kill: never renamed into place
            tmp.unlink(missing_ok=True)
            self.log.info("removed the unfinished write %s", tmp)
        session = RawSession.open(self.out)
        done: set = set()
        for key in session.frames():
            problems = session.verify_file(session.entry(*key), decode=False)
            if problems:
                self.summary.retaken += 1
                self.log.warning("frame %s will be taken again: %s", key, "; ".join(problems))
            else:
                done.add(key)
        steps = cfg.turntable.steps
        planned = [(ph, a, k) for ph in cfg.session.phases for a in range(len(targets)) for k in range(steps)]
        self.summary.planned = len(planned)
        self.summary.present_before = len(done & set(planned))
        todo = [k for k in planned if k not in done]
        self.log.info("session %s: %d planned, %d present, %d to capture", cfg.session.scene_id, len(planned),
                      self.summary.present_before, len(todo))
        if not todo:
            return
        if cfg.turntable.home:
            self.retry("turntable homing", lambda: rig.turntable.home(cfg.turntable.timeout_s))
        r = cfg.robot
        with progress(self.show_progress) as bar:
            tasks = {(ph, a): bar.add_task(f"{ph:<11s} arm {a}", total=steps,
                                           completed=sum((ph, a, k) in done for k in range(steps)))
                     for ph in cfg.session.phases for a in range(len(targets))}
            for phase in cfg.session.phases:
                pending_phase = [k for k in todo if k[0] == phase]
                if not pending_phase:
                    continue
                self._swap(phase)
                for arm, q in enumerate(targets):
                    pending = [k for (ph, a, k) in pending_phase if a == arm]
                    if not pending:
                        continue
                    self.log.info("%s: moving to arm position %d", phase, arm)
                    self.retry(f"moveJ to arm position {arm}",
                               lambda: rig.robot.move_joints(q, r.speed, r.acceleration, r.move_timeout_s))
                    state = self.retry("robot read-back", rig.robot.state)
                    err = float(np.abs(state.q - q).max())
                    if err > r.joint_tolerance_rad:
                        raise HardwareError(rig.robot.name, f"arm position {arm} not reached: joints off by {err:.4f} rad",
                                            retryable=False)
                    for step in pending:
                        self._frame(phase, arm, step, state, info)
                        bar.advance(tasks[(phase, arm)])

    def _swap(self, phase: str) -> None:
        if self.rig.set_phase is not None:
            self.rig.set_phase(phase)  # the simulator swaps the objects itself
            self.log.info("phase %s (simulator swapped the objects)", phase)
            return
        what = "the transparent objects" if phase == "transparent" else "the opaque twins"
        self.log.info("phase %s: operator places %s", phase, what)
        if not self.yes:
            self.prompt(f"Place {what} in their slots, then press Enter to capture the {phase} phase ")

    def _frame(self, phase: str, arm: int, step: int, state, info: SessionInfo) -> None:
        cfg, rig = self.cfg, self.rig
        angle = step * cfg.turntable.step_deg
        reported = self.retry(f"turntable move to {angle:.2f} deg",
                              lambda: rig.turntable.move_to(angle, cfg.turntable.timeout_s))
        if abs(reported - angle) > 0.05:
            self.summary.warnings.append(f"{phase} arm {arm} step {step}: table reports {reported:.3f} deg, "
                                         f"{angle:.3f} planned")
        if cfg.turntable.settle_s > 0:
            time.sleep(cfg.turntable.settle_s)
        t0 = time.time()
        frame = self.retry("camera grab", lambda: rig.camera.grab(cfg.camera.timeout_s))
        write_frame(self.out, info, phase, arm, step, frame.rgb, frame.depth, t=t0,
                    extra={"q_actual": state.q.tolist(), "T_base_tcp_actual": state.T_base_tcp.reshape(-1).tolist(),
                           "table_angle_reported_deg": float(reported), "t_rgb": frame.t_rgb,
                           "t_depth": frame.t_depth})
        self.summary.captured += 1


def run_capture(cfg: CaptureConfig, out: str | Path, yes: bool = False, show_progress: bool = True,
                prompt: Callable[[str], str] = input, rig: Rig | None = None,
                resume_command: str | None = None) -> CaptureSummary:
    """Capture (or resume) the session ``cfg`` into ``out``. Raises TdofError with a one-line
    message (what failed, how to resume) when it stops early."""
    out = Path(out)
    resume = resume_command or f"tdof20 capture run ... --out {out}"
    targets = check_workspace(cfg)  # refused before anything connects or moves
    check_output(out)
    rig = rig or build_rig(cfg)
    summary = CaptureSummary(out)
    t_start = time.perf_counter()
    connected = []
    log = None
    try:
        with _signals_raise():
            try:
                for dev in (rig.camera, rig.robot, rig.turntable):
                    dev.connect()
                    connected.append(dev)
                info = session_info(cfg, rig.camera.intrinsics(), targets)
                prepare_output(out, info)
                log = _logger(out)
                log.info("capture started: %s", resume)
                _Runner(cfg, rig, out, yes, prompt, show_progress, summary, log).run(targets, info)
                if rig.after_capture is not None:
                    rig.after_capture(out, show_progress)
            except CaptureInterrupted as e:
                _stop(rig, connected)
                raise TdofError(f"stopped by {e} after {summary.captured} new frames; the journal is consistent; "
                                f"resume with: {resume}") from None
            except KeyboardInterrupt:
                _stop(rig, connected)
                raise TdofError(f"stopped by Ctrl-C after {summary.captured} new frames; the journal is consistent; "
                                f"resume with: {resume}") from None
            except HardwareError as e:
                _stop(rig, connected)
                if log:
                    log.error("stopped: %s", e)
                raise TdofError(f"capture stopped: {e}; {summary.captured} new frames kept; resume with: {resume}") from None
            except OSError as e:  # the disk: full, gone read-only, a folder removed under the run
                _stop(rig, connected)
                what = _os_error(e, out)
                if log:
                    log.error("stopped: %s", what)
                raise TdofError(f"capture stopped: {what}; {summary.captured} new frames kept; "
                                f"resume with: {resume}") from None
    finally:
        for dev in connected:
            try:
                dev.close()
            except Exception:  # noqa: BLE001 - closing never hides the real error
                pass
        summary.seconds = time.perf_counter() - t_start
        if log:
            for line in summary.lines():
                log.info(line)
            for h in list(log.handlers):
                h.close()
                log.removeHandler(h)
    return summary


def _os_error(e: OSError, out: Path) -> str:
    """An OSError in words: 'cannot write <file>: <reason>' for a file of the session."""
    if e.filename and e.strerror:
        inside = Path(e.filename).resolve().is_relative_to(out.resolve())
        return f"{'cannot write ' if inside else ''}{e.filename}: {e.strerror}"
    return f"{type(e).__name__}: {e}"


def _stop(rig: Rig, connected: list) -> None:
    for dev in (rig.robot, rig.turntable):
        if dev in connected:
            try:
                dev.stop()
            except Exception:  # noqa: BLE001 - best effort
                pass


def verify_session(out: str | Path) -> list[str]:
    """Problems of a raw session, each one line; [] = good. Checks what annotation will refuse:
    every phase has frames for every arm position (an empty journal is one problem, not one per
    planned frame), every planned frame present (a frame taken again counts by its last journal
    line), files present, decodable, of session.json's camera size and matching their checksums,
    and depths in millimetres (the first opaque frame of each arm position)."""
    s = RawSession.open(out)
    lacking = []  # what annotation refuses outright: a phase, or an arm position, without frames
    for ph in s.info.phases:
        try:
            s.require_frames(ph)
        except TdofError as e:
            if not s.entries:
                return [str(e)]  # one line, not one per planned frame
            lacking.append(str(e))
    problems = [f"missing frame: {ph} arm {a} step {k}" for ph, a, k in s.missing_frames()]
    sound: dict[int, tuple] = {}  # arm -> its first frame of the depth-check phase whose files are sound
    phase = "opaque" if "opaque" in s.info.phases else s.info.phases[0]
    for key in s.frames():
        bad = s.verify_file(s.entry(*key))
        problems += bad
        if not bad and key[0] == phase:
            sound.setdefault(key[1], key)
    if sound:
        keys = [sound[a] for a in sorted(sound)]
        depth = np.concatenate([s.load_depth_mm(*k).reshape(-1) for k in keys])
        problem = depth_units_problem(s.info, depth)
        if problem:
            used = ", ".join(f"{ph} arm {a} step {k}" for ph, a, k in keys)
            problems.append(f"{s.path / SESSION_FILE}: {problem} (sampled: {used})")
    return problems + lacking
