"""``tdof20 serve worker``: claim a queued submission, score it with the scoring package's
:func:`~tdof20.scoring.evaluate` against the full dataset, write its plots to the store and record
the result — only while the claim is still this worker's (:func:`tdof20.server.db.finish_job`).
A thread renews the lease while the scorer runs; a worker killed mid-score leaves a lease that
expires, and another worker (or this one restarted) scores the submission again from its file.
Any number of workers may run, here or on machines sharing the database and the store."""

from __future__ import annotations

import os
import socket
import sys
import threading
import time

from sqlalchemy import Engine, select

from tdof20.errors import TdofError
from tdof20.scoring import evaluate
from tdof20.scoring import report
from tdof20.server.config import ServerConfig
from tdof20.server.db import Claim, claim_job, finish_job, heartbeat, init_db, make_engine, submissions
from tdof20.server.store import Store

FAILED = "scoring failed; the server's operators have the details"


def _renew(engine: Engine, claim: Claim, lease_s: float, stop: threading.Event) -> None:
    while not stop.wait(lease_s / 3):
        if not heartbeat(engine, claim, lease_s):
            return


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
        result, error = None, None
        try:
            ev = evaluate(store.submission_path(sub.stored), cfg.dataset, sub.split)
            ev.method = sub.method
            heartbeat(engine, claim, cfg.lease_s, "plots")
            out = store.results_dir(sub.uid)
            plots = [p.name for p in report.write_plots([ev], out)]
            result = {"summary": ev.summary(), "plots": plots, "warnings": list(ev.warnings),
                      "object_names": {str(k): report.object_name(k, [ev]) for k in ev.objects},
                      "scene_names": {str(k): v for k, v in ev.scene_labels.items()}}
        except TdofError as e:
            print(f"worker: submission {sub.uid}: {e}", file=sys.stderr)
            error = FAILED
    finally:
        stop.set()
        beat.join()
    return finish_job(engine, claim, result, error)


def run_worker(cfg: ServerConfig, once: bool = False, poll_s: float = 1.0, pause_s: float = 0.0,
               max_jobs: int | None = None) -> int:
    """Claim and score jobs until stopped (``once``: until the queue is empty); returns jobs recorded."""
    store = Store(cfg.data)  # (the folder first: the SQLite file lies in it)
    engine = make_engine(cfg.db_url)
    init_db(engine)
    name = f"{socket.gethostname()}:{os.getpid()}"
    done = 0
    try:
        while max_jobs is None or done < max_jobs:
            claim = claim_job(engine, name, cfg.lease_s)
            if claim is None:
                if once:
                    break
                time.sleep(poll_s)
                continue
            done += score_one(engine, store, cfg, claim, pause_s)
    finally:
        engine.dispose()
    return done


__all__ = ["FAILED", "run_worker", "score_one"]
