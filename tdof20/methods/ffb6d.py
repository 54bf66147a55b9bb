"""FFB6D (He et al., CVPR 2021): full-flow bidirectional fusion of a PSPNet-ResNet34 on RGB and a
RandLA-Net on the point cloud, with PVN3D's heads (segmentation, centre offsets, keypoint offsets),
MeanShift voting and a least-squares fit — in plain PyTorch, the same code on CPU and GPU.

    cfg = FFB6DConfig()                       # 12,800 points at 480x640, k = 16, 4 RandLA layers
    net = build(cfg, meta)
    tf = FFB6DTransform(cfg, meta, train=True)
    batch = collate([tf(item) for item in items])
    total, parts = loss(net, batch, cfg, meta)
    rows = predict_poses(net, batch, cfg, meta)   # [(b, obj_id, score, R (3,3), t (3,) mm), ...]

Network (the original's ``ffb6d.py``; image strides at 480x640)::

    rgb ─conv1/bn/relu/maxpool (1/4)─┬ layer1 (1/4, 64) ─ layer2 (1/8, 128) ─ layer3+4 dilated (1/8, 512)
                                     │  ─ PSP (1/8, 1024) ─ up_1 (1/4, 256) ─ up_2 (1/2, 64) ─ final (1/2, 64)
                                     │  ─ up_3 + final (1/1, 64)
    points (xyz, rgb, normals) ─fc0─ RandLA encoder 4 x (N/4 each) ─ decoder 4 x (nearest up-sampling)
    after each of the 4 encoder and the first 3 decoder stages, both ways:
        point -> pixel (p2r): every pixel takes the features of its nearest point (1x1 conv first),
                              concatenated with the pixel's own features, 1x1 conv
        pixel -> point (r2p): every point max-pools the features of its 16 nearest pixels (1x1 conv),
                              concatenated with the point's own features, 1x1 conv
    the full-resolution pixel features at the sampled points ++ the point features -> three heads
    (3 x [1x1 conv 128 + BN + ReLU] + 1x1 conv): segmentation logits, centre offset, 8 keypoint offsets.

Offsets are in metres (as the original: point minus keypoint); everything at the interface is mm.
The neighbour indices (RandLA's kNN and sub-sampling, p2r/r2p) are computed in the transform with
scipy's cKDTree (:func:`tdof20.methods.randla.point_pyramid`) — no compiled extension.

Pose recovery (PVN3D's ``cal_frame_poses``): per predicted class, MeanShift (Gaussian kernel,
bandwidth 40 mm, the original's radius) of the centre votes; the points whose centre vote lies
within one bandwidth of the winning mode vote for the keypoints; MeanShift per keypoint; least
squares (Kabsch) of the model keypoints + centre onto the voted ones. All classes and keypoints of
a batch go through one batched MeanShift (:mod:`tdof20.methods.ffb6d_pose`) with bounded work: 32
seeds shift over 512 of the votes (at most 20 iterations), the seed with the most votes within one
bandwidth wins and alone shifts over all votes until it moves < bandwidth/1000 (the original's stop
threshold); the mode is the median of its inlier votes. The original runs a blurring MeanShift with
every vote as a seed: N^2 kernel entries per iteration, up to 300 iterations (our earlier
every-vote-a-seed version took about 18 minutes per 480x640 image on one CPU thread at 4,000 votes
per cluster); this one takes well under 0.1 s (benchmarks/ffb6d_recovery.py).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tdof20.errors import TdofError
from tdof20.geometry.normals import normals_from_xyz
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod, forward_batch
from tdof20.methods.data import (DEFAULT_DEPTH_MODE, backproject, check_depth_mode, collate, resize_frame,
                                 resize_nearest)
from tdof20.methods.ffb6d_pose import recover_poses
from tdof20.methods.pspnet import PSPNet
from tdof20.methods.randla import RandLANet, knn_numpy, nearest_interpolation, point_pyramid, random_sample

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: image strides of the pixel maps the 4 encoder and 3 decoder fusions use (the original's ds_sr, up_sr)
DS_STRIDES = (4, 8, 8, 8)
UP_STRIDES = (4, 2, 2)


@dataclass
class FFB6DConfig:
    """Every option of FFB6D, with defaults that work (plain types: TOML-settable).

    n_points: points sampled from the input depth (the original: 480*640/24 = 12,800); fewer for
        small images (n_points must leave >= 1 point after the 4 sub-samplings: >= 256).
    """

    n_points: int = 12800
    knn: int = 16
    sub_ratios: tuple[int, ...] = (4, 4, 4, 4)
    d_out: tuple[int, ...] = (32, 64, 128, 256)
    depth_mode: str = DEFAULT_DEPTH_MODE
    backbone_weights: str = ""            # a torchvision resnet34 .pth for the RGB encoder ("" = random)
    dilated: bool = False                 # layer3/layer4 dilated (2, 4); the published FFB6D runs them undilated
    head_channels: int = 128
    # loss (the original: focal loss gamma 2 x 2.0, keypoint and centre L1 x 1.0)
    w_seg: float = 2.0
    w_kp: float = 1.0
    w_ctr: float = 1.0
    focal_gamma: float = 2.0
    # pose recovery
    bandwidth_mm: float = 40.0            # the original's radius 0.04 m
    meanshift_iters: int = 300            # the winning mode's iterations at most (the original's max_iter)
    max_votes: int = 4000                 # votes per MeanShift cluster (a random subset beyond)
    meanshift_seeds: int = 32             # seeds per cluster (the original: every vote, a blurring MeanShift)
    meanshift_seed_votes: int = 512       # votes the seeds shift over (evenly spaced subset)
    meanshift_seed_iters: int = 20        # seed iterations at most (they stop at bandwidth/100)
    meanshift_tol: float = 1e-3           # the winner stops below tol x bandwidth (the original's 1e-3)
    min_points: int = 10                  # points a class needs to get a pose
    seed: int = 0

    def __post_init__(self) -> None:
        check_depth_mode(self.depth_mode)
        self.sub_ratios = tuple(int(r) for r in self.sub_ratios)
        self.d_out = tuple(int(d) for d in self.d_out)
        if len(self.sub_ratios) != 4 or len(self.d_out) != 4:
            raise TdofError("FFB6D needs 4 RandLA layers: sub_ratios and d_out of 4 values each")
        if int(self.n_points) < int(np.prod(self.sub_ratios)):
            raise TdofError(f"n_points={self.n_points} leaves no point after sub-sampling by {self.sub_ratios} "
                            f"(need >= {int(np.prod(self.sub_ratios))})")


# --------------------------------------------------------------------------------------------
# the network


class ConvBNReLU(nn.Sequential):
    """The original's fusion layer: 1x1 Conv2d + BN + ReLU on (B,C,N,1) or (B,C,H,W)."""

    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def head(cin: int, cout: int, hidden: int = 128) -> nn.Sequential:
    layers: list[nn.Module] = []
    c = cin
    for _ in range(3):
        layers += [nn.Conv1d(c, hidden, 1, bias=False), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True)]
        c = hidden
    layers.append(nn.Conv1d(c, cout, 1))
    return nn.Sequential(*layers)


