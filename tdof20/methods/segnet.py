"""A segmentation network on its own ('segnet'): the object masks a pose method predicts with when it
has no segmentation of its own — HFF6DoF without its segmentation head, the paper's ablation.

    tdof20 train segnet --dataset ROOT --split hard --out runs/seg          # the shared training loop
    tdof20 predict runs/hff-noseg --dataset ROOT --split hard --out r.csv \\
        --set masks=segnet --set seg_run=runs/seg                             # its masks, not the truth's

The network is DenseFusion's segmentation network (:class:`SegNet`: PSPNet-ResNet18 of
:mod:`tdof20.methods.pspnet`, one logit per class; DenseFusion builds the very same module as its
``seg``), trained with pixel-wise cross-entropy against the visible masks (class 0 = background,
classes 1..n the run's objects, as every method's meta orders them).

It is registered with ``produces = 'masks'`` (:mod:`tdof20.methods.registry`): it is not a pose
method, no table compares it, and ``tdof20 predict`` on its run refuses in one line (its
:meth:`SegNetMethod.predict_poses` too); :meth:`SegNetMethod.predict_masks` is what the shared
prediction loop (:func:`tdof20.methods.predict.predict_rows`) runs on the pose run's images when
the pose method's mask source is 'segnet'. Its segmentation IoU is
:func:`tdof20.methods.predict.segmentation_iou` of its run, as for any segmenting method.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod
from tdof20.methods.data import resize_colour, resize_nearest
from tdof20.methods.pspnet import PSPNet

BACKBONES = ("resnet18", "resnet34")


@dataclass
class SegNetConfig:
    """The segmentation network's options (plain types, TOML-settable; the defaults are DenseFusion's).

    backbone: 'resnet18' (DenseFusion's) or 'resnet34'; backbone_weights: a torchvision checkpoint of
    that ResNet for the encoder ("" = random init)."""

    backbone: str = "resnet18"
    backbone_weights: str = ""

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise TdofError(f"segnet backbone must be one of {', '.join(BACKBONES)}, got '{self.backbone}'")


class SegNet(nn.Module):
    """The segmentation network: rgb (B,3,H,W) in [0,1] -> logits (B, n_classes, H, W); a PSPNet
    (:class:`~tdof20.methods.pspnet.PSPNet`) whose final 1x1 convolution gives one logit per class."""

    def __init__(self, n_classes: int, backbone_weights: str = "", backbone: str = "resnet18"):
        super().__init__()
        self.net = PSPNet(backbone=backbone, feat_dim=int(n_classes), log_softmax=False)
        if backbone_weights:
            self.net.load_backbone_weights(backbone_weights)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.net(rgb)


def build(cfg: SegNetConfig, meta: MethodMeta) -> SegNet:
    """The network for ``meta``'s objects (classes = objects + background)."""
    return SegNet(meta.n_classes, cfg.backbone_weights, cfg.backbone)


class SegNetTransform:
    """A dataset item -> ``rgb`` (3,H,W) in [0,1] at ``meta.image_size`` (area-resized, as every
    method's colour), ``scene_id``, ``im_id``; with labels also ``label`` and (the training target)
    ``seg``: class indices (H,W) int64 (nearest neighbour). Picklable."""

    def __init__(self, cfg: SegNetConfig, meta: MethodMeta, train: bool = False):
        self.hw = tuple(int(v) for v in meta.image_size)
        self.lut = torch.from_numpy(meta.class_lut(max_obj_id=1000))
        self.train = bool(train)

    def __call__(self, item: Mapping) -> dict:
        out = {"rgb": resize_colour(item["rgb"], self.hw), "scene_id": int(item.get("scene_id", 0)),
               "im_id": int(item.get("im_id", 0))}
        if "label" in item:
            lab = item["label"].long()
            cls = torch.where((lab >= 0) & (lab < len(self.lut)), self.lut[lab.clamp(0, len(self.lut) - 1)],
                              torch.zeros_like(lab))
            out["label"] = out["seg"] = resize_nearest(cls, self.hw)
        elif self.train:
            raise TdofError("segnet training targets need labels (the visible masks)")
        return out


def forward(net: SegNet, batch: Mapping) -> dict:
    """The network alone: {"seg": logits (B, n_classes, H, W)} on the network's device."""
    dev = next(net.parameters()).device
    return {"seg": net(batch["rgb"].to(dev))}


def loss(net: SegNet, batch: Mapping, cfg: SegNetConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
    """Pixel-wise cross-entropy against the visible masks. Parts: loss, seg."""
    if "seg" not in batch:
        raise TdofError("the segmentation loss needs labels (the transform's 'seg')")
    logits = forward(net, batch)["seg"].float()
    total = F.cross_entropy(logits, batch["seg"].to(logits.device))
    return total, {"loss": float(total.detach()), "seg": float(total.detach())}


@torch.no_grad()
def predict_masks(net: SegNet, batch: Mapping, cfg: SegNetConfig | None = None, meta: MethodMeta | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(classes (B,H,W) int64: the argmax class of each pixel, 0 = background; confidence (B,H,W):
    its softmax probability) of a batch, the network in eval mode."""
    was = net.training
    net.eval()
    try:
        logits = forward(net, batch)["seg"].float()
    finally:
        net.train(was)
    conf, classes = torch.softmax(logits, dim=1).max(dim=1)
    return classes, conf


class SegNetMethod(PoseMethod):
    """The segmentation network's pieces behind the method contract (the functions of this
    module); it produces masks (:meth:`predict_masks`), not poses. Its transform gives class indices."""

    config_class = SegNetConfig
    ddp_find_unused_parameters = False
    labels_are_classes = True

    def build(self, cfg: SegNetConfig, meta: MethodMeta) -> SegNet:
        return build(cfg, meta)

    def transform(self, cfg: SegNetConfig, meta: MethodMeta, train: bool = False) -> SegNetTransform:
        return SegNetTransform(cfg, meta, train=train)

    def loss(self, net: SegNet, batch: Mapping, cfg: SegNetConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
        return loss(net, batch, cfg, meta)

    def predict_poses(self, net: SegNet, batch: Mapping, cfg: SegNetConfig, meta: MethodMeta) -> list:
        raise TdofError("segnet produces masks, not poses: give its run to a pose method's prediction "
                        "(--set masks=segnet --set seg_run=RUN)")

    def forward(self, net: SegNet, batch: Mapping) -> dict:
        return forward(net, batch)

    def predict_masks(self, net: SegNet, batch: Mapping, cfg: SegNetConfig, meta: MethodMeta
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        return predict_masks(net, batch, cfg, meta)

    def prediction_summary(self, cfg: SegNetConfig, meta: MethodMeta) -> dict:
        return {}


__all__ = ["BACKBONES", "SegNet", "SegNetConfig", "SegNetMethod", "SegNetTransform", "build", "forward", "loss",
           "predict_masks"]
