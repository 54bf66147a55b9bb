"""Table 3 for every method (``tdof20 benchmark profile METHOD|all [--json]``): parameters,
multiply-adds at 480x640, and latency / FPS on this device — the network alone, the pose recovery
apart, and end to end — beside the paper's figures and the original implementations' parameter
counts.

    p = profile("pvnet", device="cpu", height=480, width=640, repeats=5)     # one method: a dict
    table = profile("all")                                                   # every registered method
    print(format_table(table))

What is measured, for a registered method (:mod:`tdof20.methods.registry`) built from its default
config for TDoF20's 20 objects (21 classes; a synthetic :class:`MethodMeta`: the counts depend
only on the number of classes and keypoints):

- parameters: every parameter of the module ``build`` returns (for DenseFusion: segmentation net +
  estimator + refiner);
- multiply-adds: torch's FlopCounterMode (convolutions, matrix products, ...) / 2, over one
  forward pass (``Method.forward``) of one 480x640 image, on PyTorch's meta device (shapes only;
  a real forward when an operation has no meta kernel); element-wise work, interpolation, KNN and
  sorting are not counted;
- network latency: ``Method.forward`` on a batch of ``batch_size`` synthetic frames;
- end to end: ``Method.predict_poses`` (network + pose recovery) on the same batch; pose recovery
  = end to end - network. The network is *untrained* (random weights): the pose recovery works on
  its own predicted output, so its time depends on how many objects the untrained segmentation
  claims (``poses`` in the result says how many poses came back);
- repeats stop early once a measurement has spent :data:`TIME_BUDGET_S` (after one timed run): a
  measurement that takes minutes on a CPU is timed once;
- input preparation: the method's transform of one frame on the CPU (DataLoader workers do it
  during predict; not part of end to end).

On CUDA: autocast (bf16 where supported, else fp16) unless ``amp=False``, channels-last weights,
``cudnn.benchmark``. Latencies are medians of ``repeats`` runs after ``warmup`` runs.
"""

from __future__ import annotations

import math
import platform
import statistics
import time
from collections.abc import Mapping, Sequence
from contextlib import nullcontext

import numpy as np
import torch

from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.data import collate
from tdof20.methods.registry import Method, get_method, method_names
from tdof20.methods.devices import amp_dtype, select_device

#: Table 3's input size
TABLE3_SIZE = (480, 640)
#: the paper's GPU for its FPS
PAPER_GPU = "GTX 1080Ti"
#: TDoF20's objects (the meta the profile builds every method for)
TDOF20_OBJECTS = 20


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


#: a measurement stops repeating (and warming up) once it has spent this long (s), after one timed run
TIME_BUDGET_S = 60.0


def _median_ms(fn, dev: torch.device, repeats: int, warmup: int, budget_s: float = TIME_BUDGET_S
               ) -> tuple[float, list[float]]:
    t_start = time.perf_counter()
    for _ in range(max(0, warmup)):
        fn()
        if time.perf_counter() - t_start > budget_s:
            break
    _sync(dev)
    times = []
    t_start = time.perf_counter()
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        fn()
        _sync(dev)
        times.append(1000 * (time.perf_counter() - t0))
        if time.perf_counter() - t_start > budget_s:
            break
    return statistics.median(times), times


def device_name(dev: torch.device) -> str:
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    return f"{dev.type} ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


# --------------------------------------------------------------------------------------------
# synthetic inputs


