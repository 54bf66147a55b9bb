"""The server's memory per upload and a worker's memory and CPU for one large submission.

    python benchmarks/server_resources.py [--images 300] [--mb 40] [--uploads 3] [--keep DIR]

Dataset: benchmarks/server_workload.py's synthetic TDoF20-hard workload at ``--images`` images
(``--keep DIR`` writes it once and reuses it). A results file of about ``--mb`` MB: the method's
estimates for every target, repeated with the translation moved by a micrometre per copy (no two
rows alike, so the file passes the strict checks) — a file of many estimates per target, as a
method that reports every hypothesis writes. Then, with a real ``tdof20 serve`` (uvicorn) on
loopback and the SQLite database and the store in a temp folder:

1. the server's resident memory (VmRSS, sampled every 10 ms) while ``--uploads`` such files are
   uploaded at once through the API: its peak over idle, in total and per upload;
   (the token is verified once before: argon2 takes 64 MiB for a moment at a token's first use);
2. one worker process (``serve worker --once``) scoring one of them with every metric the dataset
   allows: its CPU seconds (user + system) and its peak resident memory (ru_maxrss).
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from server_workload import make, results

from tdof20.server.client import submit
from tests.test_server_support import CLI, LiveServer


def big_file(root: Path, path: Path, mb: float) -> int:
    base = results(root, rot_deg=4.0, trans_mm=9.0).decode().splitlines()
    head, rows = base[0], base[1:]
    out, size, k = [head], len(head) + 1, 0
    while size < mb * 1e6:  # bounded: copies until the size is reached
        for r in rows:
            f = r.split(",")
            t = f[5].split()
            t[2] = repr(float(t[2]) + 0.001 * k)
            line = ",".join(f[:5] + [" ".join(t)] + f[6:])
            out.append(line)
            size += len(line) + 1
        k += 1
    path.write_text("\n".join(out) + "\n")
    return len(out) - 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=300)
    ap.add_argument("--mb", type=float, default=40.0)
    ap.add_argument("--uploads", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None)
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="tdof20-res-"))
    root = work / "dataset"
    make(root, a.images)
    csv = work / f"big_{a.mb:g}mb.csv"
    if not csv.is_file():
        n = big_file(root, csv, a.mb)
    else:
        n = sum(1 for _ in open(csv)) - 1
    print(f"results file: {csv.stat().st_size / 1e6:.1f} MB, {n} rows; dataset {a.images} images")
    with tempfile.TemporaryDirectory(prefix="tdof20-res-data-") as tmp:
        data = Path(tmp) / "data"
        with LiveServer(root, data, "--daily-limit", "1000", "--max-uploads", str(a.uploads),
                        "--max-upload", str(64 << 20)) as live:
            import urllib.request

            # the token verified once first (argon2's verification takes 64 MiB for a moment; the
            # server then remembers the token): what is measured is the upload's own memory
            req = urllib.request.Request(f"{live.url}/api/quota",
                                         headers={"Authorization": f"Bearer {live.tokens['alice']}"})
            urllib.request.urlopen(req, timeout=60).read()
            time.sleep(1.0)
            idle = live.rss_mb()
            peak, stop = [idle], threading.Event()

            def sample():
                while not stop.wait(0.01):
                    peak[0] = max(peak[0], live.rss_mb())

            th = threading.Thread(target=sample, daemon=True)
            th.start()
            t0 = time.perf_counter()
            with ThreadPoolExecutor(max_workers=a.uploads) as pool:  # bounded: --uploads at once
                acks = list(pool.map(lambda i: submit(csv, live.url, live.tokens["alice"], f"big{i}", "hard"),
                                     range(a.uploads)))
            wall = time.perf_counter() - t0
            stop.set()
            th.join()
            print(f"server: idle {idle:.0f} MB, peak {peak[0]:.0f} MB during {a.uploads} uploads at once "
                  f"({wall:.1f} s): {peak[0] - idle:.0f} MB over idle, "
                  f"{(peak[0] - idle) / a.uploads:.1f} MB per upload; all {[x['status'] for x in acks]}")
            worker = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--once"]
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            # one worker, one submission (the others withdrawn first)
            for x in acks[1:]:
                req = urllib.request.Request(f"{live.url}/api/submissions/{x['uid']}/withdraw", method="POST",
                                             headers={"Authorization": f"Bearer {live.tokens['alice']}"})
                urllib.request.urlopen(req, timeout=60).read()
            p = subprocess.run(worker, capture_output=True, text=True, timeout=3600)
            wall = time.perf_counter() - t0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            print(f"worker: {p.stdout.strip()} in {wall:.1f} s wall, {cpu:.1f} CPU s, "
                  f"peak RSS {after.ru_maxrss / 1024:.0f} MB (rc {p.returncode})")
            if p.returncode:
                print(p.stderr[-2000:], file=sys.stderr)


if __name__ == "__main__":
    main()
