"""Table 3 for every registered method, and training speed: parameters, multiply-adds at 480x640,
network / pose-recovery / end-to-end latency at 480x640 on this device, and training images/s at
each method's default size (a few optimiser steps: loss + backward + AdamW on synthetic frames).

    python benchmarks/methods_profile.py [--device cpu|cuda] [--methods all|hff6dof,pvnet]
        [--repeats 3] [--batch 1] [--train-batch 2] [--train-steps 3] [--no-train] [--json OUT]

The networks are untrained (random weights): each pose recovery runs on its own network's output
(tdof20.methods.profile explains what is counted). On a GPU also try ``--batch 8`` for throughput.

How long a ``tdof20 reproduce`` preset takes, estimated (issue 15 part 2):

    python benchmarks/methods_profile.py --estimate cpu [--json OUT] [--measure-batch 2]
        [--gpu-tflops 50 150] [--gpu-workers N] [--units EARLIER.json]

measures, on this device, at the preset's sizes and with its method options: a few optimiser
steps of each method at its training image size and batch (train_speed), the prediction of one
image (input transform + network + pose recovery, profile_method) at the training size and at
Table 3's size, and the simulated dataset per frame (capture + oracle labels + build of one single-
and one multi-object scene, 1 arm x 2 steps at the preset's capture size); then multiplies them by
the counts of reproduce.plan (optimiser steps per run, validation and test images per
prediction, frames). For a GPU that is not here, ``--gpu-tflops`` adds an estimate from the
measured multiply-adds: a training step = 3 x forward FLOPs (2 per multiply-add) x batch at that
many effective TFLOPS, or the input pipeline (the measured CPU transform x batch / --gpu-workers)
if slower; a prediction likewise with 1 x forward (pose recovery at the CPU's measured time). Those
are assumptions, stated as such in the output. ``--units`` reuses the unit costs of an earlier
``--json`` (e.g. after changing a preset's epochs or data, not its sizes).
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from tdof20.methods.profile import format_table, profile, train_speed
from tdof20.methods.registry import method_names


def _frame_seconds(cfg) -> tuple[float, int]:
    """CPU seconds (this process and its children) per simulated frame of the preset's data (capture
    both phases + oracle labels + dataset build), measured on one single- and one multi-object
    scene, 1 arm position x 2 steps at the preset's capture size."""
    import dataclasses
    import resource
    import tempfile
    from pathlib import Path

    from tdof20.experiments.reproduce import _sim_dataset

    def cpu() -> float:
        a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    d = dataclasses.replace(cfg.data, scenes=("single/juice_cup_340", "multi/08"), steps=2, step_deg=10.0, n_arms=1)
    small = dataclasses.replace(cfg, data=d)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = cpu()
        _sim_dataset(Path(tmp), small, False)
        dt = cpu() - t0
    frames = 2 * len(d.scenes) * d.n_arms * d.steps
    return dt / frames, frames


def _thread_ms(fn, repeats: int, warmup: int = 1) -> float:
    """Median CPU milliseconds of this thread per call of ``fn`` (with one torch thread: the work
    itself, whatever else the machine runs)."""
    import statistics

    for _ in range(warmup):
        fn()
    runs = []
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        runs.append(1000 * (time.thread_time() - t0))
    return statistics.median(runs)


