"""HFF6DoF efficiency profile (``tdof20 benchmark profile hff6dof [--json]``): parameters,
multiply-adds at 480x640, and latency / FPS on the current device — the network and the pose
recovery (voting + fitting) separately, then end to end.

The pose recovery is timed on a synthetic frame through the same function predict uses
(:func:`tdof20.methods.predict.recover_poses`): ``objects`` segments of ``pixels`` pixels each,
vectors towards 9 keypoints with 30 % outliers. On CUDA the network runs under autocast (bf16
where supported, else fp16), channels-last, with ``torch.backends.cudnn.benchmark``.
"""

from __future__ import annotations

import math
import platform
import statistics
import time

import torch

from tdof20.errors import TdofError
from tdof20.methods.data import N_CLASSES, N_KEYPOINTS, backproject
from tdof20.methods.hff6dof import HFF6DoF, count_macs, count_parameters, fill_depth_holes, geometry_map
from tdof20.methods.predict import DEFAULT_VOTING, recover_poses
from tdof20.methods.train import amp_dtype, select_device


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _median_ms(fn, dev: torch.device, runs: int, warmup: int) -> tuple[float, list[float]]:
    for _ in range(warmup):
        fn()
    _sync(dev)
    times = []
    for _ in range(max(1, runs)):
        t0 = time.perf_counter()
        fn()
        _sync(dev)
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times), times


def synthetic_frame(height: int, width: int, objects: int = 3, pixels: int = 3000, outliers: float = 0.3,
                    seed: int = 0, device: torch.device | str = "cpu") -> dict:
    """A frame for timing the pose recovery: depth (H,W) mm, K, a class map with ``objects``
    square segments of about ``pixels`` pixels, unit vectors (3K,H,W) towards each object's
    keypoints in a known pose (``outliers`` of them random), the keypoint table and the poses."""
    g = torch.Generator().manual_seed(seed)
    H, W = int(height), int(width)
    f = 0.9 * W
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=torch.float32)
    depth = torch.full((H, W), 700.0) + 30.0 * torch.rand(H, W, generator=g)
    side = max(2, int(math.sqrt(pixels)))
    if objects * side > W or side > H:
        raise ValueError(f"{objects} segments of {pixels} pixels do not fit in {W}x{H}")
    classes = torch.zeros(H, W, dtype=torch.long)
    kp_table = torch.full((N_CLASSES, N_KEYPOINTS, 3), float("nan"))
    vec = torch.zeros(N_KEYPOINTS, 3, H, W)
    P = backproject(depth, K)
    poses = {}
    for i in range(objects):
        c = 1 + i
        kp_table[c] = torch.randn(N_KEYPOINTS, 3, generator=g) * 50.0
        kp_table[c, 0] = 0.0
        q = torch.nn.functional.normalize(torch.randn(4, generator=g), dim=0)
        w, x, y, z = q.tolist()
        R = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        v0, u0 = (H - side) // 2, i * (W // objects) + (W // objects - side) // 2
        sl = (slice(v0, v0 + side), slice(u0, u0 + side))
        centre = P[sl].reshape(-1, 3).mean(0)
        t = centre + torch.tensor([0.0, 0.0, 20.0])
        classes[sl] = c
        kp_cam = kp_table[c] @ R.T + t                                    # (K,3)
        d = torch.nn.functional.normalize(kp_cam[:, None, None] - P[sl][None], dim=-1)  # (K,s,s,3)
        bad = torch.rand(side, side, generator=g) < outliers
        rnd = torch.nn.functional.normalize(torch.randn(d.shape, generator=g), dim=-1)
        d = torch.where(bad[None, ..., None], rnd, d)
        vec[:, :, sl[0], sl[1]] = d.permute(0, 3, 1, 2)
        poses[c] = (R, t)
    dev = torch.device(device)
    return {"depth": depth.to(dev), "K": K.to(dev), "classes": classes.to(dev),
            "vec": vec.reshape(3 * N_KEYPOINTS, H, W).to(dev), "kp_table": kp_table.to(dev), "poses": poses}


