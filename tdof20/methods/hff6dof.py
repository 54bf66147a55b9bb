"""HFF6DoF: hierarchical feature fusion of an RGB and a geometry ResNet34 (paper sections 3.1-3.3).

Architecture (defaults; stage table in :mod:`tdof20.methods.resnet`)::

    rgb (B,3,H,W) ──ResNet34──▶ stem, layer1, layer2, layer3, layer4
    geo (B,6,H,W) ──ResNet34──▶ stem, layer1, layer2, layer3, layer4
    for each of the last `fuse_stages` stages s:  F_s = Fuse_s(cat(rgb_s, geo_s))
            Fuse_s = 1x1 conv (2C -> C) + BN + ReLU, 3x3 conv (C -> C) + BN + ReLU
    decoder (U-Net-like, bilinear up-sampling x2 per stage):
        x = Center(F_layer4)                          two 3x3 convs at 1/32
        for s = layer3, layer2, layer1, stem:  x = Up(x); x = cat(x, F_s) if s is fused; two 3x3 convs
        x = Up(x) to H,W; one 3x3 conv
    heads (1x1 convs at full resolution):
        seg: D -> hidden -> n_classes logits           (only with seg_head)
        vec: D -> hidden -> 3K, normalised to a unit 3D vector per keypoint

``fuse_stages`` = 1..5 fuses the last N of (stem, layer1, layer2, layer3, layer4): 1 = layer4 only,
3 = layer2..layer4 (the paper's default), 5 = all five. The decoder widths do not depend on it; only
the skip inputs do. The default widths were tuned so that the default network (fuse_stages=3,
seg_head=True, 21 classes, 9 keypoints) has 56.82 M parameters and stays under 85.12 G
multiply-adds at 480x640 (paper, Table 3); see :data:`DEFAULT_DECODER_CHANNELS`.

Inputs: ``rgb`` float in [0,1] (ImageNet mean/std normalisation happens inside), ``geo`` from
:func:`geometry_map` (XYZ in metres + unit normals, zeros where depth is missing).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from tdof20.methods.resnet import STAGE_CHANNELS, ResNet34, load_torchvision_state_dict

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

#: decoder widths at strides (1, 2, 4, 8, 16, 32): full resolution, stem, layer1, layer2, layer3, centre
DEFAULT_DECODER_CHANNELS = (64, 64, 64, 128, 384, 552)
#: hidden width of the 1x1 heads
DEFAULT_HEAD_CHANNELS = 128


def conv_bn_relu(cin: int, cout: int, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, padding=k // 2, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class FuseBlock(nn.Module):
    """Fuse one stage: cat(rgb, geo) (2C) -> 1x1 conv -> C -> 3x3 conv -> C."""

    def __init__(self, c_rgb: int, c_geo: int, cout: int):
        super().__init__()
        self.reduce = conv_bn_relu(c_rgb + c_geo, cout, 1)
        self.mix = conv_bn_relu(cout, cout, 3)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return self.mix(self.reduce(torch.cat([a, b], dim=1)))


class UpBlock(nn.Module):
    """Up-sample to the skip's size, concatenate the skip (if any), two 3x3 convs."""

    def __init__(self, cin: int, c_skip: int, cout: int, n_convs: int = 2):
        super().__init__()
        layers = [conv_bn_relu(cin + c_skip, cout)] + [conv_bn_relu(cout, cout) for _ in range(n_convs - 1)]
        self.convs = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor, size: Sequence[int], skip: torch.Tensor | None) -> torch.Tensor:
        x = F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False)
        if skip is not None:
            x = torch.cat([x, skip], dim=1)
        return self.convs(x)


