"""PSPNet feature extractor of DenseFusion (PSPNet-ResNet18) and FFB6D (PSPNet-ResNet34).

After DenseFusion's ``lib/pspnet.py`` and FFB6D's ``models/cnn/pspnet.py`` (the same network; ours
is written anew on :mod:`tdof20.methods.resnet`)::

    rgb (B,3,H,W) in [0,1] -> ImageNet normalisation
    backbone  ResNet at output stride 8: conv1, bn1, relu, maxpool, layer1 (1/4, 64),
              layer2 (1/8, 128), layer3 (1/8, 256), layer4 (1/8, 512)
    psp       pyramid pooling: adaptive average pools (1, 2, 3, 6), a 1x1 conv 512 -> 512 (no bias)
              each, bilinear up-sampling back to 1/8, concatenation with the input (5 x 512),
              1x1 conv 2560 -> 1024, ReLU;  drop_1 = Dropout2d(0.3)
    up_1      x2 bilinear, 3x3 conv 1024 -> 256, BN, PReLU   (1/4);  drop_2 = Dropout2d(0.15)
    up_2      x2 bilinear, 3x3 conv 256 -> 64, BN, PReLU     (1/2);  drop_2
    up_3      x2 bilinear, 3x3 conv 64 -> 64, BN, PReLU      (1/1)
    final     1x1 conv 64 -> feat_dim, LogSoftmax over channels (both originals end so)
    -> (B, feat_dim, H, W)

The up-sampling blocks resample to the size of the matching encoder stage (then to H, W) rather
than by a fixed factor 2, so any H, W works; at 480x640 it is the same as the originals'.

Differences from the originals, all deliberate:

- backbone: ours has BatchNorm and torchvision's parameter names in both variants (a torchvision
  resnet18/34 checkpoint loads, :meth:`PSPNet.load_backbone_weights`). DenseFusion's extractor has
  no BatchNorm at all (and its up-sampling blocks none either: conv + PReLU); FFB6D's has both.
- dilation: layer3/layer4 are dilated (2, 4) torchvision-style; DenseFusion's are too (its first
  block of each keeps dilation 1 in both convs, ours in the first conv only). FFB6D's published
  extractor passes dilation to ``_make_layer`` but its blocks never receive it (stride 8,
  dilation 1): ``PSPNet(..., dilated=False)`` reproduces that.
- up-sampling blocks have BatchNorm in both variants (FFB6D's; DenseFusion's lack it).
- the unused ImageNet ``classifier`` of the originals (Linear 256 -> 256 -> n_classes, never
  called in a forward) is left out: it changes the parameter count by ~71 k only.
- ``final_seg`` (FFB6D's segmentation output of its PSPNet, unused by FFB6D itself, which segments
  with its own RGB-D head) is built only when ``n_seg_classes`` is given.

The stages stay attributes (``backbone.conv1 .. backbone.layer4``, ``psp``, ``drop_1``, ``up_1``,
``up_2``, ``up_3``, ``drop_2``, ``final``) so that FFB6D can run them one by one and fuse point
features between them; :meth:`PSPNet.encode` / :meth:`PSPNet.decode` are that split.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from tdof20.methods.resnet import OUTPUT_STRIDE_8, ResNet, load_torchvision_state_dict, resnet

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
PSP_SIZES = (1, 2, 3, 6)
#: DenseFusion's embedding width (FFB6D uses 64)
DEFAULT_FEAT_DIM = 32


class PSPModule(nn.Module):
    """Pyramid pooling: pools of ``sizes``, 1x1 conv each, up-sample, concat with the input, 1x1 conv, ReLU."""

    def __init__(self, features: int, out_features: int = 1024, sizes: Sequence[int] = PSP_SIZES):
        super().__init__()
        self.stages = nn.ModuleList([
            nn.Sequential(nn.AdaptiveAvgPool2d(output_size=(s, s)), nn.Conv2d(features, features, 1, bias=False))
            for s in sizes])
        self.bottleneck = nn.Conv2d(features * (len(sizes) + 1), out_features, kernel_size=1)
        self.relu = nn.ReLU()

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        h, w = feats.shape[2:]
        priors = [F.interpolate(stage(feats), size=(h, w), mode="bilinear", align_corners=False)
                  for stage in self.stages] + [feats]
        return self.relu(self.bottleneck(torch.cat(priors, 1)))


class PSPUpsample(nn.Module):
    """Bilinear up-sampling (align_corners=True, as the originals' nn.Upsample) to ``size``, 3x3 conv,
    BN, PReLU."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, padding=1), nn.BatchNorm2d(out_channels),
                                  nn.PReLU())

    def forward(self, x: torch.Tensor, size: Sequence[int] | None = None) -> torch.Tensor:
        size = tuple(size) if size is not None else (2 * x.shape[2], 2 * x.shape[3])
        return self.conv(F.interpolate(x, size=size, mode="bilinear", align_corners=True))


