"""Where the scorer's CPU goes on one results file: ``evaluate()`` in this process, every metric.

    python benchmarks/scoring_profile.py DATASET [RESULTS.csv] [--split hard] [--metrics M] [--profile OUT.prof]

DATASET: a dataset the scorer reads, e.g. one kept by ``benchmarks/server_throughput.py --keep DIR``
(RESULTS defaults to DIR/method_results.csv). Prints the CPU seconds (user + system of this process,
all threads) and the wall time of ``evaluate()``, its peak resident memory (ru_maxrss, the imports
included), the scorer's own ``timings`` (read, match, metrics, bop and the BOP metrics' parts) and
per object the ADD(-S) stages' seconds summed over objects. ``--profile OUT`` writes a cProfile
of the call (read it with ``python -m pstats OUT``) and prints its top 25 by cumulative time.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("results", type=Path, nargs="?")
    ap.add_argument("--split", default="hard")
    ap.add_argument("--metrics", default=None)
    ap.add_argument("--profile", type=Path, default=None)
    a = ap.parse_args()
    path = a.results or a.dataset / "method_results.csv"
    c0, t0 = _cpu(), time.perf_counter()
    from tdof20.scoring import evaluate

    imp = _cpu() - c0
    c0, t0 = _cpu(), time.perf_counter()
    prof = cProfile.Profile() if a.profile else None
    if prof:
        prof.enable()
    ev = evaluate(path, a.dataset, a.split, metrics=a.metrics)
    if prof:
        prof.disable()
    cpu, wall = _cpu() - c0, time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    s = ev.summary()
    print(f"{time.strftime('%Y-%m-%d %H:%M')}: python benchmarks/scoring_profile.py {' '.join(sys.argv[1:])} "
          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '-')}, load {'/'.join(f'{x:.1f}' for x in os.getloadavg())})")
    print(f"evaluate: {ev.n_rows} rows, {s['all']['n']} targets: {cpu:.1f} CPU s, {wall:.1f} s wall "
          f"(import {imp:.1f} CPU s), peak RSS {rss:.0f} MB")
    print("timings: " + ", ".join(f"{k} {v:.2f}" for k, v in ev.timings.items()))
    st: dict[str, float] = {}
    for o in ev.objects.values():
        for k, v in (o.stages or {}).items():
            if k.startswith("t_"):
                st[k] = st.get(k, 0.0) + v
    print("ADD(-S) stages (s, summed over objects): " + ", ".join(f"{k[2:]} {v:.2f}" for k, v in st.items()))
    print("summary all: " + ", ".join(f"{k} {v:.4f}" for k, v in s["all"].items() if k != "n"))
    if prof:
        prof.dump_stats(a.profile)
        pstats.Stats(prof).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