def unit_costs(name: str, cfg, image_size, batch_size: int, steps: int = 2, repeats: int = 2,
               measure_batch: int | None = None) -> dict:
    """One torch thread, CPU milliseconds: an optimiser step at ``image_size`` x ``batch_size``
    (synthetic frames of 3 objects, 20 object classes; measured at ``measure_batch`` images and
    scaled linearly to ``batch_size`` when given: the memory of a full batch at 480x640 does not fit
    a small machine), the input transform of one frame, the network and the whole prediction
    (untrained: its pose recovery on whatever the untrained segmentation claims, an upper bound) of
    one frame, and the forward multiply-adds."""
    mb = min(int(batch_size), int(measure_batch or batch_size))
    from tdof20.methods.profile import count_macs, example_batch, synthetic_item, synthetic_meta
    from tdof20.methods.registry import get_method

    m = get_method(name)
    meta = synthetic_meta(20, image_size)
    torch.manual_seed(0)
    net = m.build(cfg, meta).train()
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    batch = example_batch(m, cfg, meta, mb, train=True)

    def step():
        total, _ = m.loss(net, batch, cfg, meta)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()

    step_ms = _thread_ms(step, steps) * batch_size / mb
    del batch, opt
    net.eval()
    one = example_batch(m, cfg, meta, 1)
    tf = m.transform(cfg, meta, train=False)
    item = synthetic_item(meta, seed=0)
    input_ms = _thread_ms(lambda: tf(item), repeats)

    def forward():
        with torch.inference_mode():
            m.forward(net, one)

    def predict():
        with torch.inference_mode():
            m.predict_poses(net, one, cfg, meta)

    net_ms = _thread_ms(forward, repeats)
    e2e_ms = _thread_ms(predict, repeats)
    macs = count_macs(m, cfg, meta, one)
    return {"step_ms": round(step_ms, 1), "measured_batch": mb, "input_ms": round(input_ms, 1),
            "network_ms": round(net_ms, 1),
            "pose_ms": round(max(0.0, e2e_ms - net_ms), 1), "predict_ms": round(input_ms + e2e_ms, 1),
            "macs_G": round(macs / 1e9, 3)}


#: wall speed-up of two torch threads on two idle cores over one (an assumption, stated in the output)
TWO_CORE_SPEEDUP = 1.7


def estimate_preset(preset: str, tflops: list[float], workers: int | None = None, measure_batch: int | None = None,
                    units_from: str | None = None) -> dict:
    """Unit costs measured on this CPU with one torch thread (CPU time, robust to other jobs), multiplied
    out by reproduce.estimate; a 2-core wall estimate; and GPU estimates from assumed throughput
    (``workers``: data-loader processes, default the preset's train.num_workers). ``units_from``: a
    JSON this wrote before (the same image size, batch and method options): its unit costs are
    reused instead of measured again."""
    import os

    from tdof20.experiments.reproduce import estimate, make_config
    from tdof20.methods.registry import get_method

    torch.set_num_threads(1)
    cfg = make_config(preset)
    h, w = cfg.train.image_size
    bs = cfg.train.batch_size
    workers = int(workers or cfg.train.num_workers)
    load0 = os.getloadavg()
    units, prof_s = {}, 0.0
    if units_from:
        old = json.loads(open(units_from).read())
        if old["train"] != {"image_size": [h, w], "batch_size": bs}:
            raise SystemExit(f"{units_from}: measured at {old['train']}, the preset trains at {[h, w]} x {bs}")
        units = old["units"]
        prof_s = old["estimate_cpu_s"]["profile_s"]
    for name in ([] if units_from else cfg.methods):
        mcfg = get_method(name).config_from(cfg.method_options.get(name, {}), "")
        t0 = time.perf_counter()
        units[name] = unit_costs(name, mcfg, (h, w), bs, steps=1 if h * w > 200_000 else 2,
                                 measure_batch=measure_batch)
        if cfg.profile.enabled:  # Table 3: timing at the profile size (multiply-adds counted on the meta device)
            pu = unit_costs(name, mcfg, (cfg.profile.height, cfg.profile.width), 1, steps=1, repeats=1) \
                if (cfg.profile.height, cfg.profile.width) != (h, w) else units[name]
            units[name]["profile_predict_ms"] = pu["predict_ms"]
            prof_s += (cfg.profile.repeats + 2) * pu["predict_ms"] / 1000
        print(f"[{name}: {units[name]} measured in {time.perf_counter() - t0:.0f} s]", flush=True)
    frame_s, n_frames = (old["frame_s"], old["frames_measured"]) if units_from else _frame_seconds(cfg)
    step_s = {k: u["step_ms"] / 1000 for k, u in units.items()}
    image_s = {k: u["predict_ms"] / 1000 for k, u in units.items()}
    est = estimate(cfg, step_s, image_s, frame_s, prof_s)
    out = {"preset": preset, "threads": 1, "train": {"image_size": [h, w], "batch_size": bs}, "units": units,
           "frame_s": round(frame_s, 4), "frames_measured": n_frames, "load_before": load0,
           "load_after": os.getloadavg(), "estimate_cpu_s": est,
           "two_core_speedup_assumed": TWO_CORE_SPEEDUP,
           "two_core_wall_s": round(est["total_s"] / TWO_CORE_SPEEDUP, 1)}
    gpu = []
    for tf in tflops:  # assumptions, not measurements
        g_step, g_img = {}, {}
        for name, u in units.items():
            fwd = 2e9 * u["macs_G"]
            g_step[name] = max(3 * fwd * bs / (tf * 1e12), u["input_ms"] / 1000 * bs / workers)
            g_img[name] = max(fwd / (tf * 1e12), u["input_ms"] / 1000 / workers) + u["pose_ms"] / 1000
        g = estimate(cfg, g_step, g_img, frame_s / max(1, workers), 0.0)
        gpu.append({"tflops": tf, "workers": workers, "total_s": g["total_s"], "train_s": g["train_s"],
                    "val_s": g["val_s"], "test_s": g["test_s"], "dataset_s": g["dataset_s"],
                    "step_ms": {k: round(1000 * v, 2) for k, v in g_step.items()}})
    out["gpu_assumed"] = gpu
    return out


