"""Many raw sessions in one command: ``tdof20 annotate RAW [RAW ...] --out DIR``.

    summary = annotate_many([raw1, raw2, ...], out_dir, models_dir=None, stages=None, cfg=AnnotateConfig())
    print(batch_text(summary))

Each session becomes the scene folder ``DIR/<kind>/<name>``: its scene id from ``session.json``
with the slash kept as a folder level (``multi/08`` -> ``DIR/multi/08``, ``single/cube_136`` ->
``DIR/single/cube_136``), which cannot collide — a scene id has one slash, and two sessions of one
scene id are refused. Everything is checked before anything runs (each RAW is a session, no two
share a scene id, no scene folder holds something else); then every scene runs the pipeline
(:func:`tdof20.annotate.pipeline.annotate`, which resumes each scene on its own) and a failing
scene does not stop the others: the summary lists each scene's status, labelled and flagged
frames and time, and names the failed ones (``DIR/annotate_summary.json``).

Where the scenes run (``cfg.label.executor``, ``cfg.label.workers``):

- ``local``, N workers (None = every core): min(N, scenes) scenes side by side on worker
  processes, the N shared out among them (each scene's registration and labels get N // that
  many); one scene at a time in this process when N = 1 or there is one scene.
- ``ray``: one Ray task per scene (its stages in order inside the task, which holds the scene
  folder's lock: one writer per scene folder), and inside it the registration's arm positions
  and the label chunks as further tasks on the same cluster. ``ray_address`` None starts a local
  instance of N CPUs (None = every core). The folders must have the same path on every node (a
  shared file system).

The labels do not depend on where they were made: a session gives the same files alone, on local
workers or on Ray (``tests/test_annotate_scale.py``). Progress: one bar over the scenes' stages,
its text naming each running scene's stage (read from the scenes' ``work/state.json``).
"""

from __future__ import annotations

import datetime as _dt
import re
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.executors import executor_scope, resolve_workers, run_chunks
from tdof20.annotate.pipeline import annotate, check_models_dir, check_out
from tdof20.annotate.stages import parse_stages
from tdof20.annotate.state import WORK
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, write_json
from tdof20.progress import progress as _progress

__all__ = ["SUMMARY", "SceneJob", "annotate_many", "batch_text", "plan_batch", "scene_folder"]

SUMMARY = "annotate_summary.json"   # DIR's record of the last run over its scenes
_PART = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


@dataclass(frozen=True)
class SceneJob:
    """One session of a batch: absolute paths (a Ray worker may start in another folder)."""

    raw: str
    out: str
    scene_id: str


def scene_folder(out_dir: Path, scene_id: str, where: Path | None = None) -> Path:
    """``out_dir/<kind>/<name>`` for scene id ``kind/name``; a scene id that is no safe pair of
    folder names (``..``, a second slash) -> TdofError naming ``where``."""
    parts = str(scene_id).split("/")
    if len(parts) != 2 or not all(_PART.fullmatch(p) and p not in (".", "..") for p in parts):
        raise TdofError(f"scene_id {scene_id!r} is not 'kind/name' with plain names: it cannot name a scene folder",
                        where)
    return Path(out_dir).joinpath(*parts)


def plan_batch(raws: Iterable[str | Path], out_dir: str | Path, models_dir: str | Path | None = None,
               force: bool = False) -> list[SceneJob]:
    """The scene folders of ``raws`` under ``out_dir``, every check done before anything runs:
    a RAW that is not a session, two sessions of one scene id, an ``out_dir`` that is a file or
    one annotated scene itself, a scene folder annotate must not write (:func:`check_out`) —
    each one line (TdofError) naming the file."""
    out = Path(out_dir)
    raws = [Path(r) for r in raws]
    if not raws:
        raise TdofError("no raw session given")
    if out.exists() and not out.is_dir():
        raise TdofError("is not a folder (with several sessions --out is the folder their scenes go in)", out)
    if (out / WORK / "state.json").exists():
        raise TdofError("holds one annotated scene (work/state.json): with several sessions --out is the folder "
                        "their scene folders go in (DIR/multi/08 ...); choose another --out", out)
    check_models_dir(None if models_dir is None else Path(models_dir))
    jobs: list[SceneJob] = []
    seen: dict[str, Path] = {}
    for raw in raws:
        try:
            session = RawSession.open(raw)
        except TdofError as e:
            raise TdofError(f"not a raw session ({e})", raw) from None
        sid = session.info.scene_id
        if sid in seen:
            raise TdofError(f"sessions {seen[sid]} and {raw} both hold scene {sid}: one scene folder per scene id "
                            f"({scene_folder(out, sid)}); annotate one of them with another --out")
        seen[sid] = raw
        dest = scene_folder(out, sid, raw / "session.json")
        check_out(raw, dest, session, force)
        jobs.append(SceneJob(str(raw.resolve()), str(dest.resolve()), sid))
    return jobs


