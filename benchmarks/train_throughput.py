"""Training at the hardware's limit (issue 23 part 8): per method, training images/s at a preset's
image size beside the FLOP-bound rate on this machine, the input transform's share of a step, the
input pipeline's frames/s with N DataLoader workers, and (``--wait-policy``) why epochs of one
training once differed tenfold.

    python benchmarks/train_throughput.py [--preset cpu|gpu|full] [--methods all|hff6dof,pvnet]
        [--batch N] [--steps 3] [--repeats 2] [--workers 0,1,2] [--frames 16] [--concurrent 2] [--wait-policy] [--json OUT]

What is measured, on the CPU (every figure is the best of ``--repeats``: the machine is shared):

- GEMM rate: a float32 ``torch.matmul`` of two 2048x2048 matrices with torch's intra-op threads as
  training uses them (``torch.get_num_threads()``): multiply-adds/s.
- multiply-adds per training image: torch's FlopCounterMode over the loss's forward (the method's
  own training forward: DenseFusion's crop + estimator, FFB6D's RandLA-Net with its indices, ...) of
  a batch of synthetic frames (:func:`tdof20.methods.profile.synthetic_item`) through the method's
  training transform, / 2 / batch. The FLOP-bound rate = GEMM rate / (3 x that): forward +
  backward ~ 3 x forward (the counter's own forward + backward count is printed beside it, ``bwd/fwd``).
  Element-wise work, normalisation, KNN, sorting are not counted: for the dense CNNs the bound
  is tight, for point networks it flatters.
- training images/s: optimiser steps (loss + backward + AdamW) on that batch, the transform done
  beforehand (the network alone); ``% bound`` = images/s / FLOP-bound rate; ``%cpu-t`` the same
  ratio with both the GEMM and the steps timed in CPU seconds of this process (all its threads),
  which a shared machine disturbs less than wall time.
- transform: the method's training transform of one frame at the preset's capture size (one
  thread, as a loader worker runs it); ``input %`` = transform x batch / (that + step): the input
  side's share of a step without workers (with workers it overlaps the step).
- pipeline frames/s: a DataLoader over a shard of ``--frames`` synthetic frames (written in the
  shard format, :mod:`tdof20.dataset.shards`) through the transform, with each ``--workers``
  count, nothing else running in this process.
- ``--concurrent N``: N trainings at once, one thread each, in N fresh processes (what ``tdof20
  reproduce --executor ray`` does with a local instance: one CPU per training job), each running
  the same timed steps started together at a barrier: their images/s summed, against the same
  FLOP-bound rate (the GEMM rate with all of torch's threads). On this 2-core machine a small
  network at a small size uses the two cores far better as two one-thread trainings than as one
  two-thread training: mkldnn's convolutions on 3x4 to 48x64 feature maps scale poorly across
  threads, while on one thread they run near the GEMM rate.
- ``--wait-policy``: a few HFF6DoF steps in two fresh processes, OMP_WAIT_POLICY=ACTIVE (libgomp
  spinning at every barrier: what torch did before train.py / the CLI set PASSIVE) and PASSIVE,
  each with torch's default threads: wall and CPU seconds per step. On a 2-core machine shared with
  anything else, ACTIVE took 10x the CPU time and wall time per step: the cause of the demo's
  tenfold epoch-to-epoch variation.

The load average (``uptime``) is printed beside the figures: on a loaded machine they are a floor.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as training runs (tdof20.methods.train)

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from tdof20.dataset.shards import SHARD_DTYPES, ShardDataset  # noqa: E402
from tdof20.experiments.reproduce_config import PRESETS  # noqa: E402
from tdof20.methods.data import TransformedDataset, collate, worker_init  # noqa: E402
from tdof20.methods.profile import synthetic_item, synthetic_meta  # noqa: E402
from tdof20.methods.registry import get_method, method_names  # noqa: E402
from tdof20.methods.train import make_method_config  # noqa: E402

METHODS = ("hff6dof", "pvnet", "densefusion", "ffb6d")


def load() -> float:
    return round(os.getloadavg()[0], 2)


def best_s(fn, repeats: int, warmup: int = 1, clock=time.perf_counter) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return min(times)


def gemm_macs_per_s(n: int = 2048, repeats: int = 5, clock=time.perf_counter) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    return n ** 3 / best_s(lambda: torch.matmul(a, b), repeats, warmup=2, clock=clock)


def preset(name: str) -> dict:
    p = PRESETS[name]
    return {"image_size": tuple(p["train"]["image_size"]), "batch_size": int(p["train"]["batch_size"]),
            "capture": (int(p["data"]["height"]), int(p["data"]["width"])),
            "options": p.get("method_options", {})}


def write_shard(path: Path, items: list[dict]) -> Path:
    """A shard in the documented format (tdof20.dataset.shards) holding ``items`` (synthetic frames)."""
    n, m = len(items), max(len(it["obj_id"]) for it in items)
    with h5py.File(path, "w") as f:
        def put(name, arr, dtype):
            f.create_dataset(name, data=np.stack(arr).astype(dtype), chunks=(1, *arr[0].shape), compression="lzf")
        put("rgb", [it["rgb"].permute(1, 2, 0).numpy() for it in items], SHARD_DTYPES["rgb"])
        put("depth", [it["depth"].numpy().clip(0, 65535).round() for it in items], SHARD_DTYPES["depth"])
        put("depth_restored", [it["depth_restored"].numpy().round() for it in items], SHARD_DTYPES["depth_restored"])
        put("label", [it["label"].numpy() for it in items], SHARD_DTYPES["label"])
        put("instance", [it["instance"].numpy() for it in items], SHARD_DTYPES["instance"])
        obj = np.zeros((n, m), np.int16)
        R = np.zeros((n, m, 3, 3), np.float32)
        t = np.zeros((n, m, 3), np.float32)
        for j, it in enumerate(items):
            g = len(it["obj_id"])
            obj[j, :g], R[j, :g], t[j, :g] = it["obj_id"].numpy(), it["R"].numpy(), it["t"].numpy()
        for name, arr in (("obj_id", obj), ("R", R), ("t", t), ("visib_fract", np.ones((n, m), np.float32)),
                          ("K", np.stack([it["K"].numpy() for it in items])), ("depth_scale", np.ones(n, np.float32)),
                          ("scene_id", np.ones(n, np.int32)), ("im_id", np.arange(n, dtype=np.int32))):
            f.create_dataset(name, data=arr)
    return path


def pipeline_fps(data, batch_size: int, workers: int, repeats: int) -> float:
    """Frames/s of a DataLoader over ``data`` (one pass, workers started beforehand: persistent)."""
    loader = torch.utils.data.DataLoader(data, batch_size=batch_size, num_workers=workers, collate_fn=collate,
                                         worker_init_fn=worker_init, persistent_workers=workers > 0)

    def one_pass():
        for _ in loader:
            pass

    return len(data) // batch_size * batch_size / best_s(one_pass, repeats, warmup=1)


def deferrable(tf):
    """The transform's ``defer_to_device`` (its dense part batched on the training device, as
    train.py runs it on a GPU), or None. HFF6DoF's wrapper forwards it once hff6dof_method.py does;
    until then its inner HFFTransform's is measured."""
    return getattr(tf, "defer_to_device", None) or getattr(getattr(tf, "inner", None), "defer_to_device", None)