def _hours(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.1f} min"


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
    ap.add_argument("--estimate", default=None, metavar="PRESET",
                    help="estimate how long tdof20 reproduce --preset PRESET takes (see the module doc)")
    ap.add_argument("--gpu-tflops", type=float, nargs="*", default=[50.0, 150.0],
                    help="with --estimate: effective TFLOPS assumed for a GPU estimate (none: skip)")
    ap.add_argument("--gpu-workers", type=int, default=None,
                    help="with --estimate: data-loader workers assumed on a GPU (default: the preset's num_workers)")
    ap.add_argument("--units", default=None, metavar="JSON",
                    help="with --estimate: reuse the unit costs of an earlier --json instead of measuring them")
    ap.add_argument("--measure-batch", type=int, default=None,
                    help="with --estimate: measure a training step at this many images and scale to the preset's batch")
    a = ap.parse_args()
    if a.estimate:
        r = estimate_preset(a.estimate, a.gpu_tflops, a.gpu_workers, a.measure_batch, a.units)
        e = r["estimate_cpu_s"]
        print(f"preset {a.estimate}, measured with one torch thread as CPU time (load {r['load_before'][0]:.1f} -> "
              f"{r['load_after'][0]:.1f}): {_hours(e['total_s'])} of CPU = dataset {_hours(e['dataset_s'])} "
              f"({e['plan']['frames']} frames x {r['frame_s']:.3f} s) + training {_hours(e['train_s'])} + validation "
              f"{_hours(e['val_s'])} + test {_hours(e['test_s'])} + Table 3 {_hours(e['profile_s'])}; on 2 idle cores "
              f"~{_hours(r['two_core_wall_s'])} of wall (assuming {r['two_core_speedup_assumed']}x from 2 threads)")
        for m, u in r["units"].items():
            runs = [x for x in e["per_run"] if x["method"] == m]
            print(f"  {m:<12} {u['step_ms']:>9.0f} ms/step (measured at {u['measured_batch']} images) x {sum(x['steps'] for x in runs)} steps "
                  f"({len(runs)} runs); {u['predict_ms']:>7.0f} ms/image (input {u['input_ms']:.0f}, network "
                  f"{u['network_ms']:.0f}, pose {u['pose_ms']:.0f}) x "
                  f"{sum(x['test_images'] + x['val_predictions'] * x['val_images'] for x in runs)} images; "
                  f"{u['macs_G']} G multiply-adds at {r['train']['image_size'][0]}x{r['train']['image_size'][1]}")
        for g in r["gpu_assumed"]:
            print(f"  assumed GPU at {g['tflops']:g} effective TFLOPS, {g['workers']} loader workers: "
                  f"{_hours(g['total_s'])} (dataset {_hours(g['dataset_s'])} on {g['workers']} CPU workers, training "
                  f"{_hours(g['train_s'])}, validation {_hours(g['val_s'])}, test {_hours(g['test_s'])})")
        if a.json:
            with open(a.json, "w") as f:
                json.dump(r, f, indent=2)
        return
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
