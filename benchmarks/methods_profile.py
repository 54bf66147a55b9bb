"""Table 3 for every registered method, and training speed: parameters, multiply-adds at 480x640,
network / pose-recovery / end-to-end latency at 480x640 on this device, and training images/s at
each method's default size (a few optimiser steps: loss + backward + AdamW on synthetic frames).

    python benchmarks/methods_profile.py [--device cpu|cuda] [--methods all|hff6dof,pvnet]
        [--repeats 3] [--batch 1] [--train-batch 2] [--train-steps 3] [--no-train] [--json OUT]

The networks are untrained (random weights): each pose recovery runs on its own network's output
(tdof20.methods.profile explains what is counted). On a GPU also try ``--batch 8`` for throughput.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from tdof20.methods.profile import format_table, profile, train_speed
from tdof20.methods.registry import method_names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--methods", default="all", help="comma-separated registered methods, or all")
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--batch", type=int, default=1, help="images per forward pass (latency: 1)")
    ap.add_argument("--train-batch", type=int, default=2)
    ap.add_argument("--train-steps", type=int, default=3)
    ap.add_argument("--no-train", action="store_true", help="skip the training speed")
    ap.add_argument("--no-amp", action="store_true", help="float32 on CUDA too")
    ap.add_argument("--json", default=None, help="write every figure to this JSON file")
    a = ap.parse_args()
    names = method_names() if a.methods == "all" else [m.strip() for m in a.methods.split(",") if m.strip()]
    amp = False if a.no_amp else None
    rows, speeds = [], []
    for name in names:
        t0 = time.perf_counter()
        try:
            rows.append(profile(name, a.device, a.height, a.width, a.repeats, batch_size=a.batch, warmup=a.warmup,
                                amp=amp))
        except Exception as e:  # noqa: BLE001 - report and go on with the next method
            rows.append({"method": name, "error": f"{type(e).__name__}: {e}"})
        print(f"[{name}: profiled in {time.perf_counter() - t0:.0f} s]", flush=True)
        if not a.no_train:
            t0 = time.perf_counter()
            try:
                speeds.append(train_speed(name, a.device, a.train_batch, a.train_steps, amp=amp))
            except Exception as e:  # noqa: BLE001
                speeds.append({"method": name, "error": f"{type(e).__name__}: {e}"})
            print(f"[{name}: training speed in {time.perf_counter() - t0:.0f} s]", flush=True)
    print(format_table(rows))
    if speeds:
        print("\ntraining (synthetic frames, loss + backward + AdamW; median step after one warm-up step)")
        for s in speeds:
            if "error" in s:
                print(f"{s['method']:<12} error: {s['error']}")
            else:
                print(f"{s['method']:<12} {s['images_per_s']:>8.2f} images/s  batch {s['batch_size']} at "
                      f"{s['image_size'][0]}x{s['image_size'][1]}, {s['step_ms']:.0f} ms/step on {s['device']}"
                      f"{' (AMP)' if s['amp'] else ''}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"profile": rows, "training": speeds, "torch": torch.__version__}, f, indent=2)


if __name__ == "__main__":
    main()
