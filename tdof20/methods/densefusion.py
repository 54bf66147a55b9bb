"""DenseFusion (Wang et al., CVPR 2019): per-pixel dense fusion of a PSPNet-ResNet18 colour
embedding and a PointNet geometry embedding, per-point pose + confidence, and the iterative
refiner — in plain PyTorch, the same code on CPU and GPU (the original's KNN needs
``torch.utils.ffi`` and PyTorch 0.4.1; ours is :func:`tdof20.methods.randla.knn`).

    cfg = DenseFusionConfig(stage="pose")      # "seg" | "pose" | "refine" | "joint"
    net = build(cfg, meta)                      # .seg (segmentation), .estimator, .refiner
    tf = DenseFusionTransform(cfg, meta, train=True)
    total, parts = loss(net, collate([tf(i) for i in items]), cfg, meta)
    rows = predict_poses(net, batch, cfg, meta)  # [(b, obj_id, score, R, t mm), ...]

Three networks in one module, as the original runs them:

- ``seg``: the segmentation network that gives the crops (the original takes PoseCNN's labels on
  YCB and trains its own "vanilla_segmentation" net): a PSPNet-ResNet18 with ``n_classes``
  outputs, cross-entropy — :class:`tdof20.methods.segnet.SegNet`, the module the registered
  'segnet' (masks for HFF6DoF without its head) trains alone. Trained by the same :func:`loss` with ``stage="seg"`` — one training
  command with ``--config`` holding ``stage = "seg"``; ``stage = "joint"`` trains all three at once.
- ``estimator`` (the original's PoseNet): PSPNet-ResNet18 embedding (32-d) of the crop, gathered at
  the N chosen pixels; PointNet on the N points (3 -> 64 -> 128 with 32 -> 64 -> 128 on the
  embedding, fused per point, 256 -> 512 -> 1024 and an average pool as the global feature;
  128 + 256 + 1024 = 1408 per point); three heads 1408 -> 640 -> 256 -> 128 -> n_obj x {4, 3, 1}
  (quaternion, translation offset, sigmoid confidence) indexed by the crop's class.
- ``refiner`` (PoseRefineNet): the points in the frame of the current pose + the embedding ->
  PointNet -> global 1024 -> per-class quaternion and translation of a pose correction; applied
  ``refine_iterations`` (2) times.

Loss (lib/loss.py): per point i the model points under pose i, mean distance to the target
(model points under the true pose) — closest target point for symmetric objects (ADD-S, by KNN)
— weighted by the confidence, minus ``w`` log confidence (w = 0.015, distances in metres as the
original). The refiner's loss (lib/loss_refiner.py) is the same distance without confidence, per
iteration, on the points and the target moved into the frame of the previous estimate.

Pose recovery: segmentation -> one crop per predicted class (bounding box of its pixels, the
original's border-list sizes), the most confident point's pose, then the refiner's corrections.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod, forward_batch
from tdof20.methods.data import DEFAULT_DEPTH_MODE, backproject, check_depth_mode, resize_frame, resize_nearest
from tdof20.methods.fitting import quaternion_to_matrix
from tdof20.methods.pspnet import PSPNet
from tdof20.methods.randla import knn
from tdof20.methods.segnet import SegNet

STAGES = ("seg", "pose", "refine", "joint")
#: the original's crop sizes (get_bbox's border_list at 480x640), scaled to the image
BORDER_LIST = (40, 80, 120, 160, 200, 240, 280, 320, 360, 400, 440, 480, 520, 560, 600, 640, 680)


@dataclass
class DenseFusionConfig:
    """Every option of DenseFusion with a working default (plain types: TOML-settable).

    n_points: points per crop (the original: 1,000 on YCB, 500 on LineMOD); crop_size: side of
    the square the crop is resized to (so crops batch; the original feeds each crop at its own
    size, batch 1). stage: what :func:`loss` trains — "seg" (the segmentation net), "pose" (the
    estimator), "refine" (the refiner on a frozen estimator) or "joint" (all three summed).
    """

    stage: str = "joint"
    n_points: int = 1000
    n_model_points: int = 500
    crop_size: int = 160
    w: float = 0.015
    refine_iterations: int = 2
    noise_trans_mm: float = 30.0          # training: uniform noise added to the cloud and the target
    depth_mode: str = DEFAULT_DEPTH_MODE
    backbone_weights: str = ""            # a torchvision resnet18 .pth for the PSPNets ("" = random)
    min_points: int = 50                  # pixels with depth a crop needs (the original's minimum_num_pt)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise TdofError(f"unknown DenseFusion stage '{self.stage}' (valid: {', '.join(STAGES)})")
        check_depth_mode(self.depth_mode)
        if self.n_points < 1 or self.crop_size < 8:
            raise TdofError("DenseFusion needs n_points >= 1 and crop_size >= 8")


# --------------------------------------------------------------------------------------------
# networks


class _PointFusionFeat(nn.Module):
    """The two fusion stages both DenseFusion feature nets start with (PointNet on the points, 1x1
    convolutions on the colour embedding, concatenated after each): x (B,3,N), emb (B,32,N) ->
    f1 (B,128,N), f2 (B,256,N). ``conv5_in``: the channels the subclass's conv5 takes."""

    def __init__(self, emb_dim: int, conv5_in: int):
        super().__init__()
        self.conv1 = nn.Conv1d(3, 64, 1)
        self.conv2 = nn.Conv1d(64, 128, 1)
        self.e_conv1 = nn.Conv1d(emb_dim, 64, 1)
        self.e_conv2 = nn.Conv1d(64, 128, 1)
        self.conv5 = nn.Conv1d(conv5_in, 512, 1)
        self.conv6 = nn.Conv1d(512, 1024, 1)

    def fuse(self, x: torch.Tensor, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = F.relu(self.conv1(x))
        emb = F.relu(self.e_conv1(emb))
        f1 = torch.cat([x, emb], 1)
        f2 = torch.cat([F.relu(self.conv2(x)), F.relu(self.e_conv2(emb))], 1)
        return f1, f2


class PoseNetFeat(_PointFusionFeat):
    """PointNet + dense fusion of the original: x (B,3,N), emb (B,32,N) -> (B,1408,N)."""

    def __init__(self, emb_dim: int = 32):
        super().__init__(emb_dim, 256)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        f1, f2 = self.fuse(x, emb)
        g = F.relu(self.conv6(F.relu(self.conv5(f2)))).mean(2, keepdim=True)   # AvgPool1d(num_points)
        return torch.cat([f1, f2, g.expand(-1, -1, x.shape[2])], 1)


def _pick_class(y: torch.Tensor, cls: torch.Tensor, width: int) -> torch.Tensor:
    """(B, n_obj*width, ...) -> (B, width, ...) the rows of each sample's class (0-based object index)."""
    B = y.shape[0]
    y = y.view(B, -1, width, *y.shape[2:])
    idx = cls.long().view(B, 1, 1, *([1] * (y.dim() - 3))).expand(B, 1, width, *y.shape[3:])
    return torch.gather(y, 1, idx)[:, 0]


class PoseNet(nn.Module):
    """The estimator: crop (B,3,h,w) in [0,1], cloud (B,N,3) m, choose (B,N) crop-pixel index,
    cls (B,) 0-based object index -> quaternions (B,N,4), translation offsets (B,N,3) m,
    confidences (B,N) in (0,1), embedding (B,32,N)."""

    def __init__(self, n_obj: int, backbone_weights: str = ""):
        super().__init__()

        self.n_obj = int(n_obj)
        self.cnn = PSPNet(backbone="resnet18", feat_dim=32)
        if backbone_weights:
            self.cnn.load_backbone_weights(backbone_weights)
        self.feat = PoseNetFeat(32)
        for name, out in (("r", 4), ("t", 3), ("c", 1)):
            setattr(self, f"conv1_{name}", nn.Conv1d(1408, 640, 1))
            setattr(self, f"conv2_{name}", nn.Conv1d(640, 256, 1))
            setattr(self, f"conv3_{name}", nn.Conv1d(256, 128, 1))
            setattr(self, f"conv4_{name}", nn.Conv1d(128, self.n_obj * out, 1))

    def _head(self, name: str, x: torch.Tensor) -> torch.Tensor:
        for i in (1, 2, 3):
            x = F.relu(getattr(self, f"conv{i}_{name}")(x))
        return getattr(self, f"conv4_{name}")(x)

    def forward(self, crop: torch.Tensor, cloud: torch.Tensor, choose: torch.Tensor, cls: torch.Tensor):
        emb = self.cnn(crop)
        B, D = emb.shape[:2]
        emb = torch.gather(emb.view(B, D, -1), 2, choose.view(B, 1, -1).expand(B, D, -1))
        f = self.feat(cloud.transpose(1, 2), emb)
        r = _pick_class(self._head("r", f), cls, 4).transpose(1, 2)
        t = _pick_class(self._head("t", f), cls, 3).transpose(1, 2)
        c = torch.sigmoid(_pick_class(self._head("c", f), cls, 1))[:, 0]
        return r, t, c, emb.detach()


class PoseRefineNetFeat(_PointFusionFeat):
    """x (B,3,N), emb (B,32,N) -> (B,1024) global feature."""

    def __init__(self, emb_dim: int = 32):
        super().__init__(emb_dim, 384)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        f1, f2 = self.fuse(x, emb)
        x = F.relu(self.conv6(F.relu(self.conv5(torch.cat([f1, f2], 1)))))
        return x.mean(2)


class PoseRefineNet(nn.Module):
    """points in the current estimate's frame (B,N,3) m, embedding (B,32,N), cls (B,) ->
    correction quaternion (B,4), translation (B,3) m."""

    def __init__(self, n_obj: int):
        super().__init__()
        self.n_obj = int(n_obj)
        self.feat = PoseRefineNetFeat(32)
        self.conv1_r, self.conv1_t = nn.Linear(1024, 512), nn.Linear(1024, 512)
        self.conv2_r, self.conv2_t = nn.Linear(512, 128), nn.Linear(512, 128)
        self.conv3_r, self.conv3_t = nn.Linear(128, self.n_obj * 4), nn.Linear(128, self.n_obj * 3)

    def forward(self, x: torch.Tensor, emb: torch.Tensor, cls: torch.Tensor):
        g = self.feat(x.transpose(1, 2), emb)
        r = self.conv3_r(F.relu(self.conv2_r(F.relu(self.conv1_r(g)))))
        t = self.conv3_t(F.relu(self.conv2_t(F.relu(self.conv1_t(g)))))
        return _pick_class(r, cls, 4), _pick_class(t, cls, 3)


class DenseFusion(nn.Module):
    """``seg`` + ``estimator`` + ``refiner``; ``forward(batch)`` runs what the batch holds: the
    segmentation logits of ``rgb`` and, with crops, the estimator (and the refiner's first step)."""

    def __init__(self, n_classes: int, backbone_weights: str = ""):
        super().__init__()
        self.n_classes = int(n_classes)
        self.seg = SegNet(n_classes, backbone_weights)
        self.estimator = PoseNet(n_classes - 1, backbone_weights)
        self.refiner = PoseRefineNet(n_classes - 1)

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        out = {"seg": self.seg(batch["rgb"])}
        if "crop" in batch:
            r, t, c, emb = self.estimator(batch["crop"], batch["cloud"], batch["choose"], batch["cls"] - 1)
            out.update(quat=r, trans=t, conf=c)
            R, tt, _ = best_pose(r, t, c, batch["cloud"])
            x = torch.bmm(batch["cloud"] - tt[:, None], R)
            out["refine_quat"], out["refine_trans"] = self.refiner(x, emb, batch["cls"] - 1)
        return out


def build(cfg: DenseFusionConfig, meta: MethodMeta) -> DenseFusion:
    """DenseFusion for ``meta``'s objects: per-object heads for each of them, segmentation over
    objects + background."""
    return DenseFusion(meta.n_classes, cfg.backbone_weights)


# --------------------------------------------------------------------------------------------
# crops


def crop_box(mask: np.ndarray, hw: Sequence[int]) -> tuple[int, int, int, int]:
    """The original's get_bbox: the mask's bounding box grown to the next size of the border list
    (scaled from 480x640 to ``hw``), centred, shifted inside the image. -> (r0, r1, c0, c1)."""
    H, W = int(hw[0]), int(hw[1])
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    s = min(H / 480.0, W / 640.0)
    borders = [max(2, int(round(b * s))) for b in BORDER_LIST]

    def grow(n: int, limit: int) -> int:
        for b in borders:
            if b >= n:
                return min(b, limit)
        return limit

    rb, cb = grow(r1 - r0, H), grow(c1 - c0, W)
    rc, cc = (r0 + r1) // 2, (c0 + c1) // 2
    r0, c0 = rc - rb // 2, cc - cb // 2
    r0, c0 = min(max(r0, 0), H - rb), min(max(c0, 0), W - cb)
    return int(r0), int(r0 + rb), int(c0), int(c0 + cb)


def make_crop(rgb: torch.Tensor, xyz: torch.Tensor, mask: torch.Tensor, cfg: DenseFusionConfig,
              rng: np.random.Generator) -> dict | None:
    """One object's inputs from an image: rgb (3,H,W) in [0,1], xyz (H,W,3) mm of the input depth,
    mask (H,W) bool of its pixels. None when fewer than ``cfg.min_points`` pixels have depth.
    -> crop (3,S,S), cloud (N,3) m, choose (N,) index into the S x S crop, box (4,)."""
    H, W = mask.shape
    m = mask.numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    if not m.any():
        return None
    r0, r1, c0, c1 = crop_box(m, (H, W))
    pix = np.flatnonzero((m & (xyz[..., 2].numpy() > 0))[r0:r1, c0:c1].reshape(-1))
    if pix.size < max(1, int(cfg.min_points)):
        return None
    n = int(cfg.n_points)
    pix = rng.choice(pix, n, replace=False) if pix.size > n else np.resize(pix, n)   # 'wrap' pad
    h, w = r1 - r0, c1 - c0
    v, u = pix // w, pix % w
    cloud = xyz[r0:r1, c0:c1].reshape(-1, 3)[torch.from_numpy(pix)] / 1000.0
    S = int(cfg.crop_size)
    crop = F.interpolate(rgb[None, :, r0:r1, c0:c1], size=(S, S), mode="bilinear", align_corners=False)[0]
    cv = np.minimum((v + 0.5) * S / h, S - 1).astype(np.int64)
    cu = np.minimum((u + 0.5) * S / w, S - 1).astype(np.int64)
    return {"crop": crop, "cloud": cloud.to(torch.float32), "choose": torch.from_numpy(cv * S + cu),
            "box": torch.tensor([r0, r1, c0, c1], dtype=torch.int64)}


# --------------------------------------------------------------------------------------------
# the transform


class DenseFusionTransform:
    """A dataset item -> DenseFusion inputs at ``meta.image_size``.

    Always: ``rgb`` (3,H,W) in [0,1], ``depth`` (H,W) mm (input depth per ``cfg.depth_mode``),
    ``K``, ``scene_id``, ``im_id``. With labels: ``seg`` (H,W) class index per pixel (the
    segmentation target). With ``train``: one object instance picked at random among those with
    at least ``min_points`` pixels with depth (as the original), cropped from its ground-truth
    mask: ``crop`` (3,S,S), ``cloud`` (N,3) m (+ uniform translation noise), ``choose`` (N,),
    ``cls`` () class index, ``model_points`` (M,3) m, ``target`` (M,3) m (model points in the true
    pose, + the same noise), ``symmetric`` () bool, ``has_crop`` () bool (False when no object
    qualifies: zeros then, and the pose losses skip the sample).
    """

    def __init__(self, cfg: DenseFusionConfig, meta: MethodMeta, train: bool = True):
        self.cfg = cfg
        self.meta = meta
        self.train = bool(train)
        self.lut = meta.class_lut(max_obj_id=1000)

    def __call__(self, item: Mapping) -> dict:
        cfg, hw = self.cfg, self.meta.image_size
        K, depth, rgb, restored = resize_frame(item, hw, cfg.depth_mode)
        out = {"rgb": rgb, "depth": depth, "K": K, "scene_id": int(item.get("scene_id", 0)),
               "im_id": int(item.get("im_id", 0))}
        if "label" in item:
            label = resize_nearest(item["label"], hw).long()
            out["label"] = label
            out["seg"] = torch.from_numpy(self.lut[np.clip(label.numpy(), 0, len(self.lut) - 1)])
        if self.train:
            if "label" not in item:
                raise TdofError("DenseFusion training targets need labels (label, instance, obj_id, R, t)")
            out.update(self.pose_targets(rgb, depth, K, resize_nearest(item["instance"], hw), item))
        return out

    def pose_targets(self, rgb, depth, K, instance, item) -> dict:
        cfg = self.cfg
        seed = int(torch.randint(0, 2 ** 31 - 1, ()).item())
        rng = np.random.default_rng(seed)
        xyz = backproject(depth, K)
        obj = item["obj_id"].numpy().astype(np.int64)
        order = rng.permutation(len(obj))
        ins = instance.numpy()
        for g in order:
            o = int(obj[g])
            if o <= 0 or o >= len(self.lut) or self.lut[o] == 0:
                continue
            c = self.crop_for(rgb, xyz, torch.from_numpy(ins == g + 1), rng)
            if c is None:
                continue
            mp = self.meta.model_points[o]
            sel = rng.choice(len(mp), int(cfg.n_model_points), replace=len(mp) < int(cfg.n_model_points))
            mp = torch.as_tensor(mp[sel] / 1000.0, dtype=torch.float32)
            R = item["R"][g].to(torch.float32)
            t = item["t"][g].to(torch.float32) / 1000.0
            noise = torch.from_numpy(rng.uniform(-1, 1, 3) * cfg.noise_trans_mm / 1000.0).to(torch.float32)
            c.update(cloud=c["cloud"] + noise, cls=torch.tensor(int(self.lut[o])), model_points=mp,
                     target=mp @ R.T + t + noise, symmetric=torch.tensor(bool(self.meta.symmetric[o])),
                     has_crop=torch.tensor(True))
            return c
        S, N, M = int(cfg.crop_size), int(cfg.n_points), int(cfg.n_model_points)
        return {"crop": torch.zeros(3, S, S), "cloud": torch.zeros(N, 3), "choose": torch.zeros(N, dtype=torch.int64),
                "box": torch.zeros(4, dtype=torch.int64), "cls": torch.tensor(1), "model_points": torch.zeros(M, 3),
                "target": torch.zeros(M, 3), "symmetric": torch.tensor(False), "has_crop": torch.tensor(False)}

    def crop_for(self, rgb, xyz, mask, rng):
        return make_crop(rgb, xyz, mask, self.cfg, rng)


# --------------------------------------------------------------------------------------------
# loss


def point_distances(pred: torch.Tensor, target: torch.Tensor, symmetric: torch.Tensor) -> torch.Tensor:
    """pred (B,P,M,3) model points under P poses, target (B,M,3), symmetric (B,) bool -> (B,P):
    mean distance to the corresponding target point (ADD) or, for symmetric objects, to the
    closest target point (ADD-S, KNN in torch)."""
    B, P, M, _ = pred.shape
    d_add = (pred - target[:, None]).norm(dim=-1).mean(-1)
    if not bool(symmetric.any()):
        return d_add
    nn_idx = knn(pred.detach().reshape(B, P * M, 3), target, 1)[..., 0]          # (B,P*M)
    closest = torch.gather(target, 1, nn_idx[..., None].expand(B, P * M, 3)).view(B, P, M, 3)
    d_adds = (pred - closest).norm(dim=-1).mean(-1)
    return torch.where(symmetric[:, None], d_adds, d_add)


def best_pose(quat: torch.Tensor, trans: torch.Tensor, conf: torch.Tensor, cloud: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The most confident point's pose: quat (B,N,4), trans (B,N,3) offsets, conf (B,N), cloud
    (B,N,3) -> R (B,3,3), t (B,3) = cloud_i + trans_i, its confidence (B,)."""
    score, i = conf.max(1)
    bi = torch.arange(quat.shape[0], device=quat.device)
    return quaternion_to_matrix(quat[bi, i]), cloud[bi, i] + trans[bi, i], score


def to_frame(points: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Points (B,N,3) in the frame of the pose (R, t): R^T (p - t)."""
    return torch.bmm(points - t[:, None], R)


def pose_loss(out: Mapping[str, torch.Tensor], batch: Mapping[str, torch.Tensor], w: float
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The estimator's loss (lib/loss.py): mean over points of dis_i c_i - w log c_i, mean over the
    samples that have a crop; and the distance of the most confident pose (B,)."""
    R = quaternion_to_matrix(out["quat"])                                         # (B,N,3,3)
    t = batch["cloud"] + out["trans"]
    pred = torch.einsum("bnij,bmj->bnmi", R, batch["model_points"]) + t[:, :, None]
    dis = point_distances(pred, batch["target"], batch["symmetric"])                # (B,N)
    c = out["conf"].clamp_min(1e-12)
    per = (dis * c - w * torch.log(c)).mean(1)
    ok = batch["has_crop"].to(per.dtype)
    best = dis.detach().gather(1, out["conf"].argmax(1, keepdim=True))[:, 0]
    return (per * ok).sum() / ok.sum().clamp_min(1), best


def refine_loss(net: DenseFusion, out: Mapping[str, torch.Tensor], batch: Mapping[str, torch.Tensor],
                iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The refiner's loss (lib/loss_refiner.py), summed over ``iterations``: after each
    correction, the ADD(-S) distance of the corrected model points to the target, both in the
    frame of the previous estimate; the estimator's outputs are detached (it is not trained by it)."""
    cls = batch["cls"] - 1
    R, t, _ = best_pose(out["quat"].detach(), out["trans"].detach(), out["conf"].detach(), batch["cloud"])
    pts = to_frame(batch["cloud"], R, t)
    target = to_frame(batch["target"], R, t)
    emb = None
    ok = batch["has_crop"].to(pts.dtype)
    total = pts.new_zeros(())
    dis = pts.new_zeros(pts.shape[0])
    for it in range(int(iterations)):
        if it == 0:
            qr, tr = out["refine_quat"], out["refine_trans"]
        else:
            if emb is None:
                emb = embedding(net, batch)
            qr, tr = net.refiner(pts, emb, cls)
        Rr = quaternion_to_matrix(qr)
        pred = torch.bmm(batch["model_points"], Rr.transpose(1, 2)) + tr[:, None]
        dis = point_distances(pred[:, None], target, batch["symmetric"])[:, 0]
        total = total + (dis * ok).sum() / ok.sum().clamp_min(1)
        pts = to_frame(pts, Rr.detach(), tr.detach())
        target = to_frame(target, Rr.detach(), tr.detach())
    return total, dis


def embedding(net: DenseFusion, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """The estimator's colour embedding at the chosen pixels (B,32,N), no gradient."""
    with torch.no_grad():
        emb = net.estimator.cnn(batch["crop"])
        B, D = emb.shape[:2]
        return torch.gather(emb.view(B, D, -1), 2, batch["choose"].view(B, 1, -1).expand(B, D, -1))


def loss(net: DenseFusion, batch: Mapping[str, torch.Tensor], cfg: DenseFusionConfig, meta: MethodMeta
         ) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of ``cfg.stage``: "seg" cross-entropy of the segmentation; "pose" the estimator's
    confidence-weighted ADD(-S); "refine" the refiner's ADD(-S) over its iterations (estimator
    frozen); "joint" their sum. Parts: seg, pose, dis (mm, most confident point), refine, dis_refined (mm)."""
    stage = cfg.stage
    parts: dict[str, float] = {}
    total = None
    if stage in ("seg", "joint"):
        if "seg" not in batch:
            raise TdofError("the segmentation loss needs labels (the transform's 'seg')")
        logits = net.seg(batch["rgb"])
        l_seg = F.cross_entropy(logits, batch["seg"])
        parts["seg"] = float(l_seg.detach())
        total = l_seg
    if stage in ("pose", "refine", "joint"):
        if "crop" not in batch:
            raise TdofError("the pose losses need training crops (DenseFusionTransform(train=True))")
        if stage == "refine":
            with torch.no_grad():
                r, t, c, _ = net.estimator(batch["crop"], batch["cloud"], batch["choose"], batch["cls"] - 1)
            R, tt, _ = best_pose(r, t, c, batch["cloud"])
            q_r, t_r = net.refiner(to_frame(batch["cloud"], R, tt), embedding(net, batch), batch["cls"] - 1)
            out = {"quat": r, "trans": t, "conf": c, "refine_quat": q_r, "refine_trans": t_r}
        else:
            r, t, c, emb = net.estimator(batch["crop"], batch["cloud"], batch["choose"], batch["cls"] - 1)
            out = {"quat": r, "trans": t, "conf": c}
            if stage == "joint":
                R, tt, _ = best_pose(r.detach(), t.detach(), c.detach(), batch["cloud"])
                out["refine_quat"], out["refine_trans"] = net.refiner(to_frame(batch["cloud"], R, tt), emb,
                                                                      batch["cls"] - 1)
        l_pose, best = pose_loss(out, batch, cfg.w)
        ok = batch["has_crop"]
        parts["pose"] = float(l_pose.detach())
        parts["dis_mm"] = float(1000 * best[ok].mean()) if bool(ok.any()) else float("nan")
        if stage in ("pose", "joint"):
            total = l_pose if total is None else total + l_pose
        if stage in ("refine", "joint"):
            l_ref, dis = refine_loss(net, out, batch, cfg.refine_iterations)
            parts["refine"] = float(l_ref.detach())
            parts["dis_refined_mm"] = float(1000 * dis.detach()[ok].mean()) if bool(ok.any()) else float("nan")
            total = l_ref if total is None else total + l_ref
    parts["loss"] = float(total.detach())
    return total, parts


# --------------------------------------------------------------------------------------------
# pose recovery


def refine_pose(net: DenseFusion, R: torch.Tensor, t: torch.Tensor, cloud: torch.Tensor, emb: torch.Tensor,
                cls: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply the refiner ``iterations`` times: T <- T @ T_correction (eval_ycb.py); R (B,3,3), t (B,3) m."""
    for _ in range(int(iterations)):
        qr, tr = net.refiner(to_frame(cloud, R, t), emb, cls)
        Rr = quaternion_to_matrix(qr)
        t = t + torch.bmm(R, tr[..., None])[..., 0]
        R = torch.bmm(R, Rr)
    return R, t


def image_crops(rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, classes: torch.Tensor,
                cfg: DenseFusionConfig) -> list[tuple[int, int, dict]]:
    """One crop per (image, predicted class) of a batch: rgb (B,3,H,W), depth (B,H,W) mm, K (B,3,3),
    classes (B,H,W) -> [(b, class index, crop dict)]."""
    crops = []
    cpu_cls = classes.cpu()
    for b in range(rgb.shape[0]):
        xyz = backproject(depth[b].cpu(), K[b].cpu())
        rng = np.random.default_rng(int(cfg.seed))
        for c in torch.unique(cpu_cls[b]).tolist():
            if c == 0:
                continue
            cr = make_crop(rgb[b].cpu(), xyz, cpu_cls[b] == c, cfg, rng)
            if cr is not None:
                crops.append((b, int(c), cr))
    return crops


@torch.no_grad()
def predict_poses(net: DenseFusion, batch: Mapping[str, torch.Tensor], cfg: DenseFusionConfig, meta: MethodMeta
                  ) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
    """Rows (b, obj_id, score, R (3,3), t (3,) mm): segmentation -> crops -> most confident point's
    pose -> ``refine_iterations`` refinements; score = that point's confidence."""
    dev = batch["rgb"].device
    classes = net.seg(batch["rgb"]).argmax(1)
    crops = image_crops(batch["rgb"], batch["depth"], batch["K"], classes, cfg)
    if not crops:
        return []
    crop = torch.stack([c["crop"] for _, _, c in crops]).to(dev)
    cloud = torch.stack([c["cloud"] for _, _, c in crops]).to(dev)
    choose = torch.stack([c["choose"] for _, _, c in crops]).to(dev)
    cls = torch.tensor([k - 1 for _, k, _ in crops], device=dev)
    r, t, c, emb = net.estimator(crop, cloud, choose, cls)
    R, tt, score = best_pose(r, t, c, cloud)
    R, tt = refine_pose(net, R, tt, cloud, emb, cls, cfg.refine_iterations)
    R, tt = R.double().cpu().numpy(), (tt.double() * 1000.0).cpu().numpy()
    return [(b, meta.obj_of(k), float(score[i]), R[i], tt[i]) for i, (b, k, _) in enumerate(crops)]


def example_batch(cfg: DenseFusionConfig, meta: MethodMeta, batch_size: int = 1) -> dict:
    """Inputs for profiling at ``meta.image_size``: a frame (rgb, depth, K) and one crop per image
    (the estimator's inputs), without a dataset."""
    H, W = meta.image_size
    g = torch.Generator().manual_seed(0)
    S, N = int(cfg.crop_size), int(cfg.n_points)
    return {"rgb": torch.rand(batch_size, 3, H, W, generator=g), "crop": torch.rand(batch_size, 3, S, S, generator=g),
            "cloud": torch.rand(batch_size, N, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 0.7]),
            "choose": torch.randint(0, S * S, (batch_size, N), generator=g),
            "cls": torch.ones(batch_size, dtype=torch.int64)}


class DenseFusionMethod(PoseMethod):
    """DenseFusion's pieces (the functions of this module); the network takes the whole batch."""

    config_class = DenseFusionConfig

    def build(self, cfg: DenseFusionConfig, meta: MethodMeta) -> DenseFusion:
        return build(cfg, meta)

    def transform(self, cfg: DenseFusionConfig, meta: MethodMeta, train: bool = False) -> DenseFusionTransform:
        return DenseFusionTransform(cfg, meta, train=train)

    def loss(self, net: DenseFusion, batch: Mapping, cfg: DenseFusionConfig, meta: MethodMeta
             ) -> tuple[torch.Tensor, dict]:
        return loss(net, batch, cfg, meta)

    def predict_poses(self, net: DenseFusion, batch: Mapping, cfg: DenseFusionConfig, meta: MethodMeta) -> list:
        return predict_poses(net, batch, cfg, meta)

    def forward(self, net: DenseFusion, batch: Mapping) -> dict:
        return forward_batch(net, batch)

    def example_batch(self, cfg: DenseFusionConfig, meta: MethodMeta, batch_size: int = 1) -> dict:
        return example_batch(cfg, meta, batch_size)


__all__ = ["DenseFusion", "DenseFusionConfig", "DenseFusionMethod", "DenseFusionTransform", "PoseNet", "PoseRefineNet",
           "SegNet", "best_pose", "build", "crop_box", "example_batch", "loss", "make_crop", "point_distances",
           "predict_poses", "refine_pose"]