def profile(device: str = "auto", height: int = 480, width: int = 640, runs: int = 5, *, batch_size: int = 1,
            objects: int = 3, pixels: int = 3000, amp: bool | None = None, warmup: int = 2,
            fuse_stages: int = 3, seg_head: bool = True, voting: str = DEFAULT_VOTING) -> dict:
    """Profile the default HFF6DoF on ``device`` ('auto' = CUDA if present, else CPU).

    Returns {"device", "torch", "parameters", "parameters_M", "macs_480x640", "macs_480x640_G",
    "input" [B,H,W], "amp", "network_ms", "network_ms_runs", "network_fps", "input_prep_ms" (hole
    filling + geometry map of one frame on the device; not part of the end-to-end figure, predict
    does it while loading), "pose": {"objects", "pixels", "ms", "rotation_error_deg",
    "translation_error_mm"}, "end_to_end_ms", "end_to_end_fps"} — latencies are medians of
    ``runs`` runs after ``warmup`` runs; end to end = network + pose recovery per image.
    """
    dev = select_device(device)
    use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")
    torch.manual_seed(0)
    net = HFF6DoF(fuse_stages=fuse_stages, seg_head=seg_head).eval()
    params = count_parameters(net)
    macs = count_macs(net, (480, 640))
    net = net.to(dev)
    rgb = torch.rand(batch_size, 3, height, width, device=dev)
    depth = torch.full((batch_size, height, width), 700.0, device=dev)
    depth[:, ::7] = 0
    K = torch.tensor([[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1]], device=dev)
    geo = geometry_map(depth, K)
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        net = net.to(memory_format=torch.channels_last)
        rgb = rgb.contiguous(memory_format=torch.channels_last)
        geo = geo.contiguous(memory_format=torch.channels_last)

    def forward():
        with torch.inference_mode(), torch.autocast(dev.type, dtype=amp_dtype(dev), enabled=use_amp):
            out = net(rgb, geo)
            out["seg"].argmax(1) if out["seg"] is not None else None

    def prep():
        with torch.inference_mode():
            geometry_map(fill_depth_holes(depth[:1]), K)

    net_ms, net_runs = _median_ms(forward, dev, runs, warmup)
    prep_ms, _ = _median_ms(prep, dev, runs, 1)

    fit = min(height, width // max(1, objects)) ** 2
    if fit < 16:
        raise TdofError(f"{width}x{height} is too small to profile the pose recovery of {objects} objects")
    pixels = min(pixels, fit)  # small inputs: the segments shrink to fit the image
    frame = synthetic_frame(height, width, objects, pixels, device=dev)
    gen = torch.Generator(device=dev).manual_seed(0)
    res_box = []

    def recover():
        with torch.inference_mode():
            res_box.append(recover_poses(frame["classes"][None], frame["vec"][None], frame["depth"][None],
                                         frame["K"][None], frame["kp_table"], min_pixels=10, generator=gen,
                                         voting=voting))

    pose_ms, _ = _median_ms(recover, dev, max(runs, 5), warmup)
    rot_err, tr_err = 0.0, 0.0
    for r in res_box[-1][0]:
        R_gt, t_gt = frame["poses"][r["obj_id"]]
        cos = (torch.trace(torch.as_tensor(r["R"], dtype=torch.float64) @ R_gt.double().T) - 1) / 2
        rot_err = max(rot_err, math.degrees(math.acos(max(-1.0, min(1.0, float(cos))))))
        tr_err = max(tr_err, float((torch.as_tensor(r["t"]) - t_gt.double()).norm()))
    per_image = net_ms / batch_size + pose_ms
    return {
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda"
        else f"{dev.type} ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "torch": torch.__version__,
        "parameters": params, "parameters_M": round(params / 1e6, 3),
        "macs_480x640": macs, "macs_480x640_G": round(macs / 1e9, 3),
        "input": [batch_size, height, width], "amp": use_amp,
        "network_ms": round(net_ms, 3), "network_ms_runs": [round(t, 3) for t in net_runs],
        "network_fps": round(1000 * batch_size / net_ms, 2),
        "input_prep_ms": round(prep_ms, 3),
        "pose": {"voting": voting, "objects": objects, "pixels": pixels, "keypoints": N_KEYPOINTS, "ms": round(pose_ms, 3),
                 "found": len(res_box[-1][0]), "rotation_error_deg": round(rot_err, 4),
                 "translation_error_mm": round(tr_err, 4)},
        "end_to_end_ms": round(per_image, 3), "end_to_end_fps": round(1000 / per_image, 2),
    }


def format_profile(p: dict) -> str:
    """The profile as a few lines of text (what the CLI prints without --json)."""
    return "\n".join([
        f"device          {p['device']} (torch {p['torch']}){', AMP' if p['amp'] else ''}",
        f"parameters      {p['parameters']:,} ({p['parameters_M']} M; paper 56.82 M)",
        f"multiply-adds   {p['macs_480x640_G']} G at 480x640 (paper 85.12 G)",
        f"network         {p['network_ms']:.1f} ms per batch of {p['input'][0]} at {p['input'][1]}x{p['input'][2]}"
        f" -> {p['network_fps']} FPS",
        f"pose recovery   {p['pose']['ms']:.1f} ms for {p['pose']['objects']} objects x {p['pose']['pixels']} px "
        f"({p['pose']['voting']} voting + fitting; max error {p['pose']['rotation_error_deg']:.2f} deg, "
        f"{p['pose']['translation_error_mm']:.2f} mm)",
        f"end to end      {p['end_to_end_ms']:.1f} ms per image -> {p['end_to_end_fps']} FPS "
        f"(input preparation {p['input_prep_ms']:.1f} ms not included)",
    ])
