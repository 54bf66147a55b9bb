"""PVNet (Peng et al., CVPR 2019; clean-pvnet): pixel-wise voting of 2D keypoints from RGB, then PnP.

    meta = MethodMeta.from_catalog((1, 5), image_size=(240, 320))
    cfg = PVNetConfig()
    net = build(cfg, meta)
    tf = PVNetTransform(cfg, meta, train=True)            # dataset item -> inputs + targets
    batch = collate([tf(item) for item in items])
    total, parts = loss(net, batch, cfg, meta)
    rows = predict_poses(net, batch, cfg, meta)           # [(b, obj_id, score, R (3,3), t (3,) mm)]

Network (after clean-pvnet's ``lib/networks/pvnet/resnet18.py``; RGB only)::

    rgb (B,3,H,W) in [0,1] -> ImageNet normalisation -> x
    ResNet18, output stride 8 (layer3, layer4 dilated 2, 4):  x2s (64), x4s (64), x8s (128), x32s (512, 1/8)
    fc      3x3 conv 512 -> 256, BN, ReLU                              (replaces the ImageNet fc)
    conv8s  3x3 conv cat(fc, x8s) 384 -> 128, BN, LeakyReLU(0.1); up to 1/4
    conv4s  3x3 conv cat(., x4s) 192 -> 64,  BN, LeakyReLU(0.1); up to 1/2
    conv2s  3x3 conv cat(., x2s) 128 -> 32,  BN, LeakyReLU(0.1); up to 1/1
    convraw 3x3 conv cat(., x) 35 -> 32, BN, LeakyReLU(0.1)
    seg     1x1 conv 32 -> n_classes                   (objects + background)
    vertex  1x1 conv 32 -> 2K per object class         (unit 2D vectors to the K keypoints)

Several objects, one network. The original trains one network per object (seg: object or not;
vertex: 2K channels). Our images hold several objects, so one network segments all of them
(n_classes = objects + background) and, by default (``class_vectors=True``), keeps one 2K-channel
vertex head *per object class*: the head of each pixel's class is applied (the ground-truth class
in training, the predicted class at test), so each object keeps its own vector regressor as in
the original while the trunk is shared. The per-class heads are evaluated only at the pixels of
their class (never the n_objects x 2K full map), so memory and multiply-adds are those of a
single 2K-channel head. ``class_vectors=False`` shares one head by all objects.

Loss (clean-pvnet's ``trainers/pvnet.py``): smooth-L1 between predicted and unit target vectors
on the object pixels, summed and divided by (pixels x 2K), plus the cross-entropy of the
segmentation over all pixels.

Pose (clean-pvnet's ``ransac_voting_layer_v3`` + ``pnp``), batched in torch over every instance
of the batch and every keypoint: each predicted class with enough pixels is an instance; at most
``vote_max_pixels`` of its pixels vote (clean-pvnet's test setting is 100); rounds of ``n_hyp``
hypotheses (intersections of the lines of random pixel pairs); a pixel votes for a hypothesis
when cos(vector, hypothesis - pixel) > ``inlier_cos`` (0.99); rounds stop when
1 - (1 - r^2)^n_hyp_total > ``confidence`` for every keypoint (r: best inlier ratio) or after
``max_rounds``; then the winner is refined by least squares over its inliers' lines. The 2D
keypoints and the model keypoints give the pose by EPnP then Levenberg-Marquardt (OpenCV).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod, forward_rgb
from tdof20.methods.data import resize_colour, resize_nearest, scale_intrinsics
from tdof20.methods.resnet import OUTPUT_STRIDE_8, ResNet18, load_torchvision_state_dict

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class PVNetConfig:
    """PVNet options (plain types, TOML-settable); every default works."""

    # network (clean-pvnet's Resnet18 widths)
    fcdim: int = 256
    s8dim: int = 128
    s4dim: int = 64
    s2dim: int = 32
    raw_dim: int = 32
    class_vectors: bool = True        # one vertex head per object class (False: one shared head)
    backbone_weights: str = ""        # a torchvision resnet18 .pth to start from ("" = random init)
    # loss
    vote_weight: float = 1.0
    seg_weight: float = 1.0
    # voting and PnP
    n_hyp: int = 128                  # hypotheses per round (clean-pvnet: 128)
    max_rounds: int = 20              # clean-pvnet's max_iter
    confidence: float = 0.99
    inlier_cos: float = 0.99
    vote_max_pixels: int = 100        # voting pixels per instance, a random subset (clean-pvnet test: 100)
    refine_iters: int = 1             # least-squares refinements on the inliers (clean-pvnet: 1)
    robust_iters: int = 5             # then Tukey-weighted solves on the inlier lines (0 = off, the original)
    min_pixels: int = 20              # smaller predicted segments are no instance
    min_inlier_ratio: float = 0.02    # a keypoint with fewer inliers is left out of PnP
    seed: int = 0                     # the voting's random generator (predict_poses)

    def __post_init__(self) -> None:
        if not 0.0 < float(self.inlier_cos) < 1.0:
            raise TdofError(f"pvnet inlier_cos must lie in (0, 1), got {self.inlier_cos}")
        if not 0.0 < float(self.confidence) < 1.0:
            raise TdofError(f"pvnet confidence must lie in (0, 1), got {self.confidence}")
        for name in ("fcdim", "s8dim", "s4dim", "s2dim", "raw_dim", "n_hyp", "max_rounds", "vote_max_pixels"):
            if int(getattr(self, name)) < 1:
                raise TdofError(f"pvnet {name} must be >= 1, got {getattr(self, name)}")


def _conv_bn(cin: int, cout: int, act: nn.Module) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), act)


class ClassVertexHead(nn.Conv2d):
    """1x1 conv 32 -> n_sets x 2K whose forward applies, at each pixel, only the 2K outputs of the
    pixel's class: ``forward(f (B,C,H,W), classes (B,H,W) int64 0..n_sets) -> (B,2K,H,W)``
    (class 0, the background, gets zeros). With n_sets = 1 it is a plain conv (classes ignored).

    Being a Conv2d, the multiply-add counter of profile.py counts it as one 2K-channel 1x1 conv,
    which is what it computes."""

    def __init__(self, cin: int, n_out: int, n_sets: int):
        super().__init__(cin, n_out * n_sets, kernel_size=1)
        self.n_out, self.n_sets = int(n_out), int(n_sets)

    def forward(self, f: torch.Tensor, classes: torch.Tensor | None = None) -> torch.Tensor:
        if self.n_sets == 1:
            return super().forward(f)
        if f.device.type == "meta":  # shape-only pass (counting)
            return F.conv2d(f, self.weight[: self.n_out], self.bias[: self.n_out])
        if classes is None:
            raise ValueError("a per-class vertex head needs the class of each pixel")
        B, C, H, W = f.shape
        Wt = self.weight.view(self.n_sets, self.n_out, C)
        bt = self.bias.view(self.n_sets, self.n_out)
        ff = f.permute(0, 2, 3, 1).reshape(-1, C)
        cl = classes.reshape(-1)
        out = ff.new_zeros(ff.shape[0], self.n_out)
        for c in torch.unique(cl).tolist():
            if not 1 <= c <= self.n_sets:
                continue
            idx = (cl == c).nonzero()[:, 0]
            out = out.index_put((idx,), torch.addmm(bt[c - 1], ff[idx], Wt[c - 1].t()))
        return out.view(B, H, W, self.n_out).permute(0, 3, 1, 2)


class PVNet(nn.Module):
    """``forward(rgb (B,3,H,W) in [0,1], classes=None) -> {"seg": (B,n_classes,H,W) logits,
    "vertex": (B,2K,H,W)}``; ``vertex[:, 2k:2k+2]`` = (du, dv) towards keypoint k, of the head of
    ``classes`` (B,H,W) (class indices; None = the predicted ``seg.argmax(1)``). Any H, W."""

    def __init__(self, n_classes: int, n_keypoints: int = 9, class_vectors: bool = True, fcdim: int = 256,
                 s8dim: int = 128, s4dim: int = 64, s2dim: int = 32, raw_dim: int = 32):
        super().__init__()
        self.n_classes, self.n_keypoints = int(n_classes), int(n_keypoints)
        self.class_vectors = bool(class_vectors)
        self.backbone = ResNet18(replace_stride_with_dilation=OUTPUT_STRIDE_8)
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.fc = _conv_bn(512, fcdim, nn.ReLU(inplace=True))
        self.conv8s = _conv_bn(128 + fcdim, s8dim, nn.LeakyReLU(0.1, inplace=True))
        self.conv4s = _conv_bn(64 + s8dim, s4dim, nn.LeakyReLU(0.1, inplace=True))
        self.conv2s = _conv_bn(64 + s4dim, s2dim, nn.LeakyReLU(0.1, inplace=True))
        self.convraw = _conv_bn(3 + s2dim, raw_dim, nn.LeakyReLU(0.1, inplace=True))
        self.seg_head = nn.Conv2d(raw_dim, self.n_classes, 1)
        self.vertex_head = ClassVertexHead(raw_dim, 2 * self.n_keypoints,
                                           self.n_classes - 1 if self.class_vectors else 1)

    def load_backbone_weights(self, path_or_dict: str | Path | Mapping) -> list[str]:
        """Initialise the ResNet18 from a torchvision resnet18 checkpoint (path or state dict)."""
        return load_torchvision_state_dict(self.backbone, path_or_dict)

    def forward(self, rgb: torch.Tensor, classes: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        if rgb.dim() != 4 or rgb.shape[1] != 3:
            raise ValueError(f"PVNet wants rgb (B,3,H,W), got {tuple(rgb.shape)}")
        x = (rgb - self.rgb_mean) / self.rgb_std
        x2s, x4s, x8s, _, x32s = self.backbone(x)
        fm = self.conv8s(torch.cat([self.fc(x32s), x8s], 1))
        fm = F.interpolate(fm, size=x4s.shape[2:], mode="bilinear", align_corners=True)
        fm = self.conv4s(torch.cat([fm, x4s], 1))
        fm = F.interpolate(fm, size=x2s.shape[2:], mode="bilinear", align_corners=True)
        fm = self.conv2s(torch.cat([fm, x2s], 1))
        fm = F.interpolate(fm, size=x.shape[2:], mode="bilinear", align_corners=True)
        f = self.convraw(torch.cat([fm, x], 1))
        seg = self.seg_head(f)
        if classes is None and self.class_vectors:
            classes = seg.argmax(1) if seg.device.type != "meta" else None
        return {"seg": seg, "vertex": self.vertex_head(f, classes)}


def build(cfg: PVNetConfig, meta: MethodMeta) -> PVNet:
    """The PVNet of ``meta``'s objects; with ``cfg.backbone_weights`` the ResNet18 starts from it."""
    net = PVNet(meta.n_classes, meta.n_keypoints, cfg.class_vectors, cfg.fcdim, cfg.s8dim, cfg.s4dim,
                cfg.s2dim, cfg.raw_dim)
    if cfg.backbone_weights:
        net.load_backbone_weights(Path(cfg.backbone_weights))
    return net