class FFB6D(nn.Module):
    """``forward(batch) -> {"seg": (B,n_classes,N) logits, "kp_ofs": (B,K-1,N,3) m, "ctr_ofs": (B,1,N,3) m}``
    where batch is a collated :class:`FFB6DTransform` output (rgb, cld_rgb_nrm, choose and the
    neighbour indices)."""

    def __init__(self, n_classes: int, n_keypoints: int = 9, d_out: Sequence[int] = (32, 64, 128, 256),
                 head_channels: int = 128, dilated: bool = False, backbone_weights: str = ""):
        super().__init__()

        self.n_classes = int(n_classes)
        self.n_kps = int(n_keypoints) - 1          # the keypoint head: all but the centre
        # FFB6D's PSPNet-ResNet34: 64-d features, LogSoftmax in `final` and undilated stride-8
        # layer3/layer4 as the published code runs them
        cnn = PSPNet(backbone="resnet34", feat_dim=64, dilated=dilated, log_softmax=True)
        if backbone_weights:
            cnn.load_backbone_weights(backbone_weights)
        stages = pspnet_stages(cnn)
        self.cnn_pre_stages = stages["pre"]
        self.cnn_ds_stages = nn.ModuleList(stages["ds"])
        self.cnn_up_stages = nn.ModuleList(stages["up"])
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.rndla = RandLANet(in_channels=9, d_out=d_out)
        ds_rgb = (64, 128, 512, 1024)
        ds_pt = self.rndla.encoder_channels
        up_rgb = (256, 64, 64)
        up_pt = self.rndla.decoder_channels[:3]
        self.ds_fuse_r2p_pre = nn.ModuleList(ConvBNReLU(r, p) for r, p in zip(ds_rgb, ds_pt))
        self.ds_fuse_r2p_fuse = nn.ModuleList(ConvBNReLU(2 * p, p) for p in ds_pt)
        self.ds_fuse_p2r_pre = nn.ModuleList(ConvBNReLU(p, r) for r, p in zip(ds_rgb, ds_pt))
        self.ds_fuse_p2r_fuse = nn.ModuleList(ConvBNReLU(2 * r, r) for r in ds_rgb)
        self.up_fuse_r2p_pre = nn.ModuleList(ConvBNReLU(r, p) for r, p in zip(up_rgb, up_pt))
        self.up_fuse_r2p_fuse = nn.ModuleList(ConvBNReLU(2 * p, p) for p in up_pt)
        self.up_fuse_p2r_pre = nn.ModuleList(ConvBNReLU(p, r) for r, p in zip(up_rgb, up_pt))
        self.up_fuse_p2r_fuse = nn.ModuleList(ConvBNReLU(2 * r, r) for r in up_rgb)
        c = 64 + self.rndla.decoder_channels[-1]
        self.rgbd_seg_layer = head(c, self.n_classes, head_channels)
        self.ctr_ofst_layer = head(c, 3, head_channels)
        self.kp_ofst_layer = head(c, 3 * self.n_kps, head_channels)

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        rgb = (batch["rgb"] - self.rgb_mean) / self.rgb_std
        rgb_emb = self.cnn_pre_stages(rgb)
        p_emb = self.rndla.fc0(batch["cld_rgb_nrm"])[..., None]              # (B,8,N,1)
        ds_emb = []
        for i in range(4):
            rgb0 = self.cnn_ds_stages[i](rgb_emb)
            bs, c, hr, wr = rgb0.shape
            f_enc = self.rndla.dilated_res_blocks[i](p_emb, batch[f"xyz{i}"], batch[f"nei{i}"])
            p0 = random_sample(f_enc, batch[f"sub{i}"])
            if i == 0:
                ds_emb.append(f_enc)
            p2r = nearest_interpolation(self.ds_fuse_p2r_pre[i](p0), batch[f"p2r_ds{i}"]).view(bs, -1, hr, wr)
            rgb_emb = self.ds_fuse_p2r_fuse[i](torch.cat([rgb0, p2r], dim=1))
            r2p = self.ds_fuse_r2p_pre[i](random_sample(rgb0.reshape(bs, c, hr * wr), batch[f"r2p_ds{i}"]))
            p_emb = self.ds_fuse_r2p_fuse[i](torch.cat([p0, r2p], dim=1))
            ds_emb.append(p_emb)
        n_up = len(self.rndla.decoder_blocks)
        for i in range(n_up - 1):
            rgb0 = self.cnn_up_stages[i](rgb_emb)
            bs, c, hr, wr = rgb0.shape
            f_int = nearest_interpolation(p_emb, batch[f"interp{n_up - i - 1}"])
            p0 = self.rndla.decoder_blocks[i](torch.cat([ds_emb[-i - 2], f_int], dim=1))
            p2r = nearest_interpolation(self.up_fuse_p2r_pre[i](p0), batch[f"p2r_up{i}"]).view(bs, -1, hr, wr)
            rgb_emb = self.up_fuse_p2r_fuse[i](torch.cat([rgb0, p2r], dim=1))
            r2p = self.up_fuse_r2p_pre[i](random_sample(rgb0.reshape(bs, c, hr * wr), batch[f"r2p_up{i}"]))
            p_emb = self.up_fuse_r2p_fuse[i](torch.cat([p0, r2p], dim=1))
        rgb_emb = self.cnn_up_stages[n_up - 1](rgb_emb)
        f_int = nearest_interpolation(p_emb, batch["interp0"])
        p_emb = self.rndla.decoder_blocks[n_up - 1](torch.cat([ds_emb[0], f_int], dim=1))[..., 0]
        bs, di = rgb_emb.shape[:2]
        choose = batch["choose"].reshape(bs, 1, -1).expand(bs, di, -1)
        rgb_c = torch.gather(rgb_emb.reshape(bs, di, -1), 2, choose)
        rgbd = torch.cat([rgb_c, p_emb], dim=1)
        n = rgbd.shape[2]
        seg = self.rgbd_seg_layer(rgbd)
        kp = self.kp_ofst_layer(rgbd).view(bs, self.n_kps, 3, n).permute(0, 1, 3, 2)
        ctr = self.ctr_ofst_layer(rgbd).view(bs, 1, 3, n).permute(0, 1, 3, 2)
        return {"seg": seg, "kp_ofs": kp, "ctr_ofs": ctr}


