"""Simulator throughput: RGB-D frames per second at 640x480 for each phase on a multi-object scene.

    python benchmarks/sim_fps.py [--scene multi/08] [--frames 60] [--width 640 --height 480]

Prints, per phase, the rendering rate (colour + depth, what a capture would grab), and the extra
cost of the exact truth (full masks) and of PNG encoding, as the session writer pays them.
"""

from __future__ import annotations

import argparse
import json
import time

from tdof20.formats.io import encode_png
from tdof20.capture import sim_config
from tdof20.capture.rig import build_rig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="multi/08")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    ap.add_argument("--no-threads", action="store_true", help="render colour and depth one after the other")
    a = ap.parse_args()
    cfg = sim_config(a.scene, width=a.width, height=a.height)
    t = time.perf_counter()
    r = build_rig(cfg).world.renderer
    if a.no_threads:
        r._pool = None
    setup = time.perf_counter() - t
    out = {"scene": a.scene, "objects": len(r.scene.placements), "size": f"{a.width}x{a.height}",
           "setup_s": round(setup, 3)}
    for phase in ("transparent", "opaque"):
        for arm in range(len(r.T_base_cams)):  # warm the per-arm background caches, as a session does
            r.render(arm, 0.0, phase)
        frames = [(k % len(r.T_base_cams), k, k * cfg.turntable.step_deg) for k in range(a.frames)]
        t = time.perf_counter()
        glass_px = 0
        for arm, k, ang in frames:
            glass_px += int((r.render(arm, ang, phase).label >= 0).sum())
        dt = time.perf_counter() - t
        out[f"{phase}_fps"] = round(a.frames / dt, 1)
        out[f"{phase}_object_px"] = glass_px // a.frames
        rendered = [r.render(arm, ang, phase) for arm, k, ang in frames[:20]]
        t = time.perf_counter()
        for f in rendered:
            r.full_masks(f.poses)
        out[f"{phase}_truth_masks_ms"] = round((time.perf_counter() - t) / 20 * 1000, 2)
        t = time.perf_counter()
        for f in rendered:
            encode_png(f.rgb), encode_png(f.depth)
        out[f"{phase}_png_ms"] = round((time.perf_counter() - t) / 20 * 1000, 2)
    if a.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:28s} {v}")


if __name__ == "__main__":
    main()