def measure(name: str, pre: dict, batch_size: int, steps: int, repeats: int, workers: list[int], frames: int,
            gemm: float, gemm_cpu: float, input_only: bool = False) -> dict:
    m = get_method(name)
    cfg = make_method_config(m, None, pre["options"].get(name, {}))
    meta = synthetic_meta(20, pre["image_size"])
    tf = m.transform(cfg, meta, train=True)
    raw = [synthetic_item(meta, pre["capture"], seed=i) for i in range(max(frames, batch_size))]
    row = {"method": name, "image_size": list(pre["image_size"]), "capture": list(pre["capture"]),
           "batch_size": batch_size}
    if not input_only:
        row.update(_network(m, cfg, meta, tf, raw, batch_size, steps, repeats, gemm, gemm_cpu))

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as a loader worker (tdof20.methods.data.worker_init)
    try:
        tf_s = best_s(lambda: tf(raw[0]), repeats)
        light = m.transform(cfg, meta, train=True)
        defer = deferrable(light)
        if defer is not None:
            stage = defer()
            row["deferred_cpu_ms"] = round(1000 * best_s(lambda: light(raw[0]), repeats), 2)
            batch = collate([light(r) for r in raw[:batch_size]])
            row["deferred_stage_ms_per_frame_on_cpu"] = round(1000 * best_s(lambda: stage(batch), repeats)
                                                              / batch_size, 2)
    finally:
        torch.set_num_threads(threads)
    row["transform_ms"] = round(1000 * tf_s, 2)
    if "step_s" in row:
        row["input_share_percent"] = round(100 * tf_s * batch_size / (tf_s * batch_size + row["step_s"]), 1)
    row["pipeline_frames_per_s"], row["pipeline_deferred_frames_per_s"] = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        shard = ShardDataset(write_shard(Path(tmp) / "bench.h5", raw[:frames]))
        for key, t in (("pipeline_frames_per_s", tf), ("pipeline_deferred_frames_per_s", light if defer else None)):
            if t is not None:
                for w in workers:
                    row[key][str(w)] = round(pipeline_fps(TransformedDataset(shard, t), batch_size, w, repeats), 2)
    return row


