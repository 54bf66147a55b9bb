"""``tdof20 serve worker``: claim a queued submission, score it with the scoring package's
:func:`~tdof20.scoring.evaluate` against the full dataset, keep what its figures are drawn from in
the store (:mod:`tdof20.server.figures`: the server draws them when first asked for) and record
the result — only while the claim is still this worker's (:func:`tdof20.server.db.finish_job`).
A thread renews the lease while the scorer runs; a worker killed mid-score leaves a lease that
expires, and another worker (or this one restarted) scores the submission again from its file.
Any number of workers may run, here or on machines sharing the database and the store.

A submission on a protocol's validation part (``part`` val) is scored against the validation
targets (:func:`tdof20.server.facts.validation_targets`: no test image among them) and gets, besides
the summary, each image's errors per object (``per_image``), from the same scorer run on that
image's targets alone, and its condition cells. A test submission never gets per-image data; it
gets its condition cells and, where its protocol has a held-back part, its public and private parts' summaries
(:func:`test_cells`), all from the scorer's own per-target arrays. Every result records the scorer
and dataset versions it was computed with (:func:`current_versions`)."""

from __future__ import annotations

import math
import os
import socket
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

from sqlalchemy import Engine, select

from tdof20.dataset.results import read_results
from tdof20.errors import TdofError
from tdof20.formats import write_json
from tdof20.scoring import evaluate
from tdof20.scoring import report
from tdof20.scoring.dataset_view import DatasetView
from tdof20.server.cells import dataset_version, scorer_version, test_extras
from tdof20.server.config import ServerConfig
from tdof20.server.db import (Claim, claim_job, finish_job, heartbeat, held_back_part, init_db, is_resource_error,
                              make_engine, release_job, submissions)
from tdof20.server.facts import validation_targets
from tdof20.server.figures import save_figure_data
from tdof20.server.publish import hidden_frames
from tdof20.server.store import Store

FAILED = "scoring failed; the server's operators have the details"
PER_IMAGE_METRICS = "add,proj"  # per image: the errors a researcher reads (mm, px)