class PSPNet(nn.Module):
    """PSPNet embedding: ``forward(rgb (B,3,H,W) in [0,1]) -> (B, feat_dim, H, W)``.

    backbone: "resnet18" (DenseFusion) or "resnet34" (FFB6D). feat_dim: 32 (DenseFusion) or 64 (FFB6D).
    dilated: layer3/layer4 dilated (True) or plain stride 1 (FFB6D's published extractor).
    log_softmax: end with LogSoftmax over the channels, as both originals' ``final`` does.
    n_seg_classes: also build ``final_seg`` (1x1 conv 64 -> n, LogSoftmax), see :meth:`segment`.
    """

    def __init__(self, backbone: str = "resnet18", feat_dim: int = DEFAULT_FEAT_DIM, dilated: bool = True,
                 log_softmax: bool = True, n_seg_classes: int | None = None, psp_out: int = 1024):
        super().__init__()
        self.backbone_name = backbone
        self.feat_dim = int(feat_dim)
        self.backbone: ResNet = resnet(backbone, replace_stride_with_dilation=OUTPUT_STRIDE_8, dilate=dilated)
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.psp = PSPModule(512, psp_out, PSP_SIZES)
        self.drop_1 = nn.Dropout2d(p=0.3)
        self.up_1 = PSPUpsample(psp_out, 256)
        self.up_2 = PSPUpsample(256, 64)
        self.up_3 = PSPUpsample(64, 64)
        self.drop_2 = nn.Dropout2d(p=0.15)
        final: list[nn.Module] = [nn.Conv2d(64, self.feat_dim, kernel_size=1)]
        if log_softmax:
            final.append(nn.LogSoftmax(dim=1))
        self.final = nn.Sequential(*final)
        self.final_seg = None
        if n_seg_classes is not None:
            self.final_seg = nn.Sequential(nn.Conv2d(64, int(n_seg_classes), kernel_size=1), nn.LogSoftmax(dim=1))

    def load_backbone_weights(self, path_or_dict: str | Path | dict) -> list[str]:
        """Initialise the backbone from a torchvision resnet18/resnet34 checkpoint (a path or a state dict)."""
        return load_torchvision_state_dict(self.backbone, path_or_dict)

    def normalise(self, rgb: torch.Tensor) -> torch.Tensor:
        return (rgb - self.rgb_mean) / self.rgb_std

    def encode(self, rgb: torch.Tensor) -> list[torch.Tensor]:
        """[stem (1/2, 64), layer1 (1/4, 64), layer2 (1/8, 128), layer3 (1/8, 256), layer4 (1/8, 512),
        psp (1/8, 1024, after drop_1)]."""
        feats = self.backbone(self.normalise(rgb))
        return feats + [self.drop_1(self.psp(feats[-1]))]

    def decode_features(self, p: torch.Tensor, sizes: Sequence[Sequence[int]]) -> torch.Tensor:
        """psp features -> the 64-channel map before ``final``; ``sizes`` = the three target sizes
        (1/4, 1/2, 1/1 of the input)."""
        p = self.drop_2(self.up_1(p, sizes[0]))
        p = self.drop_2(self.up_2(p, sizes[1]))
        return self.up_3(p, sizes[2])

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        if rgb.dim() != 4 or rgb.shape[1] != 3:
            raise ValueError(f"PSPNet wants rgb (B,3,H,W), got {tuple(rgb.shape)}")
        feats = self.encode(rgb)
        sizes = (feats[1].shape[2:], feats[0].shape[2:], rgb.shape[2:])
        return self.final(self.decode_features(feats[-1], sizes))

    def segment(self, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(embedding (B,feat_dim,H,W), log-probabilities (B,n_seg_classes,H,W)); needs ``n_seg_classes``."""
        if self.final_seg is None:
            raise RuntimeError("this PSPNet was built without n_seg_classes")
        feats = self.encode(rgb)
        x = self.decode_features(feats[-1], (feats[1].shape[2:], feats[0].shape[2:], rgb.shape[2:]))
        return self.final(x), self.final_seg(x)