def _network(m, cfg, meta, tf, raw, batch_size, steps, repeats, gemm, gemm_cpu) -> dict:
    """Multiply-adds per image (FlopCounterMode), training images/s and their share of the bound."""
    torch.manual_seed(0)
    batch = collate([tf(raw[i]) for i in range(batch_size)])
    torch.manual_seed(0)
    net = m.build(cfg, meta).train()
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=True)  # as train.py on the CPU
    with FlopCounterMode(display=False) as fwd:
        total, _ = m.loss(net, batch, cfg, meta)
    with FlopCounterMode(display=False) as both:
        total, _ = m.loss(net, batch, cfg, meta)
        total.backward()
    opt.zero_grad(set_to_none=True)
    macs = fwd.get_total_flops() / 2 / batch_size
    bwd_ratio = both.get_total_flops() / max(1, fwd.get_total_flops())

    def train_steps():
        for _ in range(steps):
            loss, _ = m.loss(net, batch, cfg, meta)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    step_s = best_s(train_steps, repeats) / steps
    step_cpu_s = best_s(train_steps, repeats, warmup=0, clock=time.process_time) / steps
    ips = batch_size / step_s
    bound = gemm / (3 * macs) if macs else float("nan")
    return {"macs_per_image_G": round(macs / 1e9, 4), "bwd_fwd_ratio": round(bwd_ratio, 2),
            "step_s": round(step_s, 4), "images_per_s": round(ips, 3), "flop_bound_images_per_s": round(bound, 3),
            "percent_of_bound": round(100 * ips / bound, 1) if macs else None,
            # the same ratio in CPU seconds (this process's, all its threads): steadier on a shared machine
            "step_cpu_s": round(step_cpu_s, 4),
            "percent_of_bound_cpu_time": round(100 * 3 * macs * batch_size / step_cpu_s / gemm_cpu, 1)
            if macs else None}


STEP_SCRIPT = r"""
import os, resource, sys, time, torch
from tdof20.methods.profile import example_batch, synthetic_meta
from tdof20.methods.registry import get_method
m = get_method("hff6dof"); cfg = m.default_config(); meta = synthetic_meta(20, (60, 80))
torch.manual_seed(0)
net = m.build(cfg, meta).train(); opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
batch = example_batch(m, cfg, meta, 4, train=True)
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
out = []
for s in range(int(sys.argv[1])):
    w, c = time.perf_counter(), cpu()
    loss, _ = m.loss(net, batch, cfg, meta); opt.zero_grad(set_to_none=True); loss.backward(); opt.step()
    out.append((time.perf_counter() - w, cpu() - c))
print(torch.get_num_threads(), *[f"{a:.3f},{b:.3f}" for a, b in out[1:]])
"""


