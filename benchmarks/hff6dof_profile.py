"""HFF6DoF efficiency profile: parameters, multiply-adds at 480x640, network latency, and voting +
fitting latency, on the current device (CUDA if available unless --device says otherwise).

    python benchmarks/hff6dof_profile.py [--device cpu|cuda] [--runs 3] [--pixels 5000] [--json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch

from tdof20.methods.fitting import kabsch_torch
from tdof20.methods.hff6dof import HFF6DoF, count_macs, count_parameters
from tdof20.methods.voting import vote_keypoints_batched


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _time(fn, dev: torch.device, runs: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    _sync(dev)
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        _sync(dev)
        out.append(time.perf_counter() - t0)
    return out


def _synthetic_object(n: int, k: int, outliers: float, dev: torch.device, n_objects: int):
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(n_objects, n, 3, generator=g), dim=-1)
    pts = d * torch.tensor([50.0, 35.0, 25.0]) + torch.tensor([0.0, 0.0, 650.0])
    kp = torch.randn(n_objects, k, 3, generator=g) * 30 + torch.tensor([0.0, 0.0, 650.0])
    vec = torch.nn.functional.normalize(kp[:, None] - pts[:, :, None], dim=-1)
    rnd = torch.nn.functional.normalize(torch.randn(vec.shape, generator=g), dim=-1)
    bad = torch.rand(n_objects, n, 1, 1, generator=g) < outliers
    vec = torch.where(bad, rnd, vec)
    return pts.to(dev), vec.to(dev), kp.to(dev)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--amp", action="store_true", help="bf16/fp16 autocast on CUDA")
    ap.add_argument("--channels-last", action="store_true")
    ap.add_argument("--pixels", type=int, default=5000, help="object pixels for voting")
    ap.add_argument("--keypoints", type=int, default=9)
    ap.add_argument("--objects", type=int, default=1, help="instances voted together (batched)")
    ap.add_argument("--n-hyp", type=int, default=128)
    ap.add_argument("--outliers", type=float, default=0.3)
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    a = ap.parse_args()
    dev = torch.device(a.device)
    torch.manual_seed(0)

    net = HFF6DoF(n_keypoints=a.keypoints).eval()
    params = count_parameters(net)
    macs = count_macs(net, (480, 640))
    net = net.to(dev)
    if a.channels_last:
        net = net.to(memory_format=torch.channels_last)
    rgb = torch.rand(a.batch, 3, a.height, a.width, device=dev)
    geo = torch.randn(a.batch, 6, a.height, a.width, device=dev)
    if a.channels_last:
        rgb, geo = rgb.contiguous(memory_format=torch.channels_last), geo.contiguous(memory_format=torch.channels_last)
    amp_dtype = torch.bfloat16 if dev.type == "cuda" and torch.cuda.is_bf16_supported() else torch.float16

    def forward():
        with torch.inference_mode(), torch.autocast(dev.type, dtype=amp_dtype, enabled=a.amp and dev.type == "cuda"):
            net(rgb, geo)

    t_net = _time(forward, dev, a.runs, a.warmup)

    pts, vec, kp = _synthetic_object(a.pixels, a.keypoints, a.outliers, dev, a.objects)
    model_kp = kp - kp.mean(1, keepdim=True)
    gen = torch.Generator(device=dev).manual_seed(0)
    err = []

    def recover():
        est, _ = vote_keypoints_batched(pts, vec, n_hyp=a.n_hyp, generator=gen)
        kabsch_torch(model_kp, est)
        err.append(float((est - kp).norm(dim=-1).max()))

    t_pose = _time(recover, dev, max(a.runs, 5), a.warmup)
    net_ms = 1000 * statistics.median(t_net)
    pose_ms = 1000 * statistics.median(t_pose)
    res = {
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "torch": torch.__version__,
        "parameters": params,
        "parameters_M": round(params / 1e6, 3),
        "macs_480x640": macs,
        "macs_480x640_G": round(macs / 1e9, 3),
        "input": [a.batch, a.height, a.width],
        "amp": bool(a.amp and dev.type == "cuda"),
        "network_ms": round(net_ms, 2),
        "network_ms_runs": [round(1000 * t, 2) for t in t_net],
        "network_fps": round(1000 * a.batch / net_ms, 2),
        "pose_recovery": {"pixels": a.pixels, "keypoints": a.keypoints, "objects": a.objects, "n_hyp": a.n_hyp,
                          "outliers": a.outliers, "ms": round(pose_ms, 2),
                          "max_keypoint_error_mm": round(max(err), 4)},
        "end_to_end_fps": round(1000 * a.batch / (net_ms + pose_ms * a.batch), 2),
    }
    if a.json:
        print(json.dumps(res, indent=2))
        return
    print(f"device            {res['device']}  (torch {res['torch']})")
    print(f"parameters        {params:,}  ({res['parameters_M']} M; paper 56.82 M)")
    print(f"multiply-adds     {res['macs_480x640_G']} G at 480x640  (paper 85.12 G)")
    print(f"network           {net_ms:.1f} ms per batch of {a.batch} at {a.height}x{a.width}"
          f"  ({res['network_fps']} FPS; runs {res['network_ms_runs']})")
    print(f"voting + Kabsch   {pose_ms:.2f} ms for {a.objects} object(s) x {a.pixels} px x {a.keypoints} keypoints,"
          f" {a.n_hyp} hypotheses, {int(100 * a.outliers)}% outliers (max error {max(err):.3f} mm)")
    print(f"end to end        {res['end_to_end_fps']} FPS")


if __name__ == "__main__":
    main()
