"""Throughput of the benchmark server's workers and the pages' latency under a queue.

    python benchmarks/server_throughput.py [--images 9139] [--per-phase 4] [--queue 50] [--keep DIR]

Dataset: benchmarks/server_workload.py (score_speed.py's synthetic TDoF20-hard workload: 20 catalog
objects, the 6 hard test scenes sharing ``--images`` 640x480 images of 3-5 objects with ray-cast
depth; 9,139 images is TDoF20-hard's size, about 36,500 targets). ``--keep DIR`` writes it (and the
results file) to DIR once and reuses them on later runs. One results file (rotation errors of ~4
degrees, translation ~9 mm, 3 % of targets missing) is submitted through the HTTP API of a real
``tdof20 serve`` (uvicorn) on loopback, with the SQLite database and the store in a temp folder.
Scoring is the server's: every metric the dataset allows (ADD(-S), 2D projection, VSD, MSSD,
MSPD, AR); figures are drawn by the server when a results page is first opened, not by workers.

1. Scored per minute: ``--per-phase`` submissions queued, then 1 worker process (``serve worker
   --once``) started; the clock runs from the workers' start to the last result (workers' start-up
   included). Then the same with 2 workers. Also the workers' CPU seconds per submission (user +
   system, from the kernel's accounting of the waited-for worker processes), which other load on
   the machine disturbs far less than the wall clock.
2. A scored submission's results page: the first view (draws and caches its figures) and the next.
3. Page latency: ``--queue`` submissions queued, 2 workers scoring, and for ``--latency-s`` seconds
   a client fetches in turn the leaderboard (/), a queued submission's status page (/s/UID), a
   scored one's results page and one of its figures, the API's /api/submissions/UID and the
   caller's list (/api/submissions); p50 and p95 per page.

Prints the 1-minute load average beside each figure (time-sensitive: repeat and take the best).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from server_workload import make, results
from sqlalchemy import func, select

from tdof20.server.client import submit
from tdof20.server.config import ServerConfig
from tdof20.server.db import make_engine, submissions
from tests.test_server_support import CLI, LiveServer


def _done(url: str) -> int:
    engine = make_engine(url)
    try:
        with engine.begin() as c:
            return c.execute(select(func.count()).select_from(submissions).where(
                submissions.c.status == "done")).scalar_one()
    finally:
        engine.dispose()


def _queue(live, csv: Path, n: int, tag: str) -> list[str]:
    """Submit ``n`` public submissions (public: their status pages are open to the timing client)."""
    with ThreadPoolExecutor(max_workers=4) as pool:  # bounded: n uploads, 4 at a time
        return list(pool.map(lambda i: submit(csv, live.url, live.tokens["alice"], f"{tag}-{i}", "hard",
                                              public=True)["uid"], range(n)))


def _cpu_s() -> float:
    """User + system CPU seconds of this process's waited-for children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _get(url: str, headers: dict | None = None) -> float:
    """Seconds to fetch ``url`` whole (an error raises)."""
    req = urllib.request.Request(url, headers=headers or {})
    t = time.perf_counter()
    with urllib.request.urlopen(req, timeout=120) as r:
        r.read()
    return time.perf_counter() - t


def _workers(root: Path, data: Path, n: int, once: bool) -> list[subprocess.Popen]:
    cmd = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--poll", "0.5"]
    return [subprocess.Popen(cmd + (["--once"] if once else []), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            for _ in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=9139)
    ap.add_argument("--per-phase", type=int, default=4, help="submissions scored with 1 and with 2 workers")
    ap.add_argument("--queue", type=int, default=50, help="submissions queued while pages are timed")
    ap.add_argument("--latency-s", type=float, default=30.0)
    ap.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the dataset and results file here")
    a = ap.parse_args()
    print(f"{time.strftime('%Y-%m-%d %H:%M %Z')}: python benchmarks/server_throughput.py {' '.join(sys.argv[1:])}"
          f" ({os.cpu_count()} cores, load {_load()})")
    tmp = tempfile.TemporaryDirectory(prefix="tdof20-server-bench-")
    root = a.keep or Path(tmp.name) / "ds"
    t0 = time.perf_counter()
    info = make(root, a.images)
    print(f"dataset: {a.images} images, {info['targets']} targets ({'reused' if info.get('reused') else 'written'} "
          f"in {time.perf_counter() - t0:.0f} s)")
    csv = root / "method_results.csv" if a.keep else Path(tmp.name) / "method.csv"
    if not csv.is_file():
        csv.write_bytes(results(root, 4.0, 9.0, 0.03))
    print(f"results file: {csv.stat().st_size / 1e6:.1f} MB, {csv.read_text().count(chr(10)) - 1} rows")
    data = Path(tmp.name) / "data"
    with LiveServer(root, data, "--daily-limit", "100000", "--max-uploads", "8") as live:
        db = ServerConfig(dataset=root, data=data).db_url
        headers = {"Authorization": f"Bearer {live.tokens['alice']}"}
        t = time.perf_counter()
        uids = _queue(live, csv, a.per_phase, "w1")
        print(f"upload + strict checks: {(time.perf_counter() - t) / a.per_phase:.2f} s per submission "
              f"(4 at a time), load {_load()}")
        for n_workers in (1, 2):
            if n_workers == 2:
                uids = _queue(live, csv, a.per_phase, "w2")
            before = _done(db)
            load = _load()
            cpu = _cpu_s()
            t = time.perf_counter()
            procs = _workers(root, data, n_workers, once=True)
            for p in procs:
                p.wait()
            dt = time.perf_counter() - t
            cpu = _cpu_s() - cpu
            assert _done(db) - before == len(uids), "not every submission was scored"
            print(f"{n_workers} worker(s): {len(uids)} submissions in {dt:.1f} s = {60 * len(uids) / dt:.2f} scored "
                  f"per minute ({dt / len(uids):.1f} s each; {cpu / len(uids):.1f} CPU s each; "
                  f"load before {load}, after {_load()})")
        first, again = _get(f"{live.url}/s/{uids[0]}"), _get(f"{live.url}/s/{uids[0]}")
        print(f"results page of a scored submission: first view {first:.2f} s (draws its figures), "
              f"then {1e3 * again:.1f} ms (load {_load()})")
        scored_uid = uids[0]
        queued = _queue(live, csv, a.queue, "q")
        procs = _workers(root, data, 2, once=False)
        pages = {"leaderboard /": "/?split=hard", "status /s/UID (queued)": f"/s/{queued[-1]}",
                 "results /s/UID (scored)": f"/s/{scored_uid}",
                 "figure /s/UID/plots/..": f"/s/{scored_uid}/plots/accuracy_add_s.png",
                 "API /api/submissions/UID": f"/api/submissions/{queued[-1]}",
                 "API /api/submissions": "/api/submissions"}
        times: dict[str, list[float]] = {k: [] for k in pages}
        load = _load()
        end = time.monotonic() + a.latency_s
        while time.monotonic() < end:  # bounded by --latency-s
            for name, path in pages.items():
                times[name].append(_get(live.url + path, headers))
        scored = _done(db)
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        print(f"page latency, {a.queue} queued and 2 workers scoring (load {load} -> {_load()}; "
              f"{scored - 2 * a.per_phase} of the queue scored meanwhile):")
        for name, ts in times.items():
            ms = np.array(ts) * 1e3
            print(f"  {name:26s} p50 {np.percentile(ms, 50):7.1f} ms   p95 {np.percentile(ms, 95):7.1f} ms   "
                  f"({len(ms)} requests)")
    tmp.cleanup()


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


if __name__ == "__main__":
    sys.exit(main())