def _concurrent_worker(name: str, pre: dict, batch_size: int, steps: int, repeats: int, barrier, out) -> None:
    """One of ``--concurrent``'s trainings (a spawned process, one thread): wall seconds per timed run."""
    torch.set_num_threads(1)
    m = get_method(name)
    cfg = make_method_config(m, None, pre["options"].get(name, {}))
    meta = synthetic_meta(20, pre["image_size"])
    tf = m.transform(cfg, meta, train=True)
    torch.manual_seed(0)
    batch = collate([tf(synthetic_item(meta, pre["capture"], seed=i)) for i in range(batch_size)])
    net = m.build(cfg, meta).train()
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=True)

    def train_steps():
        for _ in range(steps):
            loss, _ = m.loss(net, batch, cfg, meta)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    train_steps()  # warm-up
    walls = []
    for _ in range(repeats):
        barrier.wait()
        t0 = time.perf_counter()
        train_steps()
        walls.append(time.perf_counter() - t0)
    out.put(walls)


def concurrent(name: str, pre: dict, batch_size: int, steps: int, repeats: int, n: int, gemm: float,
               macs: float) -> dict:
    """``n`` one-thread trainings of ``name`` at once: summed images/s (best of ``repeats``) and its
    share of the FLOP-bound rate."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(n), ctx.Queue()
    env_before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"  # the children's OpenMP pools, set before they start
    try:
        procs = [ctx.Process(target=_concurrent_worker, args=(name, pre, batch_size, steps, repeats, barrier, out))
                 for _ in range(n)]
        for p in procs:
            p.start()
        walls = [out.get() for _ in procs]
        for p in procs:
            p.join()
    finally:
        if env_before is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = env_before
    best = min(max(w[r] for w in walls) for r in range(repeats))  # the slowest process of the best run
    ips = n * batch_size * steps / best
    bound = gemm / (3 * macs)
    return {"processes": n, "images_per_s": round(ips, 3), "percent_of_bound": round(100 * ips / bound, 1)}


def wait_policy(steps: int = 4) -> dict:
    """HFF6DoF steps at the demo's 60x80, batch 4, in a fresh process per OMP_WAIT_POLICY."""
    out = {}
    for policy in ("ACTIVE", "PASSIVE"):
        env = dict(os.environ, OMP_WAIT_POLICY=policy)
        env.pop("OMP_NUM_THREADS", None)
        before = load()
        res = subprocess.run([sys.executable, "-c", STEP_SCRIPT, str(steps + 1)], env=env, capture_output=True,
                             text=True, check=True)
        threads, *pairs = res.stdout.split()
        wall = [float(p.split(",")[0]) for p in pairs]
        cpu = [float(p.split(",")[1]) for p in pairs]
        out[policy] = {"threads": int(threads), "wall_s": wall, "cpu_s": cpu, "load": [before, load()]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="cpu", choices=sorted(PRESETS))
    ap.add_argument("--methods", default="all")
    ap.add_argument("--batch", type=int, default=None, help="images per step (default: the preset's)")
    ap.add_argument("--steps", type=int, default=3, help="optimiser steps per timed run")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workers", default="0,1,2", help="DataLoader worker counts for the pipeline's frames/s")
    ap.add_argument("--frames", type=int, default=16, help="frames in the pipeline's shard")
    ap.add_argument("--concurrent", type=int, default=0,
                    help="also N trainings at once, one thread each (reproduce --executor ray's way): summed images/s")
    ap.add_argument("--wait-policy", action="store_true", help="also compare OMP_WAIT_POLICY ACTIVE vs PASSIVE")
    ap.add_argument("--input-only", action="store_true",
                    help="the input side only (no training steps): for the gpu/full presets' sizes on a CPU")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    a = ap.parse_args()
    pre = preset(a.preset)
    names = METHODS if a.methods == "all" else tuple(get_method(x.strip()).name for x in a.methods.split(","))
    names = tuple(n for n in names if n in method_names())
    bs = a.batch or pre["batch_size"]
    workers = [int(w) for w in a.workers.split(",") if w.strip()]
    gemm = max(gemm_macs_per_s() for _ in range(a.repeats))
    gemm_cpu = max(gemm_macs_per_s(clock=time.process_time) for _ in range(a.repeats))  # per CPU-second
    result = {"preset": a.preset, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "torch": torch.__version__,
              "gemm_gmacs_per_s": round(gemm / 1e9, 2), "gemm_gmacs_per_cpu_s": round(gemm_cpu / 1e9, 2), "rows": []}
    print(f"preset {a.preset}: train {pre['image_size'][0]}x{pre['image_size'][1]} from {pre['capture'][0]}x"
          f"{pre['capture'][1]} frames, batch {bs}; torch {torch.__version__}, {result['threads']} threads of "
          f"{result['cpus']} CPUs; GEMM {gemm / 1e9:.1f} G multiply-adds/s, {gemm_cpu / 1e9:.1f} G per CPU-second "
          f"(load {load()})")
    head = (f"{'method':<12} {'GMAC/img':>9} {'bwd/fwd':>7} {'img/s':>7} {'bound':>7} {'%bound':>7} {'%cpu-t':>7} "
            f"{'tf ms':>7} {'input%':>7}  pipeline frames/s by workers   load")
    print(head)
    print("-" * len(head))
    for name in names:
        before = load()
        try:
            row = measure(name, pre, bs, a.steps, a.repeats, workers, a.frames, gemm, gemm_cpu, a.input_only)
        except Exception as e:  # noqa: BLE001 - one method's failure must not hide the others' figures
            row = {"method": name, "error": f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:120]}"}
            print(f"{name:<12} error: {row['error']}")
            result["rows"].append(row)
            continue
        row["load_before"], row["load_after"] = before, load()
        result["rows"].append(row)
        pipe = ", ".join(f"{w}: {v}" for w, v in row["pipeline_frames_per_s"].items())
        if "step_s" in row:
            print(f"{name:<12} {row['macs_per_image_G']:>9.3f} {row['bwd_fwd_ratio']:>7.2f} {row['images_per_s']:>7.2f} "
                  f"{row['flop_bound_images_per_s']:>7.2f} {row['percent_of_bound']:>6.1f}% "
                  f"{row['percent_of_bound_cpu_time']:>6.1f}% {row['transform_ms']:>7.1f} "
                  f"{row['input_share_percent']:>6.1f}%  {pipe:<28} {before}-{row['load_after']}")
        else:
            print(f"{name:<12} {'(input only)':>64} {row['transform_ms']:>7.1f} {'':>7}  {pipe:<28} "
                  f"{before}-{row['load_after']}")
        if a.concurrent > 0 and "step_s" in row:
            row["concurrent"] = concurrent(name, pre, bs, a.steps, a.repeats, a.concurrent, gemm,
                                           row["macs_per_image_G"] * 1e9)
            c = row["concurrent"]
            print(f"{'':<12} {c['processes']} trainings at once, one thread each: {c['images_per_s']:.2f} img/s in all "
                  f"= {c['percent_of_bound']:.1f}% of the bound (load {load()})")
        if "deferred_cpu_ms" in row:
            dpipe = ", ".join(f"{w}: {v}" for w, v in row["pipeline_deferred_frames_per_s"].items())
            print(f"{'':<12} deferred dense part (train.py on a GPU): CPU part {row['deferred_cpu_ms']} ms/frame, "
                  f"dense stage {row['deferred_stage_ms_per_frame_on_cpu']} ms/frame on this CPU (batched; on the "
                  f"GPU in training); pipeline frames/s {dpipe}")
    print("bound = GEMM rate / (3 x multiply-adds per image); %cpu-t = the same in CPU seconds (GEMM and steps); "
          "input% = transform x batch / (that + step), without workers; best of", a.repeats)
    if a.wait_policy:
        wp = wait_policy()
        result["wait_policy"] = wp
        for policy, r in wp.items():
            print(f"OMP_WAIT_POLICY={policy:<8} {r['threads']} threads: wall s/step {r['wall_s']}, CPU s/step "
                  f"{r['cpu_s']} (load {r['load'][0]}-{r['load'][1]})")
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
