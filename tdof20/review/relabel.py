"""The review's relabel in a child process that never outlives the app.

``tdof20 annotate``'s place, label and QA stages start worker processes (the label stage's
forkserver and its pool). Run inside the web app, a killed app left them behind, still writing
masks, and holding what the app held. So :class:`Relabeller` runs the rerun as
``python -m tdof20.review.relabel`` in a new process group (the child, its forkserver and every
worker), with

* a *lifeline*: a pipe whose only write end the app holds. The child's watcher thread reads it;
  when the app dies in any way (Ctrl+C, ``kill``, ``kill -9``, a crash) the kernel closes that end,
  the read returns, and the watcher kills the whole group at once;
* :meth:`Relabeller.stop`: the app's shutdown kills the group itself (``tdof20 annotate review``
  calls it on SIGINT / SIGTERM before uvicorn waits for the relabel request).

The child writes its summary (or its one-line refusal) as JSON to a file the parent reads.
Whatever was written before a kill is what an interrupted ``tdof20 annotate`` leaves: atomic files,
resumed by the next run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from tdof20.errors import TdofError

__all__ = ["Relabeller", "main", "scene_config"]


def scene_config(work: Path):
    """The options of a scene's last annotate run (``work/config.json``; defaults if absent)."""
    from tdof20.annotate.config import AnnotateConfig, annotate_config_from_dict
    from tdof20.formats import read_json

    p = Path(work) / "config.json"
    if not p.exists():
        return AnnotateConfig()
    d = read_json(p)
    d = {k: ({kk: vv for kk, vv in v.items() if vv is not None} if isinstance(v, dict) else v)
         for k, v in d.items() if v is not None}
    return annotate_config_from_dict(d, str(p))


class Relabeller:
    """Runs one relabel at a time in a child process group (see the module docstring)."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._guard = threading.Lock()
        self.stopping = False

    @property
    def running(self) -> bool:
        p = self._proc
        return p is not None and p.poll() is None

    @property
    def pid(self) -> int | None:
        p = self._proc
        return p.pid if p is not None and p.poll() is None else None

    def run(self, scene: Path, raw: Path, models_dir: Path | None) -> dict:
        """Place, label and QA of ``scene`` again (blocking); the summary, or a TdofError."""
        if self.stopping:
            raise TdofError("the review app is stopping: no relabel now")
        import tdof20

        root = str(Path(tdof20.__file__).resolve().parents[1])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        r, w = os.pipe()          # both ends non-inheritable; r is passed to the child explicitly
        with tempfile.TemporaryDirectory(prefix="tdof20-relabel-") as tmp:
            result, log = Path(tmp) / "result.json", Path(tmp) / "stderr.txt"
            cmd = [sys.executable, "-m", "tdof20.review.relabel", str(scene), str(raw),
                   "-" if models_dir is None else str(models_dir), str(result), str(r)]
            try:
                with open(log, "wb") as err, self._guard:
                    self._proc = subprocess.Popen(cmd, pass_fds=(r,), start_new_session=True, env=env,
                                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
            finally:
                os.close(r)
            try:
                rc = self._proc.wait()
            finally:
                self._kill_group()      # nothing of it stays behind, whatever happened
                os.close(w)
            if result.exists():
                out = json.loads(result.read_text())
                if "error" in out:
                    raise TdofError(out["error"])
                return out["summary"]
            if self.stopping or rc < 0:
                raise TdofError("relabel stopped before it finished (the review app is stopping, or it was killed); "
                                "what it wrote is kept: relabel again, or run tdof20 annotate, to resume")
            tail = log.read_text(errors="replace").strip().splitlines()
            raise TdofError(f"relabel failed (exit {rc}): {tail[-1] if tail else 'no message'}")

    def _kill_group(self) -> None:
        p = self._proc
        if p is None:
            return
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:   # pragma: no cover - SIGKILL is not ignored
            pass

    def stop(self) -> None:
        """Kill a running relabel and every process it started (the app is stopping)."""
        self.stopping = True
        with self._guard:
            self._kill_group()


def _lifeline(fd: int) -> None:
    """Block on the app's pipe; at EOF (the app is gone) kill this whole process group."""
    try:
        while os.read(fd, 64):
            pass
    except OSError:
        pass
    os.killpg(0, signal.SIGKILL)


def main(argv: list[str]) -> int:
    scene, raw, models, result, fd = argv
    threading.Thread(target=_lifeline, args=(int(fd),), daemon=True, name="lifeline").start()
    from tdof20.annotate.pipeline import annotate
    from tdof20.formats import write_json
    try:
        cfg = scene_config(Path(scene) / "work")
        summary = annotate(Path(raw), Path(scene), models_dir=None if models == "-" else Path(models),
                           stages=("place", "label", "qa"), cfg=cfg, progress=False)
        write_json(Path(result), {"summary": summary})
    except TdofError as e:
        write_json(Path(result), {"error": str(e)})
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
