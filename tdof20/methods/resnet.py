"""ResNet18 / ResNet34 encoders with torchvision's exact parameter names (torchvision itself is not used).

The module tree mirrors ``torchvision.models.resnet18`` / ``resnet34``: ``conv1, bn1, layer1..layer4``
(each a Sequential of BasicBlocks with ``conv1, bn1, conv2, bn2`` and ``downsample.0`` /
``downsample.1`` where the shape changes) and, optionally, ``fc``. A torchvision checkpoint therefore
loads with :func:`load_torchvision_state_dict`, from a path the user gives (nothing is downloaded).

``forward`` returns the five stage feature maps (HFF6DoF, PVNet, PSPNet use them)::

    stage   name    stride  channels
    0       stem    2       64      relu(bn1(conv1(x)))   (before the max-pool)
    1       layer1  4       64
    2       layer2  8       128
    3       layer3  16      256
    4       layer4  32      512

``replace_stride_with_dilation=(False, True, True)`` (torchvision's option) keeps layer3 and layer4 at
stride 8 and dilates their 3x3 convolutions instead (dilation 2 and 4; the first block of a dilated
layer keeps the previous dilation, as torchvision does): output stride 8, as PVNet and PSPNet use.
(torchvision's BasicBlock refuses dilation; ours applies it the way torchvision's Bottleneck does.)
Dilation changes no parameter, so the same checkpoint loads. ``dilate=False`` drops the replaced
strides without dilating (FFB6D's published extractor behaves so: its layer3/layer4 run at stride 8
with dilation 1, because its ``_make_layer`` ignores the dilation it is given).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from tdof20.errors import TdofError

STAGE_NAMES = ("stem", "layer1", "layer2", "layer3", "layer4")
STAGE_CHANNELS = (64, 64, 128, 256, 512)
STAGE_STRIDES = (2, 4, 8, 16, 32)
RESNET18_LAYERS = (2, 2, 2, 2)
RESNET34_LAYERS = (3, 4, 6, 3)
#: output stride 8: layer3 and layer4 dilated instead of strided (PVNet, PSPNet)
OUTPUT_STRIDE_8 = (False, True, True)


def conv3x3(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=3, stride=stride, padding=dilation, dilation=dilation, bias=False)


def conv1x1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    """torchvision's BasicBlock (expansion 1)."""

    expansion = 1

    def __init__(self, cin: int, cout: int, stride: int = 1, downsample: nn.Module | None = None,
                 dilation: int = 1, first_dilation: int | None = None):
        super().__init__()
        self.conv1 = conv3x3(cin, cout, stride, dilation if first_dilation is None else first_dilation)
        self.bn1 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = conv3x3(cout, cout, dilation=dilation)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet(nn.Module):
    """A BasicBlock ResNet encoder; ``forward(x (B,C,H,W)) -> [stem, layer1, layer2, layer3, layer4]``.

    layers: blocks per stage ((2,2,2,2) ResNet18, (3,4,6,3) ResNet34).
    in_channels: 3 for RGB, 6 for the HFF6DoF geometry map (XYZ + normals).
    with_fc: keep torchvision's ``fc`` (512 -> num_classes) and offer :meth:`classify`; the
        encoder use never needs it.
    replace_stride_with_dilation: for layer2, layer3, layer4 (torchvision's option);
        :data:`OUTPUT_STRIDE_8` gives output stride 8. ``dilate=False``: drop those strides but keep
        dilation 1 (FFB6D's extractor as published).
    """

    arch = "resnet"

    def __init__(self, layers=RESNET34_LAYERS, in_channels: int = 3, with_fc: bool = False,
                 num_classes: int = 1000, replace_stride_with_dilation=(False, False, False), dilate: bool = True):
        super().__init__()
        if in_channels < 1:
            raise ValueError(f"in_channels must be >= 1, got {in_channels}")
        layers = tuple(int(n) for n in layers)
        rswd = tuple(bool(r) for r in replace_stride_with_dilation)
        if len(layers) != 4 or min(layers) < 1:
            raise ValueError(f"layers must be 4 block counts >= 1, got {layers}")
        if len(rswd) != 3:
            raise ValueError(f"replace_stride_with_dilation needs 3 flags (layer2..layer4), got {rswd}")
        self.in_channels = in_channels
        self.layers_config = layers
        self.replace_stride_with_dilation = rswd
        self.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        cin, dilation = 64, 1
        self.stage_strides = [2, 4]
        for i, (n_blocks, cout) in enumerate(zip(layers, STAGE_CHANNELS[1:]), start=1):
            stride, prev = (1 if i == 1 else 2), dilation
            if i > 1 and rswd[i - 2]:
                if dilate:
                    dilation *= stride
                stride = 1
            if i > 1:
                self.stage_strides.append(self.stage_strides[-1] * stride)
            downsample = None
            if stride != 1 or cin != cout:
                downsample = nn.Sequential(conv1x1(cin, cout, stride), nn.BatchNorm2d(cout))
            blocks = [BasicBlock(cin, cout, stride, downsample, dilation=dilation, first_dilation=prev)]
            blocks += [BasicBlock(cout, cout, dilation=dilation) for _ in range(n_blocks - 1)]
            setattr(self, f"layer{i}", nn.Sequential(*blocks))
            cin = cout
        self.stage_strides = tuple(self.stage_strides)
        self.fc = nn.Linear(512, num_classes) if with_fc else None
        self.avgpool = nn.AdaptiveAvgPool2d(1) if with_fc else None
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    @property
    def output_stride(self) -> int:
        return self.stage_strides[-1]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        stem = self.relu(self.bn1(self.conv1(x)))
        f1 = self.layer1(self.maxpool(stem))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [stem, f1, f2, f3, f4]

    def classify(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits (B, num_classes); only with ``with_fc=True``."""
        if self.fc is None:
            raise RuntimeError(f"this {type(self).__name__} was built without fc (with_fc=False)")
        return self.fc(torch.flatten(self.avgpool(self.forward(x)[-1]), 1))


class ResNet18(ResNet):
    """torchvision's resnet18 layout (11,689,512 parameters with fc)."""

    arch = "resnet18"

    def __init__(self, in_channels: int = 3, with_fc: bool = False, num_classes: int = 1000,
                 replace_stride_with_dilation=(False, False, False), dilate: bool = True):
        super().__init__(RESNET18_LAYERS, in_channels, with_fc, num_classes, replace_stride_with_dilation, dilate)


class ResNet34(ResNet):
    """torchvision's resnet34 layout (21,797,672 parameters with fc)."""

    arch = "resnet34"

    def __init__(self, in_channels: int = 3, with_fc: bool = False, num_classes: int = 1000,
                 replace_stride_with_dilation=(False, False, False), dilate: bool = True):
        super().__init__(RESNET34_LAYERS, in_channels, with_fc, num_classes, replace_stride_with_dilation, dilate)


def resnet(name: str, **kwargs) -> ResNet:
    """``resnet("resnet18" | "resnet34", **kwargs)``."""
    table = {"resnet18": ResNet18, "resnet34": ResNet34}
    if name not in table:
        raise ValueError(f"unknown backbone '{name}' (valid: {', '.join(table)})")
    return table[name](**kwargs)


def _unwrap_state_dict(obj: object, origin: str) -> dict[str, torch.Tensor]:
    """Accept a bare state dict or one wrapped as {'state_dict': ...} / {'model': ...};
    strip a DataParallel ``module.`` prefix."""
    if isinstance(obj, nn.Module):
        obj = obj.state_dict()
    for key in ("state_dict", "model"):
        if isinstance(obj, Mapping) and key in obj and isinstance(obj[key], Mapping):
            obj = obj[key]
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise TdofError("is not a torch state dict of tensors (expected a torchvision resnet checkpoint)",
                        origin)
    out = {}
    for k, v in obj.items():
        out[k[len("module."):] if k.startswith("module.") else k] = v
    return out


def load_torchvision_state_dict(model: ResNet, path_or_dict: str | Path | Mapping) -> list[str]:
    """Load a torchvision ``resnet18`` / ``resnet34`` checkpoint (a path or a state dict) into ``model``
    (its own layout: a resnet18 file into a ResNet18).

    Strict on the backbone: every ``conv1 / bn1 / layer*`` parameter and BatchNorm running
    statistic must be present with the right shape; ``fc.*`` is ignored either way, and
    ``num_batches_tracked`` may be absent (torchvision's own resnet34 file predates it).

    In-channel adaptation of ``conv1``: a 3-channel checkpoint loads into a model with
    ``in_channels = 3m`` (e.g. the 6-channel geometry encoder) by repeating the RGB filters m times
    scaled by 1/m (0.5 for 6 channels), so that an input whose m channel groups are equal gives
    the same response as the RGB network. Any other channel mismatch is an error.

    Returns the list of checkpoint keys that were ignored. Raises :class:`TdofError` naming the
    file (or ``<state dict>``) on an unreadable file, missing keys or mismatched shapes.
    """
    origin = "<state dict>"
    if isinstance(path_or_dict, (str, Path)):
        origin = str(path_or_dict)
        p = Path(path_or_dict)
        if not p.is_file():
            raise TdofError(f"no such checkpoint file (give a torchvision {getattr(model, 'arch', 'resnet')} .pth)", p)
        try:
            obj = torch.load(p, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unpickling failure is a user file problem
            raise TdofError(f"cannot be read as a torch checkpoint ({type(exc).__name__}: {exc})", p) from None
    else:
        obj = path_or_dict
    sd = _unwrap_state_dict(obj, origin)

    own = model.state_dict()
    wanted = {k: v for k, v in own.items() if not k.startswith("fc.")}
    missing = [k for k in wanted if k not in sd and not k.endswith("num_batches_tracked")]
    if missing:
        more = f" (+{len(missing) - 5} more)" if len(missing) > 5 else ""
        raise TdofError(f"checkpoint lacks {type(model).__name__} keys {', '.join(missing[:5])}{more}", origin)
    new: dict[str, torch.Tensor] = {}
    for k, target in wanted.items():
        if k not in sd:
            continue
        v = sd[k]
        if k == "conv1.weight" and v.dim() == 4 and v.shape[1] != target.shape[1]:
            cin, cw = target.shape[1], v.shape[1]
            if v.shape[0] == target.shape[0] and v.shape[2:] == target.shape[2:] and cin % cw == 0:
                m = cin // cw
                v = v.repeat(1, m, 1, 1) / m
        if v.shape != target.shape:
            raise TdofError(f"key {k} has shape {tuple(v.shape)}, the model expects {tuple(target.shape)}",
                            origin)
        new[k] = v.to(dtype=target.dtype)
    model.load_state_dict(new, strict=False)
    return sorted(k for k in sd if k not in new)
