"""Simulated capture throughput, and the capture driver's own overhead per frame, at 640x480.

    python benchmarks/capture_throughput.py [--steps 40] [--arms 2]

1. throughput: `capture run --sim` end to end (render, write, journal; truth/ timed separately);
2. driver overhead: the same runner with a camera that hands back one pre-rendered frame at once,
   so what remains per frame is the driver's own work — journal line (fsync), checksums, two
   atomic PNG writes, progress. Target: <= 20 ms per frame.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from tdof20.capture import run_capture, sim_config
from tdof20.capture.hardware.interfaces import RGBDFrame
from tdof20.capture.rig import build_rig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="multi/08")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--arms", type=int, default=2)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    a = ap.parse_args()
    cfg = sim_config(a.scene, steps=a.steps, step_deg=360.0 / a.steps, n_arms=a.arms, width=a.width, height=a.height)
    tmp = Path(tempfile.mkdtemp(prefix="tdof20-bench-"))
    try:
        rig = build_rig(cfg)
        after = rig.after_capture
        rig.after_capture = None
        t = time.perf_counter()
        s = run_capture(cfg, tmp / "full", yes=True, show_progress=False, rig=rig)
        capture_s = time.perf_counter() - t
        t = time.perf_counter()
        after(tmp / "full", False)
        truth_s = time.perf_counter() - t
        n = s.captured
        print(f"frames                       {n} ({a.width}x{a.height}, {a.scene})")
        print(f"capture_fps                  {n / capture_s:.1f}   (render + write + journal)")
        print(f"truth_ms_per_frame           {truth_s / (n / 2) * 1000:.1f}   (masks, poses, depth of the transparent phase)")

        rig = build_rig(cfg)
        rig.after_capture = None
        f = rig.world.renderer.render(0, 0.0, "transparent")
        rig.camera.grab = lambda timeout_s: RGBDFrame(f.rgb, f.depth, time.time(), time.time())
        t = time.perf_counter()
        s = run_capture(cfg, tmp / "overhead", yes=True, show_progress=True, rig=rig)
        dt = time.perf_counter() - t
        print(f"driver_overhead_ms_per_frame {dt / s.captured * 1000:.1f}   (journal + checksums + PNG writes + progress; target <= 20)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