class HFF6DoF(nn.Module):
    """The HFF6DoF network.

    ``forward(rgb (B,3,H,W) in [0,1], geo (B,6,H,W)) -> {"seg": (B,n_classes,H,W) logits or None,
    "vec": (B,3K,H,W)}`` where ``vec[:, 3k:3k+3]`` is the unit vector from each pixel's 3D point
    towards keypoint k. H and W need not be multiples of 32.
    """

    def __init__(self, n_classes: int = 21, n_keypoints: int = 9, fuse_stages: int = 3, seg_head: bool = True,
                 decoder_channels: Sequence[int] = DEFAULT_DECODER_CHANNELS,
                 head_channels: int = DEFAULT_HEAD_CHANNELS, geo_channels: int = 6):
        super().__init__()
        if not 1 <= int(fuse_stages) <= 5:
            raise ValueError(f"fuse_stages must be 1..5, got {fuse_stages}")
        if len(decoder_channels) != 6:
            raise ValueError("decoder_channels needs 6 widths (strides 1, 2, 4, 8, 16, 32)")
        self.n_classes = int(n_classes)
        self.n_keypoints = int(n_keypoints)
        self.fuse_stages = int(fuse_stages)
        self.has_seg_head = bool(seg_head)
        self.config = dict(n_classes=self.n_classes, n_keypoints=self.n_keypoints, fuse_stages=self.fuse_stages,
                           seg_head=self.has_seg_head, decoder_channels=tuple(int(c) for c in decoder_channels),
                           head_channels=int(head_channels), geo_channels=int(geo_channels))
        self.rgb_encoder = ResNet34(in_channels=3)
        self.geo_encoder = ResNet34(in_channels=geo_channels)
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

        self.fused = tuple(range(5 - self.fuse_stages, 5))  # stage indices that are fused
        self.fuse = nn.ModuleDict({str(s): FuseBlock(STAGE_CHANNELS[s], STAGE_CHANNELS[s], STAGE_CHANNELS[s])
                                   for s in self.fused})
        d_full, *d_stage = decoder_channels  # d_stage[s] for stages 0..4
        self.center = nn.Sequential(conv_bn_relu(STAGE_CHANNELS[4], d_stage[4]), conv_bn_relu(d_stage[4], d_stage[4]))
        ups = {}
        cin = d_stage[4]
        for s in (3, 2, 1, 0):
            skip = STAGE_CHANNELS[s] if s in self.fused else 0
            ups[str(s)] = UpBlock(cin, skip, d_stage[s])
            cin = d_stage[s]
        self.up = nn.ModuleDict(ups)
        self.up_full = UpBlock(cin, 0, d_full, n_convs=1)

        def head(cout: int) -> nn.Sequential:
            return nn.Sequential(conv_bn_relu(d_full, head_channels, 1), nn.Conv2d(head_channels, cout, 1))

        self.seg_head = head(self.n_classes) if self.has_seg_head else None
        self.vec_head = head(3 * self.n_keypoints)

    def load_backbone_weights(self, path_or_dict) -> None:
        """Initialise both encoders from a torchvision resnet34 checkpoint (the geometry encoder's
        6-channel conv1 gets the RGB filters in both halves, scaled by 0.5)."""
        if isinstance(path_or_dict, (str, Path)):
            path_or_dict = Path(path_or_dict)
        load_torchvision_state_dict(self.rgb_encoder, path_or_dict)
        load_torchvision_state_dict(self.geo_encoder, path_or_dict)

    def forward(self, rgb: torch.Tensor, geo: torch.Tensor) -> dict[str, torch.Tensor | None]:
        B, _, H, W = rgb.shape
        if geo.shape[0] != B or geo.shape[2:] != rgb.shape[2:]:
            raise ValueError(f"rgb {tuple(rgb.shape)} and geo {tuple(geo.shape)} differ in batch or size")
        fr = self.rgb_encoder((rgb - self.rgb_mean) / self.rgb_std)
        fg = self.geo_encoder(geo)
        fused = {s: self.fuse[str(s)](fr[s], fg[s]) for s in self.fused}
        x = self.center(fused[4])
        for s in (3, 2, 1, 0):
            x = self.up[str(s)](x, fr[s].shape[2:], fused.get(s))
        x = self.up_full(x, (H, W), None)
        vec = self.vec_head(x)
        # F.normalize's norm over the 3-long middle dimension is ~20x slower on the CPU than the sum of
        # squares by hand (41 vs ~2 ms at 4x27x96x128 on one thread: 3 % of a training step); same maths
        v = vec.view(B, self.n_keypoints, 3, H, W)
        vec = (v / (v * v).sum(dim=2, keepdim=True).sqrt().clamp_min(1e-6)).view(B, -1, H, W)
        seg = self.seg_head(x) if self.seg_head is not None else None
        return {"seg": seg, "vec": vec}


# --------------------------------------------------------------------------------------------
# counting