# ---------------------------------------------------------------------------------------------
# one scene, wherever it runs
# ---------------------------------------------------------------------------------------------
def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def _figures(s: dict) -> dict:
    """Labelled and flagged frames and the failed stage, from an annotate summary."""
    lab = s.get("label") or {}
    reg = (s.get("registration") or {}).get("flagged")
    fig: dict[str, Any] = {"frames": s.get("frames_planned"),
                           "labelled": lab.get("labelled", 0) + lab.get("already_done", 0) if lab else None,
                           "flagged": len(lab.get("skipped") or []) if lab else (None if reg is None else len(reg))}
    ev = s.get("evaluation")
    if ev:
        fig["wrong_labels"] = ev.get("wrong_labels")
    if s.get("failed_objects"):
        fig["failed_objects"] = s["failed_objects"]
    failed = [st for st, e in (s.get("stages") or {}).items() if e.get("status") == "failed"]
    if failed:
        fig["stage"] = failed[0]
    return fig


@dataclass(frozen=True)
class _RunScene:
    """``annotate`` one scene; every error becomes the scene's row (status "failed"), so one
    failing scene never stops the others (picklable: runs on worker processes and Ray tasks)."""

    models_dir: str | None
    stages: tuple[str, ...]
    cfg: AnnotateConfig
    force: bool

    def __call__(self, job: SceneJob) -> dict:
        t0, wall0 = time.perf_counter(), time.time()
        row: dict[str, Any] = {"scene": job.scene_id, "raw": job.raw, "out": job.out}
        try:
            s = annotate(job.raw, job.out, self.models_dir, self.stages, self.cfg, self.force, progress=False)
        except Exception as e:  # noqa: BLE001 - a scene's failure, whatever it is, is its row
            row.update(status="failed", error=str(e) if isinstance(e, TdofError) else _first_line(e))
            if not isinstance(e, TdofError):
                row["traceback"] = traceback.format_exc()
            summary = Path(job.out) / WORK / "summary.json"
            try:   # the figures this run got to (a run refused before it started writes none)
                if summary.exists() and summary.stat().st_mtime >= wall0 - 1.0:
                    row.update(_figures(read_json(summary)))
            except (TdofError, OSError):
                pass
        else:
            ran = any(e.get("status") == "ran" for e in s["stages"].values())
            row.update(status="partial" if s.get("partial") else "annotated" if ran else "up to date", **_figures(s))
        row["seconds"] = round(time.perf_counter() - t0, 3)
        return row


# ---------------------------------------------------------------------------------------------
# progress: one bar, the running scenes' stages
# ---------------------------------------------------------------------------------------------
class _Poller(threading.Thread):
    """Every ``every`` s: each running scene's stage from its ``work/state.json`` (a stage
    started in this run and not finished) -> the bar's position and text."""

    def __init__(self, bar, task, jobs: list[SceneJob], chosen: tuple[str, ...], done: dict, since: str,
                 every: float = 0.5):
        super().__init__(daemon=True)
        self.bar, self.task, self.jobs, self.chosen, self.done, self.since = bar, task, jobs, chosen, done, since
        self.every = every
        self.halt = threading.Event()

    def _stage(self, job: SceneJob) -> tuple[int, str | None]:
        try:
            stages = read_json(Path(job.out) / WORK / "state.json").get("stages", {})
        except (TdofError, OSError, ValueError, AttributeError):
            return 0, None
        finished = 0
        for i, st in enumerate(self.chosen):
            e = stages.get(st) or {}
            if e.get("started", "") >= self.since and not e.get("finished"):
                return i, st
            finished += e.get("finished", "") >= self.since
        return finished, None

    def update(self) -> None:
        n = len(self.chosen)
        completed, running = 0, []
        for job in self.jobs:
            if job.out in self.done:
                completed += n
                continue
            k, st = self._stage(job)
            completed += k
            if st is not None:
                running.append(f"{job.scene_id} {st}")
        text = f"annotate {len(self.done)}/{len(self.jobs)} scenes" + (f" · {' · '.join(running)}" if running else "")
        self.bar.update(self.task, completed=completed, description=text)

    def run(self) -> None:
        while not self.halt.wait(self.every):
            self.update()

    def stop(self) -> None:
        self.halt.set()
        self.join()
        self.update()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


