"""HFF6DoF behind the method contract (:class:`~tdof20.methods.contract.PoseMethod`):
:class:`HFF6DoFMethod`, with its config, network, transform, loss and pose recovery.

    m = get_method("hff6dof")
    cfg = HFF6DoFConfig(fuse_stages=3, seg_head=True, depth_mode="filled", voting="bearing")
    net = build(cfg, meta)                                   # HFF6DoF (tdof20.methods.hff6dof)
    tf = HFF6DoFTransform(cfg, meta, train=True)             # wraps hff6dof_data.HFFTransform
    total, parts = loss(net, collate([tf(i) for i in items]), cfg, meta)   # losses.hff_loss
    rows = predict_poses(net, batch, cfg, meta)              # hff6dof_pose.recover_poses

The pieces wrap hff6dof_data.HFFTransform, losses.hff_loss and hff6dof_pose.recover_poses. A run
records the network's options as its "network" table (:meth:`HFF6DoFMethod.run_record`); a run
written before the interface (config.json {"method": "hff6dof", "network": {...}, "keypoints": ...,
"image_size": ..., "depth_mode": ...}, with or without "classes") gives its (cfg, meta) through
:func:`config_from_run`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tdof20.config import config_from_data
from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod
from tdof20.methods.data import DEFAULT_DEPTH_MODE, check_depth_mode, identity_classes, keypoints_from_json
from tdof20.methods.hff6dof import DEFAULT_DECODER_CHANNELS, DEFAULT_HEAD_CHANNELS, HFF6DoF
from tdof20.methods.hff6dof_data import HFFTransform, check_vector_origin
from tdof20.methods.hff6dof_pose import default_min_pixels, recover_poses
from tdof20.methods.losses import hff_loss

MASKS = ("auto", "network", "segnet", "gt")
VOTINGS = ("bearing", "3d")


@dataclass
class HFF6DoFConfig:
    """HFF6DoF's options (plain types, TOML-settable); every default works.

    Network: fuse_stages (1..5: the last N encoder stages fused; the paper's 3), seg_head (the
    segmentation head; off = the paper's ablation, prediction then takes its masks from a separately
    trained segmentation network, masks 'segnet'),
    decoder_channels (6 widths at strides 1..32) and head_channels (sized to the paper's 56.82 M),
    backbone_weights (a torchvision resnet34 .pth for both encoders; "" = random init).
    Input: depth_mode 'raw' | 'filled' (the transparent sensor's depth; 'restored' is privileged,
    an upper bound only). Targets: vector_origin 'restored' (vectors start at the true surface
    point, the restored depth; default) | 'observed' (at the input depth's back-projected point the
    network sees; pixels without input depth get no vector loss and cast no 3D vote: the paper's
    3D voting + least squares made to work on glass depth, docs/hff6dof.md). Loss: w_vec (weight of the vector field's L1; the paper's 2).
    Prediction: masks ('auto' = the network's segmentation when it has the head, else 'gt';
    'network'; 'segnet' = the masks of the segmentation network trained in the run folder
    ``seg_run`` (``tdof20 train segnet``, on the same data and image size: the paper's ablation
    without the head); 'gt' = the dataset's visible masks, an oracle: never a compared row),
    seg_run (that run folder; read only with masks 'segnet'), voting ('bearing' | '3d'),
    min_pixels (smallest segment; 0 = 0.05 % of the image, at least 10), max_points (voting pixels
    per object), n_hyp, inlier_cos, bearing_tol (RANSAC), seed (the voting's generator).
    """

    fuse_stages: int = 3
    seg_head: bool = True
    decoder_channels: tuple[int, ...] = DEFAULT_DECODER_CHANNELS
    head_channels: int = DEFAULT_HEAD_CHANNELS
    backbone_weights: str = ""
    depth_mode: str = DEFAULT_DEPTH_MODE
    vector_origin: str = "restored"
    w_vec: float = 2.0
    masks: str = "auto"
    seg_run: str = ""
    voting: str = "bearing"
    min_pixels: int = 0
    max_points: int = 2000
    n_hyp: int = 128
    inlier_cos: float = 0.99
    bearing_tol: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        self.decoder_channels = tuple(int(c) for c in self.decoder_channels)
        if not 1 <= int(self.fuse_stages) <= 5:
            raise TdofError(f"hff6dof fuse_stages must be in 1..5, got {self.fuse_stages}")
        if len(self.decoder_channels) != 6 or min(self.decoder_channels) < 1:
            raise TdofError(f"hff6dof decoder_channels needs 6 widths >= 1, got {list(self.decoder_channels)}")
        check_depth_mode(self.depth_mode)
        check_vector_origin(self.vector_origin)
        if self.masks not in MASKS:
            raise TdofError(f"hff6dof masks must be one of {', '.join(MASKS)}, got '{self.masks}'")
        if self.masks == "segnet" and not str(self.seg_run).strip():
            raise TdofError("hff6dof masks = 'segnet' needs seg_run = the folder of a segmentation run "
                            "(tdof20 train segnet ...)")
        if str(self.seg_run).strip() and self.masks != "segnet":
            raise TdofError(f"hff6dof seg_run is read only with masks = 'segnet' (masks is '{self.masks}')")
        if self.voting not in VOTINGS:
            raise TdofError(f"hff6dof voting must be one of {', '.join(VOTINGS)}, got '{self.voting}'")
        if not 0.0 < float(self.inlier_cos) < 1.0:
            raise TdofError(f"hff6dof inlier_cos must lie in (0, 1), got {self.inlier_cos}")
        for name in ("head_channels", "max_points", "n_hyp"):
            if int(getattr(self, name)) < 1:
                raise TdofError(f"hff6dof {name} must be >= 1, got {getattr(self, name)}")
        if int(self.min_pixels) < 0 or float(self.w_vec) < 0 or float(self.bearing_tol) <= 0:
            raise TdofError("hff6dof min_pixels and w_vec must be >= 0 and bearing_tol > 0")


def build(cfg: HFF6DoFConfig, meta: MethodMeta) -> HFF6DoF:
    """The HFF6DoF of ``meta``'s objects (classes = objects + background, ``meta.n_keypoints``)."""
    net = HFF6DoF(n_classes=meta.n_classes, n_keypoints=meta.n_keypoints, fuse_stages=cfg.fuse_stages,
                  seg_head=cfg.seg_head, decoder_channels=cfg.decoder_channels, head_channels=cfg.head_channels)
    if cfg.backbone_weights:
        net.load_backbone_weights(Path(cfg.backbone_weights))
    return net


class HFF6DoFTransform:
    """A dataset item -> HFF6DoF inputs (+ targets with ``train``) at ``meta.image_size``:
    :class:`~tdof20.methods.hff6dof_data.HFFTransform` with the meta's classes (labels become class
    indices 0..n) and keypoints. Output: rgb, geo, depth (the input depth), K, scene_id, im_id,
    label (when the item has labels); with ``train``: seg, vec, mask. Picklable."""

    def __init__(self, cfg: HFF6DoFConfig, meta: MethodMeta, train: bool = False):
        classes = list(meta.obj_ids)
        self.inner = HFFTransform({o: meta.keypoints[o] for o in classes}, meta.image_size, cfg.depth_mode,
                                  targets=bool(train), classes=classes, vector_origin=cfg.vector_origin)

    def __call__(self, item: Mapping) -> dict:
        return self.inner(item)

    def defer_to_device(self):
        """The dense part (hole filling, geometry map, vector targets) batched on the training device
        (:meth:`~tdof20.methods.hff6dof_data.HFFTransform.defer_to_device`); train.py uses it on a GPU."""
        return self.inner.defer_to_device()


def forward(net: HFF6DoF, batch: Mapping) -> dict:
    """The network alone: ``net(rgb, geo)`` on the network's device (channels-last on CUDA)."""
    dev = next(net.parameters()).device
    rgb, geo = batch["rgb"].to(dev, non_blocking=True), batch["geo"].to(dev, non_blocking=True)
    if dev.type == "cuda":
        rgb = rgb.contiguous(memory_format=torch.channels_last)
        geo = geo.contiguous(memory_format=torch.channels_last)
    return net(rgb, geo)


def loss(net: HFF6DoF, batch: Mapping, cfg: HFF6DoFConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
    """The paper's loss (section 3.6): cross-entropy of the segmentation + w_vec x L1 of the
    vector field on the object pixels (losses.hff_loss). Parts: loss, seg, vec."""
    dev = next(net.parameters()).device
    out = forward(net, batch)
    seg = out["seg"].float() if out["seg"] is not None else None
    total, parts = hff_loss(seg, out["vec"].float(), batch["seg"].to(dev), batch["vec"].to(dev),
                            batch["mask"].to(dev), w_vec=float(cfg.w_vec), return_parts=True)
    return total, {"loss": float(total.detach()), "seg": float(parts["seg"]), "vec": float(parts["vec"])}


def mask_source(cfg: HFF6DoFConfig, net: HFF6DoF) -> str:
    """'network', 'segnet' or 'gt': where the object pixels come from (cfg.masks, 'auto' resolved:
    the network's head when it has one, else the ground truth, an oracle)."""
    if cfg.masks == "auto":
        return "network" if net.has_seg_head else "gt"
    if cfg.masks == "network" and not net.has_seg_head:
        raise TdofError("the network has no segmentation head: predict with masks = 'segnet' and seg_run = a "
                        "segmentation run (tdof20 train segnet), or masks = 'gt' (ground-truth masks, an oracle)")
    return cfg.masks


@torch.no_grad()
def predict_poses(net: HFF6DoF, batch: Mapping, cfg: HFF6DoFConfig, meta: MethodMeta
                  ) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
    """Rows (b, obj_id, score, R (3,3), t (3,) mm) of a batch: the network, the object pixels (its
    segmentation's argmax; with masks 'segnet' or 'gt' the batch's ``label``, class indices: the
    segmentation run's classes, which the shared prediction loop puts there, or the ground truth), then
    :func:`tdof20.methods.hff6dof_pose.recover_poses` (voting + fitting; score = mean inlier fraction)."""
    source = mask_source(cfg, net)
    if source != "network" and "label" not in batch:
        raise TdofError("predicting with ground-truth masks needs the labels in the batch" if source == "gt" else
                        "predicting with a segmentation run's masks needs them in the batch's 'label' (the shared "
                        "prediction loop, tdof20.methods.predict, puts them there)")
    was = net.training
    net.eval()
    try:
        out = forward(net, batch)
    finally:
        net.train(was)
    dev = out["vec"].device
    if source == "network":
        conf, classes = torch.softmax(out["seg"].float(), dim=1).max(dim=1)
    else:
        classes, conf = batch["label"].to(dev).long(), None
    kp_table = torch.as_tensor(meta.keypoint_array(), dtype=torch.float32, device=dev)
    min_pixels = int(cfg.min_pixels) or default_min_pixels(meta.image_size)
    gen = torch.Generator(device=dev).manual_seed(int(cfg.seed))
    res = recover_poses(classes, out["vec"].float(), batch["depth"].to(dev), batch["K"].to(dev), kp_table,
                        min_pixels, max_points=int(cfg.max_points), n_hyp=int(cfg.n_hyp),
                        inlier_cos=float(cfg.inlier_cos), generator=gen, confidence=conf, voting=cfg.voting,
                        bearing_tol=float(cfg.bearing_tol))
    return [(b, meta.obj_of(r["obj_id"]), float(r["score"]), np.asarray(r["R"], np.float64),
             np.asarray(r["t"], np.float64)) for b, found in enumerate(res) for r in found]


# --------------------------------------------------------------------------------------------
# runs


def config_from_run(config: Mapping, path: str | Path | None = None) -> tuple[HFF6DoFConfig, MethodMeta]:
    """(cfg, meta) of an HFF6DoF run from its config.json, also one written before the interface:
    the network options from "network", the input depth from "depth_mode", the objects from
    "classes" (a run without them: ids 1..n_classes-1, class = obj_id), their keypoints from
    "keypoints", the input size from "image_size"; a recorded "method_config" / "meta" wins, except
    that the "network" table, when there is one, decides the architecture.
    Such an old run records no diameters, symmetries or surface samples (prediction needs none):
    the meta then carries the keypoints' extent as diameter, no symmetry and the keypoints as
    samples."""
    try:
        if "method_config" in config:
            cfg = config_from_data(HFF6DoFConfig, dict(config["method_config"]), path or "")
        else:
            cfg = HFF6DoFConfig(depth_mode=str(config["depth_mode"]))
        if "network" in config:  # the network table describes the architecture (every HFF6DoF run has one)
            net = config["network"]
            cfg = dataclasses.replace(cfg, fuse_stages=int(net["fuse_stages"]), seg_head=bool(net["seg_head"]),
                                      decoder_channels=tuple(int(c) for c in net["decoder_channels"]),
                                      head_channels=int(net["head_channels"]))
            if int(net.get("geo_channels", 6)) != 6:
                raise TdofError(f"its network has {net['geo_channels']} geometry channels; HFF6DoF's input has 6",
                                path)
        if "meta" in config:
            meta = MethodMeta.from_json(config["meta"])
        else:
            classes = config.get("classes")
            classes = identity_classes(int(config["network"]["n_classes"])) if classes is None else \
                [int(c) for c in classes]
            kps = keypoints_from_json(config["keypoints"])
            missing = [o for o in classes if o not in kps]
            if missing:
                raise TdofError(f"its keypoints lack objects {missing}", path)
            kps = {o: kps[o] for o in classes}
            meta = MethodMeta(obj_ids=tuple(classes), keypoints=kps,
                              diameters={o: float(2 * np.linalg.norm(k - k[0], axis=1).max()) for o, k in kps.items()},
                              symmetric={o: False for o in classes}, model_points=kps,
                              image_size=tuple(int(v) for v in config["image_size"]))
    except (KeyError, TypeError, ValueError) as e:
        raise TdofError(f"not a readable HFF6DoF run config ({type(e).__name__}: {e})", path) from None
    except TdofError as e:
        if e.path is None and path is not None:
            raise TdofError(str(e), path) from None
        raise
    n = config.get("network", {}).get("n_classes") if isinstance(config.get("network"), Mapping) else None
    if n is not None and int(n) != meta.n_classes:
        raise TdofError(f"its network has {n} classes but its objects make {meta.n_classes}", path)
    return cfg, meta


#: the keys of a run's "network" table (every HFF6DoF run records one)
NETWORK_KEYS = ("n_classes", "n_keypoints", "fuse_stages", "seg_head", "decoder_channels", "head_channels",
                "geo_channels")


def network_table(net: HFF6DoF) -> dict:
    """The network's "network" table (what a run records of its architecture)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in net.config.items()}


class HFF6DoFMethod(PoseMethod):
    """HFF6DoF's pieces (the functions of this module). Every parameter takes part in each loss, so
    DistributedDataParallel need not look for unused ones; its transform gives class indices."""

    config_class = HFF6DoFConfig
    ddp_find_unused_parameters = False
    labels_are_classes = True

    def build(self, cfg: HFF6DoFConfig, meta: MethodMeta) -> HFF6DoF:
        return build(cfg, meta)

    def transform(self, cfg: HFF6DoFConfig, meta: MethodMeta, train: bool = False) -> HFF6DoFTransform:
        return HFF6DoFTransform(cfg, meta, train=train)

    def loss(self, net: HFF6DoF, batch: Mapping, cfg: HFF6DoFConfig, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
        return loss(net, batch, cfg, meta)

    def predict_poses(self, net: HFF6DoF, batch: Mapping, cfg: HFF6DoFConfig, meta: MethodMeta) -> list:
        return predict_poses(net, batch, cfg, meta)

    def forward(self, net: HFF6DoF, batch: Mapping) -> dict:
        return forward(net, batch)

    def config_from_run(self, config: Mapping, path=None) -> tuple[HFF6DoFConfig, MethodMeta]:
        return config_from_run(config, path)

    def missing_run_keys(self, config: Mapping) -> list[str]:
        """A run without "method_config" (written before the interface) needs its whole "network" table."""
        if "method_config" in config:
            return []
        if not isinstance(config.get("network"), dict):
            return ["network (not a table)" if "network" in config else "method_config"]
        return [f"network.{k}" for k in NETWORK_KEYS if k not in config["network"]]

    def run_record(self, net: HFF6DoF) -> dict:
        return {"network": network_table(net)}

    def mask_source(self, cfg: HFF6DoFConfig, net: HFF6DoF) -> str:
        return mask_source(cfg, net)

    def prediction_summary(self, cfg: HFF6DoFConfig, meta: MethodMeta) -> dict:
        """The summary's options, ``min_pixels`` as used (0 = the image-size rule resolved)."""
        return {**super().prediction_summary(cfg, meta),
                "min_pixels": int(cfg.min_pixels) or default_min_pixels(meta.image_size)}


__all__: Sequence[str] = ("HFF6DoFConfig", "HFF6DoFMethod", "HFF6DoFTransform", "NETWORK_KEYS", "build",
                          "config_from_run", "forward", "loss", "mask_source", "network_table",
                          "predict_poses")