def synthetic_meta(n_objects: int = TDOF20_OBJECTS, image_size: Sequence[int] = TABLE3_SIZE, seed: int = 0,
                   n_keypoints: int = 9, n_model_points: int = 500) -> MethodMeta:
    """A meta of ``n_objects`` made-up objects (ids 1..n, about 100 mm across, keypoints centre
    first): what profiling needs without building catalog meshes."""
    rng = np.random.default_rng(seed)
    ids = tuple(range(1, int(n_objects) + 1))
    kps, pts = {}, {}
    for o in ids:
        p = rng.normal(size=(n_model_points, 3))
        p = 50.0 * p / np.linalg.norm(p, axis=1, keepdims=True) * np.array([1.0, 0.8, 1.2])
        pts[o] = p
        kps[o] = np.concatenate([np.zeros((1, 3)), p[rng.choice(len(p), n_keypoints - 1, replace=False)]])
    return MethodMeta(obj_ids=ids, keypoints=kps, diameters={o: 120.0 for o in ids},
                      symmetric={o: o % 2 == 0 for o in ids}, model_points=pts,
                      image_size=tuple(int(v) for v in image_size))


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def synthetic_item(meta: MethodMeta, hw: Sequence[int] | None = None, n_objects: int = 3, seed: int = 0,
                   holes: float = 0.6) -> dict:
    """A dataset item (the layout transforms take, with labels) of a made-up frame at ``hw``
    (default ``meta.image_size``): ``n_objects`` of the meta's objects as discs 600 mm away in front
    of a plane at 800 mm, in random poses centred on the discs; the restored depth is a dome over
    each disc, the sensor depth loses ``holes`` of the object pixels (glass) and is noisy. For
    timing and for checking that a method's pieces run — not a faithful rendering."""
    H, W = (int(v) for v in (hw or meta.image_size))
    rng = np.random.default_rng(seed)
    f = 0.9 * W
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    n = max(1, min(int(n_objects), len(meta.obj_ids)))
    objs = [meta.obj_ids[i] for i in rng.choice(len(meta.obj_ids), n, replace=False)]
    v, u = np.mgrid[:H, :W].astype(np.float64)
    restored = np.full((H, W), 800.0)
    label = np.zeros((H, W), np.int64)
    inst = np.zeros((H, W), np.int64)
    r = max(2.0, 0.07 * W)
    R = np.zeros((n, 3, 3))
    t = np.zeros((n, 3))
    for i, o in enumerate(objs):
        uc, vc = (i + 0.5) * W / n, H / 2 + 0.1 * H * (-1) ** i
        d2 = ((u - uc) ** 2 + (v - vc) ** 2) / r ** 2
        disc = d2 < 1
        restored = np.where(disc, 600.0 - 30.0 * (1 - d2), restored)
        label[disc], inst[disc] = o, i + 1
        R[i] = _rotation(rng)
        t[i] = np.array([(uc - K[0, 2]) * 620.0 / f, (vc - K[1, 2]) * 620.0 / f, 620.0])
    depth = restored + rng.normal(0, 2.0, (H, W))
    depth[(label > 0) & (rng.random((H, W)) < holes)] = 0.0
    rgb = np.clip(60 + 40 * rng.random((3, H, W)) + 120 * (label > 0)[None] * rng.random((3, 1, 1)), 0, 255)
    return {"rgb": torch.from_numpy(rgb.astype(np.uint8)), "depth": torch.from_numpy(depth.astype(np.float32)),
            "depth_restored": torch.from_numpy(restored.astype(np.float32)),
            "K": torch.from_numpy(K.astype(np.float32)), "scene_id": 1, "im_id": int(seed),
            "label": torch.from_numpy(label), "instance": torch.from_numpy(inst),
            "obj_id": torch.tensor(objs, dtype=torch.int64), "R": torch.from_numpy(R.astype(np.float32)),
            "t": torch.from_numpy(t.astype(np.float32))}


def example_batch(method: Method, cfg, meta: MethodMeta, batch_size: int = 1, train: bool = False,
                  n_objects: int = 3) -> dict:
    """A collated batch of ``batch_size`` synthetic frames through the method's transform, merged
    with the module's own ``example_batch`` (e.g. DenseFusion's crop inputs) when it has one."""

    tf = method.transform(cfg, meta, train=train)
    batch = collate([tf(synthetic_item(meta, n_objects=n_objects, seed=i)) for i in range(int(batch_size))])
    if not train:
        own = method.example_batch(cfg, meta, batch_size)
        if own:
            batch = {**batch, **own}
    return batch


