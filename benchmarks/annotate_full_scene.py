"""Time of a full-size annotation: one simulated session of 4 arm positions x 400 steps of 0.9 deg
at 640x480, both phases (3,200 frames, the paper's layout), annotated with the exact models.

    python benchmarks/annotate_full_scene.py --dir /tmp/full        # captures DIR/raw once, then reuses it
    python benchmarks/annotate_full_scene.py --dir /tmp/full --stages register
    python benchmarks/annotate_full_scene.py --dir /tmp/full --scene multi/11 --steps 400 --arms 4

What the docs call "the full 3,200-frame scene" (``tdof20 annotate DIR/raw --out DIR/scene
--models DIR/raw/truth/models --force``), run through :func:`tdof20.annotate.pipeline.annotate`
with every stage forced. Printed per stage: wall seconds and the CPU seconds of this process and
every worker process it started (a poller sums the CPU times of the process tree every 0.1 s,
so workers that end between two polls lose at most that much), the registration's own per-arm
figures, the label stage's frames/s, and the evaluation's medians against the simulator's truth
(so a fast wrong answer does not pass), and the peak memory (RSS) of the process tree, of this
process and of its largest worker per stage (polled as the CPU). The load average of the machine
is printed beside the times: the wall times are only comparable on an idle machine, the CPU
times are.
The capture itself takes ~5 min on 2 cores and ~3 GB of disk.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class TreeCPU:
    """CPU seconds (user + system) of this process and all its descendants, polled in a thread:
    the last seen total of every process (also those that ended) is kept; also the peak resident
    memory (RSS) seen of each process and of the whole tree at once."""

    def __init__(self, interval: float = 0.1):
        import psutil

        self.psutil, self.interval = psutil, interval
        self.me = psutil.Process()
        self.seen: dict[tuple[int, float], float] = {}
        self.peak_rss: dict[tuple[int, float], int] = {}
        self.peak_tree_rss = 0
        self._stop = threading.Event()
        self._poll()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _poll(self) -> None:
        ps = self.psutil
        tree = 0
        for p in [self.me] + self.me.children(recursive=True):
            try:
                with p.oneshot():
                    t = p.cpu_times()
                    rss = p.memory_info().rss
                    key = (p.pid, p.create_time())
                self.seen[key] = t.user + t.system
                self.peak_rss[key] = max(self.peak_rss.get(key, 0), rss)
                tree += rss
            except (ps.NoSuchProcess, ps.AccessDenied, ps.ZombieProcess):
                pass
        self.peak_tree_rss = max(self.peak_tree_rss, tree)

    def reset_peaks(self) -> None:
        self.peak_rss.clear()
        self.peak_tree_rss = 0

    def peaks_mib(self) -> tuple[float, float, float]:
        """(peak RSS of the tree, of this process, of the largest worker), MiB, since the last reset."""
        me = max((v for (pid, _), v in self.peak_rss.items() if pid == self.me.pid), default=0)
        worker = max((v for (pid, _), v in self.peak_rss.items() if pid != self.me.pid), default=0)
        return self.peak_tree_rss / 2**20, me / 2**20, worker / 2**20

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._poll()

    def total(self) -> float:
        self._poll()
        return sum(self.seen.values())

    def stop(self) -> None:
        self._stop.set()
        self.thread.join()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, required=True, help="DIR/raw (captured once) and DIR/scene")
    ap.add_argument("--scene", default="multi/11")
    ap.add_argument("--arms", type=int, default=4)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--stages", default=None, help="only these stages (e.g. register, or label,qa); the "
                                                   "stages before must have run into DIR/scene")
    ap.add_argument("--out", default="scene", help="the scene folder's name under DIR")
    args = ap.parse_args()

    from tdof20.annotate.config import AnnotateConfig
    from tdof20.annotate.pipeline import annotate
    from tdof20.annotate.stages import STAGES, parse_stages
    from tdof20.capture import run_capture, sim_config

    raw = args.dir / "raw"
    if not (raw / "session.json").exists():
        t = time.perf_counter()
        run_capture(sim_config(args.scene, steps=args.steps, step_deg=360.0 / args.steps, n_arms=args.arms,
                               width=args.width, height=args.height), raw, yes=True, show_progress=False)
        print(f"captured {args.scene}, {args.arms} x {args.steps} steps at {args.width}x{args.height} in "
              f"{time.perf_counter() - t:.0f} s -> {raw}", flush=True)
    out = args.dir / args.out
    models = raw / "truth" / "models"
    cfg = AnnotateConfig()
    chosen = parse_stages(args.stages)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; cores {os.cpu_count()}", flush=True)
    cpu = TreeCPU()
    rows = []
    t_all, c_all = time.perf_counter(), cpu.total()
    summary = None
    for st in chosen:
        t, c = time.perf_counter(), cpu.total()
        cpu.reset_peaks()
        summary = annotate(raw, out, models, stages=st, cfg=cfg, force=True, progress=False)
        rows.append((st, time.perf_counter() - t, cpu.total() - c, os.getloadavg()[0], cpu.peaks_mib()))
        print(f"  {st:12s} wall {rows[-1][1]:7.1f} s   cpu {rows[-1][2]:7.1f} s   (load {rows[-1][3]:.2f})   "
              "peak RSS: tree {:.0f} MiB, main {:.0f} MiB, largest worker {:.0f} MiB".format(*rows[-1][4]), flush=True)
    wall, cpus = time.perf_counter() - t_all, cpu.total() - c_all
    cpu.stop()
    print(f"  {'all':12s} wall {wall:7.1f} s = {int(wall // 60)} min {wall % 60:.0f} s   cpu {cpus:7.1f} s   "
          f"(load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())})")
    work = out / "work"
    if "register" in chosen:
        reg = json.loads((work / "registration.json").read_text())
        print("  register: " + json.dumps(reg.get("timing_s", {})))
    if "label" in chosen:
        lab = json.loads((work / "label.json").read_text())
        print(f"  label: {lab.get('labelled')} frames, {lab.get('frames_per_s')} frames/s, "
              f"skipped {len(lab.get('skipped', []))}")
    if (work / "evaluation.json").exists() and (set(chosen) & {"qa"}):
        ev = json.loads((work / "evaluation.json").read_text())
        a = ev.get("all", ev)
        keys = [k for k in ("motion_rot_deg", "motion_trans_mm", "surface_mm", "iou_visib") if k in a]
        print("  against the truth (medians): " + ", ".join(f"{k} {a[k]['median']}" for k in keys))
    if summary is not None and summary.get("registration"):
        print(f"  flagged frames: {len(summary['registration'].get('flagged', []))}")
    print(json.dumps({"stages": {r[0]: {"wall_s": round(r[1], 2), "cpu_s": round(r[2], 2),
                                        "peak_rss_mib": {"tree": round(r[4][0]), "main": round(r[4][1]),
                                                         "worker": round(r[4][2])}} for r in rows},
                      "wall_s": round(wall, 2), "cpu_s": round(cpus, 2), "all_stages": list(STAGES)}))


if __name__ == "__main__":
    main()