def pspnet_stages(cnn: nn.Module) -> dict:
    """The PSPNet's modules as FFB6D's stages: pre (conv1, bn1, relu, maxpool), 4 down-sampling
    stages (layer1, layer2, layer3 + layer4, PSP + dropout) and 4 up-sampling stages
    (up_1, up_2, final, up_3 + final — ``final`` is shared, as in the original)."""
    enc = cnn.backbone
    pre = nn.Sequential(enc.conv1, enc.bn1, enc.relu, enc.maxpool)
    ds = [enc.layer1, enc.layer2, nn.Sequential(enc.layer3, enc.layer4), nn.Sequential(cnn.psp, cnn.drop_1)]
    up = [nn.Sequential(cnn.up_1, cnn.drop_2), nn.Sequential(cnn.up_2, cnn.drop_2), cnn.final,
          nn.Sequential(cnn.up_3, cnn.final)]
    return {"pre": pre, "ds": ds, "up": up}


def build(cfg: FFB6DConfig, meta: MethodMeta) -> FFB6D:
    """The FFB6D network for ``meta``'s objects (classes = objects + background)."""
    check_image_size(meta.image_size)
    return FFB6D(meta.n_classes, meta.n_keypoints, cfg.d_out, cfg.head_channels, cfg.dilated, cfg.backbone_weights)