# ---------------------------------------------------------------------------------------------
# the batch
# ---------------------------------------------------------------------------------------------
def annotate_many(raws: Iterable[str | Path], out_dir: str | Path, models_dir: str | Path | None = None,
                  stages: str | Iterable[str] | None = None, cfg: AnnotateConfig = AnnotateConfig(),
                  force: bool = False, progress: bool = True) -> dict:
    """Annotate every session of ``raws`` into ``out_dir/<kind>/<name>`` (module docstring).

    Returns (and writes to ``out_dir/annotate_summary.json``) ``{"out", "executor", "workers",
    "scenes_side_by_side", "seconds", "scenes": [row per session, in the order given], "failed":
    [scene ids], "partial": [scene ids]}``; a row: ``scene``, ``raw``, ``out``, ``status``
    ("annotated", "up to date", "partial": labelled but for the objects in ``failed_objects``, or
    "failed"), ``frames``, ``labelled``, ``flagged`` (frames not labelled, with reasons in the
    scene's ``work/summary.json``), ``wrong_labels`` (simulated sessions), ``seconds``, and for a
    failed one ``error`` and ``stage``. A bad RAW, two sessions of one scene id or a scene folder
    annotate must not write raise TdofError before anything runs; a scene's failure does not."""
    chosen = parse_stages(stages)
    jobs = plan_batch(raws, out_dir, models_dir, force)
    out = Path(out_dir)
    executor, address, workers = cfg.label.executor, cfg.label.ray_address, cfg.label.workers
    if executor == "local":
        n = resolve_workers(workers)
        side = min(n, len(jobs))
        job_cfg = cfg.with_label_options(workers=max(1, n // side)) if side > 1 else cfg
        pool: int | None = side
    else:   # Ray places the scene tasks and their chunks on its CPUs
        side, job_cfg, pool = None, cfg, workers
    fn = _RunScene(None if models_dir is None else str(Path(models_dir).resolve()), chosen, job_cfg, force)
    rows: dict[str, dict] = {}
    t0, since = time.perf_counter(), _now()
    # Ray starts (or is reached) before anything is written: an unreachable cluster is one line
    with executor_scope(executor, address, workers, start=True), _progress(progress, unit="stage") as bar:
        out.mkdir(parents=True, exist_ok=True)
        task = bar.add_task(f"annotate 0/{len(jobs)} scenes", total=len(jobs) * len(chosen))
        poller = _Poller(bar, task, jobs, chosen, rows, since)
        poller.start()
        try:
            for row in run_chunks(fn, jobs, executor=executor, workers=pool, ray_address=address):
                rows[row["out"]] = row
        except Exception as e:  # noqa: BLE001 - the executor itself failed (a worker died, the cluster went)
            why = str(e) if isinstance(e, TdofError) else _first_line(e)
            for job in jobs:
                rows.setdefault(job.out, {"scene": job.scene_id, "raw": job.raw, "out": job.out, "status": "failed",
                                          "error": f"not finished: {why}", "seconds": None})
        finally:
            poller.stop()
    ordered = [rows[j.out] for j in jobs]
    summary = {"out": str(out.resolve()), "executor": executor, "ray_address": address, "workers": workers,
               "scenes_side_by_side": side, "seconds": round(time.perf_counter() - t0, 3), "scenes": ordered,
               "failed": [r["scene"] for r in ordered if r["status"] == "failed"],
               "partial": [r["scene"] for r in ordered if r["status"] == "partial"]}
    write_json(out / SUMMARY, summary)
    return summary


def _duration(s: float | None) -> str:
    if s is None:
        return "-"
    return f"{s:.1f} s" if s < 60 else f"{int(s // 60)} min {s % 60:.0f} s"


def batch_text(summary: dict) -> str:
    """The table ``tdof20 annotate RAW... --out DIR`` prints: per scene its status, labelled of
    planned frames, flagged frames, time and folder; then each failed scene's error."""
    rows = summary["scenes"]
    w = max([5] + [len(r["scene"]) for r in rows])
    lines = [f"{'scene':<{w}}  {'status':<10}  {'labelled':>9}  {'flagged':>7}  {'time':>10}  folder"]
    for r in rows:
        lab = "-" if r.get("labelled") is None else f"{r['labelled']}/{r.get('frames', '?')}"
        fl = "-" if r.get("flagged") is None else str(r["flagged"])
        lines.append(f"{r['scene']:<{w}}  {r['status']:<10}  {lab:>9}  {fl:>7}  {_duration(r.get('seconds')):>10}  "
                     f"{r['out']}")
    done = sum(r["status"] != "failed" for r in rows)
    lines.append(f"{done} of {len(rows)} scenes annotated in {_duration(summary.get('seconds'))} "
                 f"({summary['executor']}" + (f", {summary['workers']} workers" if summary.get("workers") else "")
                 + f"); summary: {Path(summary['out']) / SUMMARY}")
    for r in rows:
        if r["status"] == "failed":
            at = f" in stage '{r['stage']}'" if r.get("stage") else ""
            lines.append(f"  {r['scene']} failed{at}: {r.get('error')}")
        for f in r.get("failed_objects") or []:
            lines.append(f"  {r['scene']} partial: object {f['obj_id']} not labelled: {f['reason']}")
    return "\n".join(lines)