def count_parameters(model: nn.Module, trainable_only: bool = False) -> int:
    """Exact number of parameters (buffers such as BatchNorm statistics not included)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def _mac_hook(counter: list[int]):
    def hook(module: nn.Module, inputs, output) -> None:
        if isinstance(module, nn.ConvTranspose2d):
            x = inputs[0]
            kh, kw = module.kernel_size
            counter[0] += x.numel() * (module.out_channels // module.groups) * kh * kw
        elif isinstance(module, nn.Conv2d):
            kh, kw = module.kernel_size
            counter[0] += output.numel() * (module.in_channels // module.groups) * kh * kw
        elif isinstance(module, nn.Conv1d):
            counter[0] += output.numel() * (module.in_channels // module.groups) * module.kernel_size[0]
        elif isinstance(module, nn.Linear):
            counter[0] += output.numel() * module.in_features
    return hook


def _input_shapes(model: nn.Module, input_shape) -> list[tuple[int, ...]]:
    shape = tuple(input_shape)
    if isinstance(model, HFF6DoF) and len(shape) == 2 and all(isinstance(v, int) for v in shape):
        H, W = shape
        return [(1, 3, H, W), (1, model.config["geo_channels"], H, W)]
    if all(isinstance(v, int) for v in shape):
        return [shape]
    return [tuple(s) for s in shape]


def count_macs(model: nn.Module, input_shape, meta: bool = True) -> int:
    """Multiply-accumulate operations of one forward pass, counted by forward hooks over
    Conv1d / Conv2d / ConvTranspose2d / Linear (biases, BatchNorm, activations, interpolation not counted).

    input_shape: one shape (B,C,H,W), a sequence of shapes (one per forward argument), or for
    HFF6DoF simply (H, W), meaning rgb (1,3,H,W) and geo (1,6,H,W).
    meta: run on PyTorch's ``meta`` device (shapes only, no arithmetic, instantaneous); falls back to
    a real forward under ``torch.no_grad`` if the meta pass fails.
    """
    shapes = _input_shapes(model, input_shape)
    counter = [0]
    hook = _mac_hook(counter)
    handles = [m.register_forward_hook(hook) for m in model.modules()
               if isinstance(m, (nn.Conv1d, nn.Conv2d, nn.ConvTranspose2d, nn.Linear))]
    was_training = model.training
    model.eval()
    try:
        done = False
        if meta:
            try:
                from torch.func import functional_call
                tensors = {k: torch.empty_like(v, device="meta")
                           for k, v in list(model.named_parameters()) + list(model.named_buffers())}
                args = [torch.zeros(s, device="meta") for s in shapes]
                with torch.no_grad():
                    functional_call(model, tensors, tuple(args))
                done = True
            except Exception:  # noqa: BLE001 - an op without a meta kernel: count for real
                counter[0] = 0
        if not done:
            p = next(model.parameters(), None)
            dev = p.device if p is not None else torch.device("cpu")
            with torch.no_grad():
                model(*[torch.zeros(s, device=dev) for s in shapes])
    finally:
        for h in handles:
            h.remove()
        model.train(was_training)
    return counter[0]


# --------------------------------------------------------------------------------------------
# inputs


def geometry_map(depth_mm: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Depth (B,H,W) in mm (0 = missing) and intrinsics K (B,3,3) or (3,3) -> (B,6,H,W).

    Channels 0-2: the organised XYZ map in the camera frame, in **metres** (so the values are
    O(1), like normalised RGB); channels 3-5: unit surface normals facing the camera, from the
    cross product of central differences (one-sided at borders and next to holes). Every channel is
    0 where the depth is missing; normals are 0 where no neighbour pair is valid.
    """
    if depth_mm.dim() == 2:
        depth_mm = depth_mm[None]
    B, H, W = depth_mm.shape
    z = depth_mm.to(torch.float32) / 1000.0
    K = K.to(device=z.device, dtype=torch.float32)
    if K.dim() == 2:
        K = K.expand(B, 3, 3)
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    v, u = torch.meshgrid(torch.arange(H, device=z.device, dtype=torch.float32),
                          torch.arange(W, device=z.device, dtype=torch.float32), indexing="ij")
    valid = z > 0
    xyz = torch.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], dim=1)  # (B,3,H,W)
    xyz = xyz * valid[:, None]

    def grad(dim: int) -> torch.Tensor:
        # central difference where both neighbours are valid, else one-sided, else 0
        p = F.pad(xyz, (1, 1, 1, 1))
        vp = F.pad(valid, (1, 1, 1, 1))[:, None]
        sl = slice(1, -1)
        if dim == 3:
            nxt, prv, cen = p[..., sl, 2:], p[..., sl, :-2], p[..., sl, sl]
            vn, vpv = vp[..., sl, 2:], vp[..., sl, :-2]
        else:
            nxt, prv, cen = p[..., 2:, sl], p[..., :-2, sl], p[..., sl, sl]
            vn, vpv = vp[..., 2:, sl], vp[..., :-2, sl]
        vc = valid[:, None]
        central = torch.where(vn & vpv, nxt - prv, torch.zeros_like(cen))
        fwd = torch.where(vn & vc, nxt - cen, torch.zeros_like(cen))
        bwd = torch.where(vpv & vc, cen - prv, torch.zeros_like(cen))
        return torch.where(vn & vpv, central, fwd + bwd)

    du, dv = grad(3), grad(2)
    n = torch.cross(du, dv, dim=1)
    # the sum of squares by hand: torch's norm over a 3-long middle dimension is ~30x slower here
    # (11.7 vs 0.4 ms a 4x3x96x128 batch on one thread)
    norm = (n * n).sum(dim=1, keepdim=True).sqrt()
    ok = valid[:, None] & (norm > 1e-12)
    n = torch.where(ok, n / norm.clamp_min(1e-12), torch.zeros_like(n))
    flip = (n * xyz).sum(dim=1, keepdim=True) > 0
    n = torch.where(flip, -n, n)
    return torch.cat([xyz, n], dim=1)