def check_image_size(hw: Sequence[int]) -> None:
    if int(hw[0]) % 8 or int(hw[1]) % 8:
        raise TdofError(f"FFB6D needs an image size divisible by 8 (its stride-8 encoder), got {tuple(hw)}")


# --------------------------------------------------------------------------------------------
# the transform


class FFB6DTransform:
    """A dataset item -> FFB6D inputs (+ targets with ``train``) at ``meta.image_size``.

    Output: ``rgb`` (3,H,W) in [0,1]; ``K`` (3,3); ``depth`` (H,W) mm (the input depth per
    ``cfg.depth_mode``); ``choose`` (N,) pixel index of each sampled point; ``cld_rgb_nrm`` (9,N):
    xyz in metres, rgb in [0,1], unit normals (:func:`tdof20.geometry.normals.normals_from_xyz`);
    RandLA's ``xyz{i}``, ``nei{i}``, ``sub{i}``, ``interp{i}`` (i = 0..3); the fusion indices
    ``r2p_ds{i}`` (N_{i+1},16) / ``p2r_ds{i}`` (pixels,1) at strides (4, 8, 8, 8) and
    ``r2p_up{i}`` / ``p2r_up{i}`` (i = 0..2) at strides (4, 2, 2). With targets: ``labels`` (N,)
    class index of each point, ``kp_ofs`` (N,K-1,3) and ``ctr_ofs`` (N,3) point minus keypoint in
    metres (0 off the objects), ``n_gt``-free, so items stack.

    Points: the pixels with input depth, N sampled at random (wrapped when fewer, as the original),
    then shuffled; an image without any depth samples all pixels (their points at the origin).
    Sampling is seeded by torch's generator when training (DataLoader workers differ) and by
    ``cfg.seed`` + the image id otherwise (repeatable predictions).
    """

    def __init__(self, cfg: FFB6DConfig, meta: MethodMeta, train: bool = True):
        check_image_size(meta.image_size)
        self.cfg = cfg
        self.meta = meta
        self.train = bool(train)
        self.lut = meta.class_lut(max_obj_id=1000)
        self.kp = meta.keypoint_array() / 1000.0                            # (C,K,3) m by class

    def __call__(self, item: Mapping) -> dict:
        cfg, hw = self.cfg, self.meta.image_size
        H, W = hw
        K, depth, rgb, restored = resize_frame(item, hw, cfg.depth_mode)
        xyz_map = (backproject(depth, K) / 1000.0).numpy()                   # (H,W,3) m

        nrm = normals_from_xyz(xyz_map)
        seed = int(torch.randint(0, 2 ** 31 - 1, ()).item()) if self.train else \
            (int(cfg.seed) * 1000003 + int(item.get("scene_id", 0)) * 10007 + int(item.get("im_id", 0))) % 2 ** 31
        rng = np.random.default_rng(seed)
        valid = np.flatnonzero(depth.numpy().reshape(-1) > 0)
        if valid.size == 0:
            valid = np.arange(H * W)
        n = int(cfg.n_points)
        choose = rng.choice(valid, n, replace=False) if valid.size > n else np.resize(rng.permutation(valid), n)
        choose = choose[rng.permutation(n)]
        cld = xyz_map.reshape(-1, 3)[choose].astype(np.float32)
        rgb_pt = rgb.permute(1, 2, 0).reshape(-1, 3).numpy()[choose]
        nrm_pt = nrm.reshape(-1, 3)[choose]
        out = {"rgb": rgb, "K": K, "depth": depth, "choose": torch.from_numpy(choose.astype(np.int64)),
               "cld_rgb_nrm": torch.from_numpy(np.concatenate([cld, rgb_pt, nrm_pt], 1).T.astype(np.float32).copy()),
               "scene_id": int(item.get("scene_id", 0)), "im_id": int(item.get("im_id", 0))}
        out.update({k: torch.from_numpy(v) for k, v in fusion_indices(cld, xyz_map, cfg.knn, cfg.sub_ratios).items()})
        if "label" in item:
            out["label"] = resize_nearest(item["label"], hw)
        if self.train:
            if "label" not in item:
                raise TdofError("FFB6D training targets need labels (label, instance, obj_id, R, t)")
            out.update(self.targets(out["label"], resize_nearest(item["instance"], hw), choose, cld,
                                    item["obj_id"], item["R"], item["t"]))
        return out

    def targets(self, label: torch.Tensor, instance: torch.Tensor, choose: np.ndarray, cld: np.ndarray,
                obj_id: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> dict:
        lab = label.numpy().reshape(-1)[choose]
        ins = instance.numpy().reshape(-1)[choose].astype(np.int64)
        obj = obj_id.numpy().astype(np.int64)
        cls_of_gt = self.lut[np.clip(obj, 0, len(self.lut) - 1)]             # (G,) 0 = not ours
        gi = np.clip(ins - 1, 0, max(0, len(obj) - 1))
        on = (ins > 0) & (lab > 0) & (cls_of_gt[gi] > 0) if len(obj) else np.zeros(len(choose), bool)
        cls = np.where(on, cls_of_gt[gi], 0)
        kp_cam = np.einsum("gij,gkj->gki", R.numpy().astype(np.float64), self.kp[cls_of_gt]) \
            + t.numpy().astype(np.float64)[:, None] / 1000.0                  # (G,K,3) m
        ofs = cld[:, None].astype(np.float64) - kp_cam[gi]                    # (N,K,3)
        ofs = np.where(on[:, None, None], ofs, 0.0).astype(np.float32)
        return {"labels": torch.from_numpy(cls.astype(np.int64)), "ctr_ofs": torch.from_numpy(ofs[:, 0].copy()),
                "kp_ofs": torch.from_numpy(ofs[:, 1:].copy())}


def fusion_indices(cld: np.ndarray, xyz_map: np.ndarray, k: int = 16, ratios: Sequence[int] = (4, 4, 4, 4)
                   ) -> dict[str, np.ndarray]:
    """All neighbour indices of one image (FFB6D's dataset ``get_item``): RandLA's pyramid of the
    sampled points ``cld`` (N,3) and the p2r / r2p indices between the points of each stage and
    the pixels of the map at that stage's stride (``xyz_map`` (H,W,3), sub-sampled at
    ``[::s, ::s]``)."""
    pyr = point_pyramid(cld, k, ratios)
    out = {f"{name}{i}": pyr[f"{name}{i}"] for i in range(len(ratios)) for name in ("xyz", "nei", "sub", "interp")}
    maps = {s: xyz_map[::s, ::s].reshape(-1, 3) for s in set(DS_STRIDES) | set(UP_STRIDES)}
    for i, s in enumerate(DS_STRIDES):
        sub = pyr[f"xyz{i + 1}"]
        out[f"r2p_ds{i}"] = knn_numpy(sub, maps[s], k)
        out[f"p2r_ds{i}"] = knn_numpy(maps[s], sub, 1)
    for i, s in enumerate(UP_STRIDES):
        pts = pyr[f"xyz{len(ratios) - i - 1}"]
        out[f"r2p_up{i}"] = knn_numpy(pts, maps[s], k)
        out[f"p2r_up{i}"] = knn_numpy(maps[s], pts, 1)
    return {k_: (v.astype(np.float32) if k_.startswith("xyz") else v.astype(np.int64)) for k_, v in out.items()}


def example_batch(cfg: FFB6DConfig, meta: MethodMeta, batch_size: int = 1) -> dict:
    """A batch of inputs at ``meta.image_size`` from a synthetic frame (a tilted plane 0.7-0.8 m
    away): for profiling (multiply-adds, latency) without a dataset."""

    H, W = meta.image_size
    f = 0.9 * W
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=torch.float32)
    v = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    depth = 700.0 + 100.0 * v / H
    g = torch.Generator().manual_seed(0)
    item = {"rgb": torch.randint(0, 256, (3, H, W), generator=g, dtype=torch.uint8), "depth": depth,
            "depth_restored": depth, "K": K, "scene_id": 0, "im_id": 0}
    tf = FFB6DTransform(cfg, meta, train=False)
    return collate([tf(item) for _ in range(batch_size)])