# --------------------------------------------------------------------------------------------
# inputs and targets


def keypoint_vectors(uv: torch.Tensor, instance: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Unit 2D vectors (2K,H,W) from every pixel (u, v) of instance g (``instance`` (H,W) = g + 1,
    0 = none) to the projected keypoints ``uv`` (N,K,2) of that instance; 0 outside instances.
    Channel 2k is du, 2k + 1 is dv (clean-pvnet's layout)."""
    H, W = instance.shape
    N, Kp, _ = uv.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    pix = torch.stack([u, v], -1)                                       # (H,W,2)
    g = (instance.long() - 1).clamp(0, max(N - 1, 0))
    d = uv.to(torch.float32)[g] - pix[:, :, None]                       # (H,W,K,2)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(eps)
    d = torch.where((instance > 0)[..., None, None], d, torch.zeros_like(d))
    return d.reshape(H, W, 2 * Kp).permute(2, 0, 1).contiguous()


def project_keypoints(kp_model: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(N,K,3) model keypoints mm, R (N,3,3), t (N,3) mm, K (3,3) -> (N,K,2) pixel coordinates."""
    cam = torch.einsum("nij,nkj->nki", R.to(torch.float32), kp_model.to(torch.float32)) + t.to(torch.float32)[:, None]
    p = cam @ K.to(torch.float32).T
    return p[..., :2] / p[..., 2:].clamp_min(1e-6)


class PVNetTransform:
    """A dataset item -> PVNet inputs (and targets with ``train=True``) at ``meta.image_size``.

    Output: ``rgb`` (3,H,W) float in [0,1], ``K`` (3,3) scaled, ``scene_id``, ``im_id``; with
    ``train``: ``cls`` (H,W) int64 class index per pixel (0 = background and objects outside
    ``meta``), ``vertex`` (2K,H,W) unit 2D vectors from each visible object pixel to its object's
    projected keypoints (ground-truth pose), ``mask`` (H,W) bool where ``vertex`` is defined.
    The depth is not used (PVNet is RGB only). Picklable."""

    def __init__(self, cfg: PVNetConfig, meta: MethodMeta, train: bool = False):
        self.image_size = tuple(meta.image_size)
        self.train = bool(train)
        self.lut = torch.from_numpy(meta.class_lut(1000))
        self.kp = torch.from_numpy(meta.keypoint_array()).to(torch.float32)   # (n_classes,K,3)

    def __call__(self, item: Mapping) -> dict:
        hw = self.image_size
        src_hw = tuple(item["rgb"].shape[1:])
        K = scale_intrinsics(torch.as_tensor(item["K"]), src_hw, hw)
        out = {"rgb": resize_colour(item["rgb"], hw), "K": K,
               "scene_id": int(item["scene_id"]), "im_id": int(item["im_id"])}
        if not self.train:
            return out
        if "label" not in item or "instance" not in item:
            raise TdofError(f"PVNet training targets need labels (scene {item.get('scene_id')}, "
                            f"image {item.get('im_id')} has none)")
        label = resize_nearest(item["label"], hw).long()
        inst = resize_nearest(item["instance"], hw).long()
        lut = self.lut
        if int(label.max()) >= len(lut):
            lut = torch.cat([lut, torch.zeros(int(label.max()) + 1 - len(lut), dtype=lut.dtype)])
        cls = lut[label.clamp_min(0)]
        obj = torch.as_tensor(item["obj_id"]).long().reshape(-1)
        gcls = lut[obj.clamp(0, len(lut) - 1)]                           # class of each gt
        n = obj.numel()
        inst = torch.where((inst > 0) & (inst <= n), inst, torch.zeros_like(inst))
        ok_gt = torch.cat([torch.zeros(1, dtype=torch.bool), gcls > 0])
        inst = torch.where(ok_gt[inst] & (cls > 0), inst, torch.zeros_like(inst))
        uv = project_keypoints(self.kp[gcls], torch.as_tensor(item["R"]).reshape(-1, 3, 3),
                               torch.as_tensor(item["t"]).reshape(-1, 3), K)
        out.update(cls=torch.where(inst > 0, cls, torch.zeros_like(cls)) if n else torch.zeros_like(cls),
                   vertex=keypoint_vectors(uv, inst), mask=inst > 0)
        return out


# --------------------------------------------------------------------------------------------
# loss


def loss(net: PVNet, batch: Mapping, cfg: PVNetConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
    """clean-pvnet's loss: smooth-L1 on the vectors of the object pixels / (pixels x 2K) + cross-entropy."""
    dev = next(net.parameters()).device
    rgb = batch["rgb"].to(dev, non_blocking=True)
    cls = batch["cls"].to(dev, non_blocking=True).long()
    target = batch["vertex"].to(dev, non_blocking=True)
    w = batch["mask"].to(dev, non_blocking=True)[:, None].to(target.dtype)
    out = net(rgb, cls)
    vert = out["vertex"].float()
    vote = F.smooth_l1_loss(vert * w, target * w, reduction="sum") / (w.sum().clamp_min(1.0) * target.shape[1])
    seg = F.cross_entropy(out["seg"].float(), cls)
    total = cfg.vote_weight * vote + cfg.seg_weight * seg
    return total, {"loss": float(total.detach()), "vote": float(vote.detach()), "seg": float(seg.detach())}


# --------------------------------------------------------------------------------------------
# 2D RANSAC voting


def _votes2d(h: torch.Tensor, Vn: torch.Tensor, Dn: torch.Tensor) -> torch.Tensor:
    """Inlier mask (B,K,Hh,N) of hypotheses h (B,K,Hh,2): cos(v_n, h - p_n) > c, as
    num |num| > c^2 |h - p|^2 with num = h.v - p.v, by two batched matmuls."""
    one = torch.ones_like(h[..., :1])
    num = torch.matmul(torch.cat([h, one], -1), Vn)
    negd2 = torch.matmul(torch.cat([h, (h * h).sum(-1, keepdim=True), one], -1), Dn)
    return torch.addcmul(negd2, num, num.abs()) > 0


def _lines_lsq(w: torch.Tensor, p: torch.Tensor, v: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """Point (B,K,2) nearest (least squares) to the weighted lines (p_n, v_nk): with normals
    n = (v_y, -v_x): sum w n n^T x = sum w n (n.p). Ill-conditioned systems keep ``fallback``."""
    nrm = torch.stack([v[..., 1], -v[..., 0]], -1)                      # (B,K,N,2)
    wn = w[..., None] * nrm
    A = torch.matmul(wn.transpose(-1, -2), nrm)                          # (B,K,2,2)
    b = (wn * (nrm * p[:, None]).sum(-1, keepdim=True)).sum(-2)          # (B,K,2)
    ev = torch.linalg.eigvalsh(A)
    good = ((w > 0).sum(-1) >= 2) & (ev[..., 0] > 1e-9 * w.sum(-1).clamp_min(1e-12))
    eye = torch.eye(2, dtype=A.dtype, device=A.device)
    x, _ = torch.linalg.solve_ex(torch.where(good[..., None, None], A, eye.expand_as(A)), b[..., None])
    x = x[..., 0]
    return torch.where(good[..., None] & torch.isfinite(x).all(-1, keepdim=True), x, fallback)


def vote_keypoints_2d(coords: torch.Tensor, vectors: torch.Tensor, valid: torch.Tensor | None = None, *,
                      n_hyp: int = 128, inlier_cos: float = 0.99, max_rounds: int = 20, confidence: float = 0.99,
                      refine_iters: int = 1, robust_iters: int = 5, min_scale: float = 1e-4, min_cross: float = 1e-6,
                      generator: torch.Generator | None = None,
                      max_elements: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    """RANSAC voting of 2D keypoints for B instances at once (PVNet).

    coords (B,N,2) pixel coordinates (u, v); vectors (B,N,K,2) directions towards the K keypoints
    (normalised here); valid (B,N) bool (padding False; None = all).
    Returns (keypoints (B,K,2), n_inliers (B,K) int64); NaN and 0 where an instance has fewer than
    two valid pixels or no hypothesis got a vote.

    After clean-pvnet's refinement (``refine_iters`` least-squares solves over the winner's
    inliers), ``robust_iters`` more solves weight the inlier lines by Tukey's biweight of their
    distance to the current estimate, at a scale of 4.685 x 1.4826 x the median inlier distance
    (at least ``min_scale`` px): an outlier vector that falls inside the 0.99 cone by chance
    (about 4.5 % of random directions) no longer pulls the estimate by up to sin(8 deg) x its
    distance. 0 = off (the original).
    """
    if coords.dim() != 3 or coords.shape[-1] != 2:
        raise ValueError(f"coords must be (B,N,2), got {tuple(coords.shape)}")
    if vectors.dim() != 4 or vectors.shape[:2] != coords.shape[:2] or vectors.shape[-1] != 2:
        raise ValueError(f"vectors must be (B,N,K,2) matching coords {tuple(coords.shape)}, got {tuple(vectors.shape)}")
    if not 0.0 < float(inlier_cos) < 1.0:
        raise ValueError(f"inlier_cos must lie in (0, 1), got {inlier_cos}")
    B, N, Kp, _ = vectors.shape
    dev = coords.device
    dtype = torch.float64 if coords.dtype == torch.float64 else torch.float32
    if valid is None:
        valid = torch.ones(B, N, dtype=torch.bool, device=dev)
    valid = valid.to(dev, torch.bool) & torch.isfinite(coords).all(-1) & torch.isfinite(vectors).all(-1).all(-1)
    valid = valid & (vectors.norm(dim=-1) > 1e-9).all(-1)
    nan = (torch.full((B, Kp, 2), float("nan"), device=dev, dtype=dtype), torch.zeros(B, Kp, dtype=torch.long, device=dev))
    if N == 0 or B == 0:
        return nan
    # valid pixels first; coordinates centred on each instance's mean pixel
    order = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)
    bi = torch.arange(B, device=dev)[:, None]
    val = valid[bi, order]
    nv = val.sum(1)
    p = torch.where(val[..., None], coords.to(dtype)[bi, order], torch.zeros((), dtype=dtype, device=dev))
    v = F.normalize(vectors.to(dtype)[bi, order], dim=-1, eps=1e-12)
    v = torch.where(val[..., None, None], v, torch.zeros_like(v))
    centre = p.sum(1, keepdim=True) / nv.clamp_min(1)[:, None, None].to(dtype)
    p = torch.where(val[..., None], p - centre, torch.zeros_like(p))
    v = v.permute(0, 2, 1, 3).contiguous()                               # (B,K,N,2)
    pv = (v * p[:, None]).sum(-1)                                        # (B,K,N)
    Vn = torch.cat([v, -pv[..., None]], -1).transpose(-1, -2).contiguous()       # (B,K,3,N)
    pp = torch.where(val, (p * p).sum(-1), torch.full_like(p[..., 0], 1e30))
    c2 = float(inlier_cos) ** 2
    Dn = torch.cat([2 * c2 * p, -c2 * torch.ones_like(p[..., :1]), -c2 * pp[..., None]], -1)
    Dn = Dn.transpose(-1, -2)[:, None].contiguous()                      # (B,1,4,N)

    H = int(n_hyp)
    chunk = max(1, int(max_elements) // max(1, B * Kp * N))
    best = torch.zeros(B, Kp, 2, dtype=dtype, device=dev)
    best_n = torch.full((B, Kp), -1, dtype=torch.long, device=dev)
    ki = torch.arange(Kp, device=dev)[None, :, None]
    bb = torch.arange(B, device=dev)[:, None, None]
    gdev = generator.device if generator is not None else dev
    total = 0
    for _ in range(max(1, int(max_rounds))):
        r = torch.rand((B, Kp, H, 2), generator=generator, device=gdev).to(dev)
        idx = torch.minimum((r * nv[:, None, None, None]).long(), (nv - 1).clamp_min(0)[:, None, None, None])
        pi, pj = p[bb, idx[..., 0]], p[bb, idx[..., 1]]                  # (B,K,H,2)
        vi, vj = v[bb, ki, idx[..., 0]], v[bb, ki, idx[..., 1]]
        cross = vi[..., 0] * vj[..., 1] - vi[..., 1] * vj[..., 0]
        ok = (cross.abs() > min_cross) & (idx[..., 0] != idx[..., 1]) & (nv[:, None, None] >= 2)
        d = pj - pi
        s = (d[..., 0] * vj[..., 1] - d[..., 1] * vj[..., 0]) / torch.where(ok, cross, torch.ones_like(cross))
        hyp = torch.where(ok[..., None], pi + s[..., None] * vi, torch.zeros_like(pi))
        counts = torch.cat([_votes2d(hyp[:, :, h0:h0 + chunk], Vn, Dn).sum(-1) for h0 in range(0, H, chunk)], 2)
        counts = torch.where(ok, counts, torch.full_like(counts, -1))
        n_r, w_r = counts.max(2)                                         # (B,K)
        better = n_r > best_n
        best = torch.where(better[..., None], torch.gather(hyp, 2, w_r[..., None, None].expand(-1, -1, 1, 2))[:, :, 0],
                           best)
        best_n = torch.where(better, n_r, best_n)
        total += H
        ratio = best_n.clamp_min(0).to(torch.float64) / nv.clamp_min(1)[:, None].to(torch.float64)
        live = nv >= 2
        if not bool(live.any()):
            break
        if float(ratio[live].min()) > 0 and \
                float((1 - (1 - ratio[live].min() ** 2) ** total)) > float(confidence):
            break
    found = best_n > 0
    inl = _votes2d(best[:, :, None], Vn, Dn)[:, :, 0]                    # (B,K,N)
    x = best
    for _ in range(max(0, int(refine_iters))):
        x = _lines_lsq(inl.to(dtype), p, v, x)
        inl = _votes2d(x[:, :, None], Vn, Dn)[:, :, 0]
    for _ in range(max(0, int(robust_iters))):
        dx = x[:, :, None] - p[:, None]                                     # (B,K,N,2)
        perp = (dx[..., 0] * v[..., 1] - dx[..., 1] * v[..., 0]).abs()      # line-to-estimate distances
        med = torch.where(inl, perp, torch.full_like(perp, float("nan"))).nanmedian(-1).values
        c = (4.685 * 1.4826 * med.nan_to_num(0.0)).clamp_min(float(min_scale))[..., None]
        w = torch.where(inl & (perp < c), (1 - (perp / c) ** 2) ** 2, torch.zeros_like(perp))
        x = _lines_lsq(w, p, v, x)
        inl = _votes2d(x[:, :, None], Vn, Dn)[:, :, 0]
    n_inl = torch.where(found, inl.sum(-1), torch.zeros_like(best_n))
    x = torch.where(found[..., None], x + centre, torch.full_like(x, float("nan")))
    return x, n_inl


# --------------------------------------------------------------------------------------------
# pose


def pnp_pose(model_kp: np.ndarray, kp2d: np.ndarray, K: np.ndarray, use: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose (R (3,3), t (3,) mm) from model keypoints (K,3) mm and their image points (K,2):
    OpenCV EPnP, then Levenberg-Marquardt (solvePnPRefineLM). ``use`` selects keypoints (at least
    4). None when too few keypoints, PnP fails or the object lands behind the camera."""
    import cv2

    ok = np.isfinite(kp2d).all(1) & np.isfinite(model_kp).all(1)
    if use is not None:
        ok &= np.asarray(use, bool)
    if ok.sum() < 4:
        return None
    obj = np.ascontiguousarray(model_kp[ok], dtype=np.float64)
    img = np.ascontiguousarray(kp2d[ok], dtype=np.float64)
    cam = np.asarray(K, dtype=np.float64)
    dist = np.zeros(4)
    try:
        good, rvec, tvec = cv2.solvePnP(obj, img, cam, dist, flags=cv2.SOLVEPNP_EPNP)
        if not good:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, cam, dist, rvec, tvec)
    except cv2.error:
        return None
    if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()) or tvec[2, 0] <= 0:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec[:, 0].copy()


@torch.no_grad()
def predict_poses(net: PVNet, batch: Mapping, cfg: PVNetConfig, meta: MethodMeta
                  ) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
    """Poses of a batch: rows (b, obj_id, score, R (3,3), t (3,) mm). Every predicted class with at
    least ``cfg.min_pixels`` pixels is one instance (one per object and image: TDoF20's images
    never hold an object twice); score = the mean inlier ratio of its keypoints x its mean class
    probability."""
    was = net.training
    net.eval()
    try:
        dev = next(net.parameters()).device
        rgb = batch["rgb"].to(dev)
        out = net(rgb)
    finally:
        net.train(was)
    prob = out["seg"].float().softmax(1)
    conf, cls = prob.max(1)                                              # (B,H,W)
    B, H, W = cls.shape
    Kp = meta.n_keypoints
    vert = out["vertex"].float().view(B, Kp, 2, H, W)
    gen = torch.Generator(device=dev).manual_seed(int(cfg.seed))
    v_, u_ = torch.meshgrid(torch.arange(H, device=dev, dtype=torch.float32),
                            torch.arange(W, device=dev, dtype=torch.float32), indexing="ij")
    pix = torch.stack([u_, v_], -1).reshape(-1, 2)
    owners, coords, vecs = [], [], []
    for b in range(B):
        classes, counts = torch.unique(cls[b], return_counts=True)
        for c, n in zip(classes.tolist(), counts.tolist()):
            if c <= 0 or n < max(2, int(cfg.min_pixels)):
                continue
            idx = (cls[b].reshape(-1) == c).nonzero()[:, 0]
            if idx.numel() > cfg.vote_max_pixels:
                pick = torch.randperm(idx.numel(), generator=gen, device=dev)[: cfg.vote_max_pixels]
                idx = idx[pick]
            owners.append((b, c, float(conf[b].reshape(-1)[cls[b].reshape(-1) == c].mean())))
            coords.append(pix[idx])
            vecs.append(vert[b].reshape(Kp, 2, -1)[:, :, idx].permute(2, 0, 1))
    if not owners:
        return []
    n = max(len(c) for c in coords)
    P = torch.zeros(len(owners), n, 2, device=dev)
    V = torch.zeros(len(owners), n, Kp, 2, device=dev)
    M = torch.zeros(len(owners), n, dtype=torch.bool, device=dev)
    for i, (c, v) in enumerate(zip(coords, vecs)):
        P[i, : len(c)], V[i, : len(c)], M[i, : len(c)] = c, v, True
    kp2d, n_inl = vote_keypoints_2d(P, V, M, n_hyp=cfg.n_hyp, inlier_cos=cfg.inlier_cos, max_rounds=cfg.max_rounds,
                                    confidence=cfg.confidence, refine_iters=cfg.refine_iters,
                                    robust_iters=cfg.robust_iters, generator=gen)
    kp2d, n_inl, nvalid = kp2d.cpu().numpy(), n_inl.cpu().numpy(), M.sum(1).cpu().numpy()
    Ks = batch["K"].cpu().numpy().astype(np.float64)
    rows = []
    for i, (b, c, cprob) in enumerate(owners):
        obj = meta.obj_of(c)
        ratio = n_inl[i] / max(1, nvalid[i])
        fit = pnp_pose(meta.keypoints[obj], kp2d[i], Ks[b], ratio >= cfg.min_inlier_ratio)
        if fit is None:
            continue
        R, t = fit
        rows.append((int(b), int(obj), float(ratio.mean() * cprob), R, t))
    return rows


def rotation_error_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (degrees) of R1 R2^T."""
    c = (np.trace(np.asarray(R1) @ np.asarray(R2).T) - 1) / 2
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


class PVNetMethod(PoseMethod):
    """PVNet's pieces (the functions of this module); the network reads the colour image alone."""

    config_class = PVNetConfig

    def build(self, cfg: PVNetConfig, meta: MethodMeta) -> PVNet:
        return build(cfg, meta)

    def transform(self, cfg: PVNetConfig, meta: MethodMeta, train: bool = False) -> PVNetTransform:
        return PVNetTransform(cfg, meta, train=train)

    def loss(self, net: PVNet, batch: Mapping, cfg: PVNetConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
        return loss(net, batch, cfg, meta)

    def predict_poses(self, net: PVNet, batch: Mapping, cfg: PVNetConfig, meta: MethodMeta) -> list:
        return predict_poses(net, batch, cfg, meta)

    def forward(self, net: PVNet, batch: Mapping) -> dict:
        return forward_rgb(net, batch)


__all__ = ["PVNet", "PVNetConfig", "PVNetMethod", "PVNetTransform", "build", "keypoint_vectors", "loss", "pnp_pose",
           "predict_poses", "project_keypoints", "vote_keypoints_2d"]
