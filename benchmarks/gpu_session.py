"""The one prepared run for a lent GPU machine (issue 23 part 10): the GPU tests, every method's
end-to-end FPS at 480x640 (Table 3), training images/s at the gpu preset's size and batch (240x320,
8 images, AMP as train.py uses it on CUDA), one epoch of the gpu preset per method and protocol
(its optimiser steps, counted by ``reproduce.plan``, times the measured step), and the input
pipeline's frames/s with N loader workers (the CPU transform that feeds the GPU).

On the device machine (its python3 holds torch; a package it lacks travels as a wheel, see
/work/.library/device/README.md: this needs only ``isal``, cp312)::

    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \\
        --platform manylinux_2_17_x86_64 -d .whl isal==1.9.1          # once, here (.whl git-ignored)
    run(command="python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl && "
                "PYTHONPATH=/tmp/site:. python3 benchmarks/gpu_session.py --out $OUT", carry=[".whl"], timeout_s=540)

Here, to check the script itself (CPU, small sizes): ``python benchmarks/gpu_session.py --device cpu --quick``.
Budget: ~6-8 min of a 15-minute lease (``--budget-s`` stops starting new measurements past it).
Prints one table last and writes every figure to OUT/gpu_session.json.

What the epoch figure is: steps per epoch x the measured step time of synthetic frames with the
transform done beforehand, i.e. the GPU's side; the input side is the pipeline row (frames/s with
the preset's 8 workers): an epoch takes the longer of the two.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402

from tdof20.experiments.reproduce_config import make_config  # noqa: E402
from tdof20.experiments.reproduce_plan import plan  # noqa: E402
from tdof20.methods.profile import profile, train_speed  # noqa: E402

METHODS = ("hff6dof", "pvnet", "densefusion", "ffb6d")


def steps_per_epoch(preset: str) -> dict[str, dict[str, float]]:
    """{method: {protocol: optimiser steps of one epoch}} of a preset's main runs (reproduce.plan)."""
    out: dict[str, dict[str, float]] = {}
    for r in plan(make_config(preset))["runs"]:
        if r["row"] == f"{r['method']}_{r['split']}" and r["seed"] == 0 and r["epochs"]:
            out.setdefault(r["method"], {})[r["split"]] = r["steps"] / r["epochs"]
    return out


def gpu_tests(timeout_s: int) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_voting.py",
                        "-k", "gpu"], capture_output=True, text=True, timeout=timeout_s)
    tail = (p.stdout + p.stderr).strip().splitlines()[-1:] or [""]
    return {"rc": p.returncode, "summary": tail[0], "seconds": round(time.perf_counter() - t0, 1)}


def pipeline(name: str, workers: list[int], frames: int, preset: str) -> dict:
    from train_throughput import measure
    from train_throughput import preset as preset_sizes

    row = measure(name, preset_sizes(preset), 8, 0, 1, workers, frames, float("nan"), float("nan"), input_only=True)
    return {"transform_ms": row["transform_ms"], "frames_per_s": row["pipeline_frames_per_s"],
            "deferred_frames_per_s": row.get("pipeline_deferred_frames_per_s") or {}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=os.environ.get("OUT", "gpu_session_out"))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--quick", action="store_true", help="small sizes and few repeats: checks the script, not the GPU")
    ap.add_argument("--budget-s", type=float, default=420.0)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    names = [m.strip() for m in a.methods.split(",") if m.strip()]
    H, W, reps, tb, ts = (48, 64, 1, 2, 1) if a.quick else (480, 640, 20, 8, 10)
    frames, workers = (8, [0]) if a.quick else (64, [0, 4, 8, 15])
    res: dict = {"device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else platform.processor(),
                 "torch": torch.__version__, "cuda": torch.version.cuda, "quick": a.quick, "methods": {}}
    res["gpu_tests"] = gpu_tests(120) if torch.cuda.is_available() else {"summary": "no GPU: not run"}
    print(f"GPU tests: {res['gpu_tests']['summary']}", flush=True)
    epochs = steps_per_epoch("gpu")
    for name in names:
        if time.perf_counter() - t_start > a.budget_s:
            res["methods"][name] = {"skipped": "over --budget-s"}
            continue
        r: dict = {}
        for key, fn in (("profile", lambda: profile(name, a.device, H, W, reps, batch_size=1, warmup=2)),
                        ("train", lambda: train_speed(name, a.device, tb, ts,
                                                      image_size=(60, 80) if a.quick else None)),
                        ("pipeline", lambda: pipeline(name, workers, frames, "smoke" if a.quick else "gpu"))):
            t0 = time.perf_counter()
            try:
                r[key] = fn()
            except Exception as e:  # noqa: BLE001 - report it and go on with the next measurement
                r[key] = {"error": f"{type(e).__name__}: {e}"}
            print(f"[{name} {key}: {time.perf_counter() - t0:.0f} s]", flush=True)
        step_s = r["train"].get("step_ms", float("nan")) / 1000.0
        r["epoch_s"] = {split: round(n * step_s, 1) for split, n in epochs.get(name, {}).items()}
        res["methods"][name] = r
        (out / "gpu_session.json").write_text(json.dumps(res, indent=2, default=str))
    res["seconds"] = round(time.perf_counter() - t_start, 1)
    (out / "gpu_session.json").write_text(json.dumps(res, indent=2, default=str))
    print(f"\n{res['device']}, torch {res['torch']}; {'QUICK (script check, not figures)' if a.quick else ''}")
    print(f"{'method':<12} {'e2e FPS':>8} {'net ms':>7} {'train img/s':>11} {'epoch simple':>12} {'epoch hard':>10}  "
          f"pipeline frames/s by workers")
    for name, r in res["methods"].items():
        if "skipped" in r:
            print(f"{name:<12} skipped ({r['skipped']})")
            continue
        p, t = r["profile"], r["train"]
        pipe = r["pipeline"].get("frames_per_s") or r["pipeline"].get("error", "")
        print(f"{name:<12} {p.get('end_to_end_fps', float('nan')):>8.2f} {p.get('network_ms', float('nan')):>7.1f} "
              f"{t.get('images_per_s', float('nan')):>11.1f} {r['epoch_s'].get('simple', float('nan')):>11.0f}s "
              f"{r['epoch_s'].get('hard', float('nan')):>9.0f}s  {pipe}")
    print(f"({res['seconds']:.0f} s in all; {out / 'gpu_session.json'})")


if __name__ == "__main__":
    main()