def to_device(batch: Mapping, dev: torch.device) -> dict:
    return {k: v.to(dev, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


# --------------------------------------------------------------------------------------------
# counting


def count_parameters(net: torch.nn.Module) -> int:
    """Every parameter (buffers such as BatchNorm statistics not included)."""
    return sum(p.numel() for p in net.parameters())


def count_macs(method: Method, cfg, meta: MethodMeta, batch: Mapping, net: torch.nn.Module | None = None) -> int:
    """Multiply-adds of one ``Method.forward`` of ``batch``: FlopCounterMode's FLOPs / 2 on a copy of
    the network built on the meta device (shapes only); when an operation has no meta kernel, a
    real forward of ``net`` (built here if None) under ``torch.no_grad``."""
    from torch.utils.flop_counter import FlopCounterMode

    try:
        with torch.device("meta"):
            mnet = method.build(cfg, meta)
        mnet.eval()
        mb = {k: torch.empty_like(v, device="meta") if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        with FlopCounterMode(display=False) as fc, torch.no_grad():
            method.forward(mnet, mb)
        return int(fc.get_total_flops()) // 2
    except Exception:  # noqa: BLE001 - an op without a meta kernel (or data-dependent): count for real
        pass
    if net is None:
        net = method.build(cfg, meta)
    was = net.training
    net.eval()
    try:
        dev = next(net.parameters()).device
        with FlopCounterMode(display=False) as fc, torch.no_grad():
            method.forward(net, to_device(batch, dev))
    finally:
        net.train(was)
    return int(fc.get_total_flops()) // 2


# --------------------------------------------------------------------------------------------
# profile


def profile_method(name: str, device: str = "auto", height: int = 480, width: int = 640, repeats: int = 5, *,
                   batch_size: int = 1, amp: bool | None = None, warmup: int = 2, n_objects: int = TDOF20_OBJECTS,
                   cfg=None, macs_size: Sequence[int] | None = TABLE3_SIZE) -> dict:
    """Profile one registered method on ``device`` at ``height`` x ``width`` (see the module doc).

    Returns {"method", "description", "inputs", "device", "torch", "parameters", "parameters_M",
    "macs_480x640", "macs_480x640_G" (at ``macs_size``, None to skip), "input" [B,H,W], "amp",
    "network_ms", "network_ms_runs", "network_fps", "pose_ms", "end_to_end_ms", "end_to_end_fps",
    "poses" (rows predict_poses returned for the batch), "input_ms" (the transform of one frame, CPU),
    "untrained": True, "paper": {...}, "original": {...}}.
    """
    method = get_method(name)
    if min(int(height), int(width)) < 16 or int(batch_size) < 1 or int(repeats) < 1:
        raise TdofError("profile needs height and width >= 16, batch size and repeats >= 1")
    dev = select_device(device)
    use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")
    cfg = method.default_config() if cfg is None else cfg
    meta = synthetic_meta(n_objects, (height, width))
    torch.manual_seed(0)
    net = method.build(cfg, meta).eval()
    params = count_parameters(net)
    batch = example_batch(method, cfg, meta, batch_size)
    macs = None
    if macs_size is not None:
        mh, mw = (int(v) for v in macs_size)
        if (mh, mw) == (int(height), int(width)) and batch_size == 1:
            macs = count_macs(method, cfg, meta, batch, net)
        else:
            m_meta = synthetic_meta(n_objects, (mh, mw))
            macs = count_macs(method, cfg, m_meta, example_batch(method, cfg, m_meta, 1))

    tf = method.transform(cfg, meta, train=False)
    item = synthetic_item(meta, seed=0)
    input_ms, _ = _median_ms(lambda: tf(item), torch.device("cpu"), min(3, int(repeats)), 0)

    net = net.to(dev)
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        net = net.to(memory_format=torch.channels_last)
    dbatch = to_device(batch, dev)

    def autocast():
        return torch.autocast(dev.type, dtype=amp_dtype(dev)) if use_amp else nullcontext()

    def forward():
        with torch.inference_mode(), autocast():
            method.forward(net, dbatch)

    rows_box: list = []

    def predict():
        with torch.inference_mode(), autocast():
            rows_box.append(method.predict_poses(net, dbatch, cfg, meta))

    net_ms, net_runs = _median_ms(forward, dev, repeats, warmup)
    e2e_ms, e2e_runs = _median_ms(predict, dev, repeats, min(1, warmup))
    pose_ms = max(0.0, e2e_ms - net_ms)
    B = int(batch_size)
    return {
        "method": method.name, "description": method.description, "inputs": method.inputs,
        "device": device_name(dev), "torch": torch.__version__,
        "parameters": params, "parameters_M": round(params / 1e6, 3),
        "macs_480x640": macs, "macs_480x640_G": None if macs is None else round(macs / 1e9, 3),
        "macs_size": None if macs_size is None else [int(v) for v in macs_size],
        "input": [B, int(height), int(width)], "amp": use_amp,
        "network_ms": round(net_ms, 3), "network_ms_runs": [round(t, 3) for t in net_runs],
        "network_fps": round(1000 * B / net_ms, 2),
        "pose_ms": round(pose_ms, 3), "end_to_end_ms": round(e2e_ms, 3),
        "end_to_end_ms_runs": [round(t, 3) for t in e2e_runs],
        "end_to_end_fps": round(1000 * B / e2e_ms, 2) if e2e_ms > 0 else math.inf,
        "poses": len(rows_box[-1]) if rows_box else 0, "input_ms": round(input_ms, 3), "untrained": True,
        "paper": dict(method.paper), "original": dict(method.original), "notes": method.notes,
    }


def profile(method: str = "hff6dof", device: str = "auto", height: int = 480, width: int = 640, repeats: int = 5,
            **kw) -> dict | list[dict]:
    """:func:`profile_method` of one method, or of every registered one for ``method='all'`` (a
    list; a method that fails gets {"method", "error"} instead of stopping the table)."""
    if str(method).strip().lower() != "all":
        return profile_method(method, device, height, width, repeats, **kw)
    select_device(device)  # a bad --device is one error, not one per method
    out = []
    for name in method_names():
        try:
            out.append(profile_method(name, device, height, width, repeats, **kw))
        except TdofError as e:
            out.append({"method": name, "error": str(e)})
        except Exception as e:  # noqa: BLE001 - one broken method must not hide the others' figures
            out.append({"method": name, "error": f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:160]}"})
    return out


# --------------------------------------------------------------------------------------------
# text


def _paper_text(p: dict) -> tuple[str, str, str]:
    paper, orig = p.get("paper") or {}, p.get("original") or {}
    par = []
    if "parameters_M" in paper:
        par.append(f"paper {paper['parameters_M']} M")
    if "parameters_M" in orig and orig.get("parameters_M") != paper.get("parameters_M"):
        par.append(f"original {orig['parameters_M']} M")
    macs = f"paper {paper['macs_G']} G" if "macs_G" in paper else "paper: none"
    fps = f"paper {paper['fps']} FPS on a {paper.get('gpu', PAPER_GPU)}" if "fps" in paper else ""
    return "; ".join(par) or "paper: none", macs, fps


def format_profile(p: dict) -> str:
    """One method's profile as a few lines (what the CLI prints without --json)."""
    if "error" in p:
        return f"{p['method']:<12} error: {p['error']}"
    par, macs, fps = _paper_text(p)
    size = "x".join(str(v) for v in (p.get("macs_size") or TABLE3_SIZE))
    lines = [
        f"{p['method']} ({p['inputs']}) on {p['device']} (torch {p['torch']}){', AMP' if p['amp'] else ''}",
        f"  parameters      {p['parameters']:,} ({p['parameters_M']} M; {par})",
        "  multiply-adds   " + (f"{p['macs_480x640_G']} G at {size} ({macs})" if p["macs_480x640_G"] is not None
                                 else "not counted"),
        f"  network         {p['network_ms']:.1f} ms per batch of {p['input'][0]} at {p['input'][1]}x{p['input'][2]}"
        f" -> {p['network_fps']} FPS",
        f"  pose recovery   {p['pose_ms']:.1f} ms ({p['poses']} poses from the untrained network's own output)",
        f"  end to end      {p['end_to_end_ms']:.1f} ms -> {p['end_to_end_fps']} FPS"
        + (f" ({fps})" if fps else "") + f"; input preparation {p['input_ms']:.1f} ms (CPU) not included",
    ]
    if p.get("notes"):
        lines.append(f"  notes           {p['notes']}")
    if (p.get("original") or {}).get("source"):
        lines.append(f"  original        {p['original']['source']}")
    return "\n".join(lines)


def format_table(rows: Sequence[dict]) -> str:
    """Table 3 for all methods: one line per method, then the paper's figures and notes."""
    head = (f"{'method':<12} {'input':<5} {'params M':>9} {'MACs G':>8} {'net ms':>9} {'pose ms':>9} "
            f"{'e2e ms':>9} {'FPS':>7}   paper / original")
    lines = [head, "-" * len(head)]
    dev = None
    for p in rows:
        if "error" in p:
            lines.append(f"{p['method']:<12} error: {p['error']}")
            continue
        dev = dev or f"{p['device']} (torch {p['torch']}){', AMP' if p['amp'] else ''}, batch {p['input'][0]} at " \
                     f"{p['input'][1]}x{p['input'][2]}"
        par, macs, fps = _paper_text(p)
        mg = "-" if p["macs_480x640_G"] is None else f"{p['macs_480x640_G']:.2f}"
        lines.append(f"{p['method']:<12} {p['inputs']:<5} {p['parameters_M']:>9.2f} {mg:>8} {p['network_ms']:>9.1f} "
                     f"{p['pose_ms']:>9.1f} {p['end_to_end_ms']:>9.1f} {p['end_to_end_fps']:>7.2f}   "
                     + "; ".join(x for x in (par, macs, fps) if x))
    if dev:
        lines.append(f"on {dev}; untrained networks (pose recovery on their own output); multiply-adds at "
                     f"{TABLE3_SIZE[0]}x{TABLE3_SIZE[1]}, FlopCounterMode / 2")
    for p in rows:
        if "error" not in p:
            note = "; ".join(x for x in (p.get("notes"), (p.get("original") or {}).get("source")) if x)
            if p.get("poses") == 0:
                note += "; the untrained network found no object: its pose recovery was not exercised"
            if note:
                lines.append(f"  {p['method']}: {note}")
    return "\n".join(lines)


def train_speed(name: str, device: str = "auto", batch_size: int = 2, steps: int = 3, image_size=None,
                amp: bool | None = None, n_objects: int = TDOF20_OBJECTS, cfg=None) -> dict:
    """Training images/s of a method: ``steps`` optimiser steps (loss + backward + AdamW) on a batch
    of synthetic frames at ``image_size`` (default: the method's), after one warm-up step.
    Returns {"method", "device", "image_size", "batch_size", "steps", "step_ms", "images_per_s", "loss"}."""
    method = get_method(name)
    dev = select_device(device)
    use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")
    hw = tuple(int(v) for v in (image_size or method.default_image_size))
    cfg = method.default_config() if cfg is None else cfg
    meta = synthetic_meta(n_objects, hw)
    torch.manual_seed(0)
    net = method.build(cfg, meta).to(dev).train()
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=dev.type in ("cpu", "cuda"))  # as train.py
    batch = to_device(example_batch(method, cfg, meta, batch_size, train=True), dev)
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp and amp_dtype(dev) == torch.float16)
    last = [float("nan")]

    def step():
        with torch.autocast(dev.type, dtype=amp_dtype(dev)) if use_amp else nullcontext():
            total, _ = method.loss(net, batch, cfg, meta)
        opt.zero_grad(set_to_none=True)
        scaler.scale(total).backward()
        scaler.step(opt)
        scaler.update()
        last[0] = float(total.detach())

    ms, _ = _median_ms(step, dev, steps, 1)
    return {"method": method.name, "device": device_name(dev), "image_size": list(hw),
            "batch_size": int(batch_size), "steps": int(steps), "amp": use_amp, "step_ms": round(ms, 2),
            "images_per_s": round(1000 * int(batch_size) / ms, 2), "loss": last[0]}


__all__ = ["count_macs", "count_parameters", "example_batch", "format_profile", "format_table", "profile",
           "profile_method", "synthetic_item", "synthetic_meta", "train_speed"]