def _finite(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None  # inf: no estimate for the target


def per_image_errors(results: Path, root: Path, targets: list[dict], lease) -> list[dict]:
    """Each validation image's errors per object instance, from the scorer run on that image's
    targets alone: [{"scene_id", "im_id", "obj_id", "add_mm", "adds_mm", "add_s_ok", "proj_px"}].
    ``lease()`` is called between images (the worker's heartbeat)."""
    res = read_results(results)
    ds = DatasetView(root)
    by_image: dict[tuple[int, int], list[dict]] = defaultdict(list)
    for t in targets:
        by_image[(int(t["scene_id"]), int(t["im_id"]))].append(t)
    out = []
    with tempfile.TemporaryDirectory(prefix="tdof20-val-") as tmp:
        path = Path(tmp) / "targets.json"
        for (sid, im), tg in sorted(by_image.items()):
            write_json(path, tg, indent=None)
            ev = evaluate(res, root, None, path, dataset=ds, metrics=PER_IMAGE_METRICS)
            for ob, o in ev.objects.items():
                for k in range(o.n):
                    out.append({"scene_id": sid, "im_id": im, "obj_id": int(ob), "add_mm": _finite(o.add[k]),
                                "adds_mm": _finite(o.adds[k]), "add_s_ok": bool(o.add_s_ok[k]),
                                "proj_px": _finite(o.proj[k])})
            lease()
    return out


def test_cells(engine: Engine, cfg: ServerConfig, sub, ev, path: Path) -> dict:
    """A test result's condition cells and, where the protocol has a held-back part, its public and
    private parts' summaries (:func:`tdof20.server.cells.test_extras`, from the scorer's arrays)."""
    part = held_back_part(engine, sub.split)
    private = None if part is None else {(int(s), int(i)) for s, i in part["images"]}
    return test_extras(ev, Path(cfg.dataset), sub.split, path, private, hidden_frames(cfg.dataset))


def current_versions(engine: Engine, root: Path, split: str) -> dict:
    """The scorer and dataset versions a result of ``split`` computed now is on."""
    part = held_back_part(engine, split)
    return {"scorer": scorer_version(), "dataset": dataset_version(root, split, part and part["digest"])}


def _renew(engine: Engine, claim: Claim, lease_s: float, stop: threading.Event) -> None:
    while not stop.wait(lease_s / 3):
        try:
            if not heartbeat(engine, claim, lease_s):
                return
        except Exception as e:  # a database error: try again at the next beat (the lease may lapse)
            if not is_resource_error(e):
                raise


def score_one(engine: Engine, store: Store, cfg: ServerConfig, claim: Claim, pause_s: float = 0.0) -> bool:
    """Score the claimed submission; returns whether its result was recorded."""
    with engine.begin() as c:
        sub = c.execute(select(submissions).where(submissions.c.id == claim.submission_id)).first()
    stop = threading.Event()
    beat = threading.Thread(target=_renew, args=(engine, claim, cfg.lease_s, stop), daemon=True)
    beat.start()
    try:
        heartbeat(engine, claim, cfg.lease_s, "scoring")
        if pause_s:
            time.sleep(pause_s)
        result, error, versions = None, None, None
        try:
            out = store.results_dir(sub.uid)
            path = store.submission_path(sub.stored)
            if sub.part == "val":
                targets = validation_targets(cfg.dataset, sub.split)
                out.mkdir(parents=True, exist_ok=True)
                write_json(out / "val_targets.json", targets, indent=None)
                ev = evaluate(path, cfg.dataset, None, out / "val_targets.json")
            else:
                ev = evaluate(path, cfg.dataset, sub.split)
            ev.method = sub.method
            heartbeat(engine, claim, cfg.lease_s, "figure data")
            save_figure_data(ev, out)
            result = {"summary": ev.summary(), "warnings": list(ev.warnings),
                      "object_names": {str(k): report.object_name(k, [ev]) for k in ev.objects},
                      "scene_names": {str(k): v for k, v in ev.scene_labels.items()}}
            if sub.part == "val":
                heartbeat(engine, claim, cfg.lease_s, "per-image errors")
                result["per_image"] = per_image_errors(path, cfg.dataset, targets,
                                                       lambda: heartbeat(engine, claim, cfg.lease_s))
                heartbeat(engine, claim, cfg.lease_s, "conditions")
                result.update(test_extras(ev, Path(cfg.dataset), sub.split, path, None, hidden_frames(cfg.dataset),
                                          targets))
            else:
                heartbeat(engine, claim, cfg.lease_s, "conditions and parts")
                result.update(test_cells(engine, cfg, sub, ev, path))
            versions = current_versions(engine, cfg.dataset, sub.split)
        except TdofError as e:
            if is_resource_error(e):  # (a write that found no room, inside a reader or writer)
                raise
            print(f"worker: submission {sub.uid}: {e}", file=sys.stderr)
            error = FAILED
    finally:
        stop.set()
        beat.join()
    return finish_job(engine, claim, result, error, versions if error is None else None)


def _why(e: BaseException) -> str:
    """One line on a resource error (never a traceback)."""
    text = " ".join(str(getattr(e, "orig", None) or e).split())
    return f"{type(e).__name__}: {text[:200]}"


def run_worker(cfg: ServerConfig, once: bool = False, poll_s: float = 1.0, pause_s: float = 0.0,
               max_jobs: int | None = None, max_wait_s: float = 30.0) -> int:
    """Claim and score jobs until stopped (``once``: until the queue is empty); returns jobs recorded.

    A full disk or a database error (claiming, scoring, writing what the figures are drawn from,
    recording) does not stop the worker and does not count as a try: it gives its job back to the
    queue (:func:`~tdof20.server.db.release_job`; retried until the database takes it, else the
    lease lapses), says so in one line on stderr and waits — ``poll_s``, doubling up to
    ``max_wait_s`` while the trouble lasts — before it claims again. With ``once`` it still stops
    only when the queue is empty, so a job given back is scored once room is freed."""
    store = Store(cfg.data)  # (the folder first: the SQLite file lies in it)
    engine = make_engine(cfg.db_url)
    init_db(engine)
    scorer_version()  # (fixed now, for this process: the scorer it imported, whatever lands on disk later)
    name = f"{socket.gethostname()}:{os.getpid()}"
    done = 0
    wait = 0.0
    pending: Claim | None = None  # a job to give back
    try:
        while max_jobs is None or done < max_jobs:
            claim = None
            try:
                if pending is not None:
                    release_job(engine, pending)
                    pending = None
                claim = claim_job(engine, name, cfg.lease_s)
                if claim is None:
                    if once:
                        break
                    time.sleep(poll_s)
                    continue
                done += score_one(engine, store, cfg, claim, pause_s)
                wait = 0.0
            except Exception as e:
                if not is_resource_error(e):
                    raise
                pending = pending or claim
                wait = min(max_wait_s, max(poll_s, 2 * wait))
                what = f"job of submission {pending.submission_id} given back; " if pending is not None else ""
                print(f"worker: {_why(e)}: {what}waiting {wait:g} s", file=sys.stderr, flush=True)
                time.sleep(wait)
    finally:
        engine.dispose()
    return done


__all__ = ["FAILED", "run_worker", "score_one"]