# --------------------------------------------------------------------------------------------
# the loss


def focal_loss(logits: torch.Tensor, target: torch.Tensor, gamma: float = 2.0) -> torch.Tensor:
    """Mean focal loss (the original's FocalLoss, gamma 2): logits (B,C,N), target (B,N)."""
    logp = F.log_softmax(logits, dim=1).gather(1, target[:, None])[:, 0]
    return (-(1 - logp.exp()) ** gamma * logp).mean()


def offset_l1(pred: torch.Tensor, target: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
    """The original's of_l1_loss, summed over keypoints, mean over the batch: pred (B,K,N,3),
    target (B,N,K,3), on (B,N) bool — L1 over object points / (their count + 1e-3)."""
    w = on.to(pred.dtype)[:, None, :, None]
    diff = (pred - target.permute(0, 2, 1, 3)).abs() * w
    per = diff.sum(dim=(2, 3)) / (w.sum(dim=(2, 3)) + 1e-3)                  # (B,K)
    return per.sum(1).mean()


def loss(net: FFB6D, batch: Mapping[str, torch.Tensor], cfg: FFB6DConfig, meta: MethodMeta
         ) -> tuple[torch.Tensor, dict[str, float]]:
    """2 x focal(seg) + L1(keypoint offsets) + L1(centre offsets) (FFB6D's train_ycb.py)."""
    out = net(batch)
    labels = batch["labels"]
    on = labels > 0
    l_seg = focal_loss(out["seg"], labels, cfg.focal_gamma)
    l_kp = offset_l1(out["kp_ofs"], batch["kp_ofs"], on)
    l_ctr = offset_l1(out["ctr_ofs"], batch["ctr_ofs"][:, :, None], on)
    total = cfg.w_seg * l_seg + cfg.w_kp * l_kp + cfg.w_ctr * l_ctr
    acc = (out["seg"].argmax(1) == labels).float().mean()
    return total, {"loss": float(total.detach()), "seg": float(l_seg.detach()), "kp_ofs": float(l_kp.detach()),
                   "ctr_ofs": float(l_ctr.detach()), "seg_acc": float(acc)}


@torch.no_grad()
def predict_poses(net: FFB6D, batch: Mapping[str, torch.Tensor], cfg: FFB6DConfig, meta: MethodMeta
                  ) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
    """Rows (b, obj_id, score, R (3,3), t (3,) mm) of a batch: argmax segmentation of the points,
    then :func:`recover_poses`."""
    out = net(batch)
    prob = torch.softmax(out["seg"].float(), dim=1)
    conf, cls = prob.max(1)
    pts = batch["cld_rgb_nrm"][:, :3].transpose(1, 2).float() * 1000.0
    kps = torch.as_tensor(meta.keypoint_array(), dtype=torch.float32, device=pts.device)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    rows = recover_poses(pts, cls, out["ctr_ofs"][:, 0].float() * 1000.0, out["kp_ofs"].float() * 1000.0, kps,
                         cfg.bandwidth_mm, cfg.meanshift_iters, cfg.max_votes, cfg.min_points, gen, conf,
                         cfg.meanshift_seeds, cfg.meanshift_seed_votes, cfg.meanshift_seed_iters, cfg.meanshift_tol)
    return [(b, meta.obj_of(c), s, R, t) for b, c, s, R, t in rows]


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


class FFB6DMethod(PoseMethod):
    """FFB6D's pieces (the functions of this module); the network takes the whole batch."""

    config_class = FFB6DConfig

    def build(self, cfg: FFB6DConfig, meta: MethodMeta) -> FFB6D:
        return build(cfg, meta)

    def transform(self, cfg: FFB6DConfig, meta: MethodMeta, train: bool = False) -> FFB6DTransform:
        return FFB6DTransform(cfg, meta, train=train)

    def loss(self, net: FFB6D, batch: Mapping, cfg: FFB6DConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
        return loss(net, batch, cfg, meta)

    def predict_poses(self, net: FFB6D, batch: Mapping, cfg: FFB6DConfig, meta: MethodMeta) -> list:
        return predict_poses(net, batch, cfg, meta)

    def forward(self, net: FFB6D, batch: Mapping) -> dict:
        return forward_batch(net, batch)

    def example_batch(self, cfg: FFB6DConfig, meta: MethodMeta, batch_size: int = 1) -> dict:
        return example_batch(cfg, meta, batch_size)


__all__ = ["FFB6D", "FFB6DConfig", "FFB6DMethod", "FFB6DTransform", "build", "example_batch", "focal_loss",
           "fusion_indices", "loss", "offset_l1", "predict_poses"]
