"""HFF6DoF's data: the transform from a dataset item to its network inputs (colour, the geometry
map of the input depth) and training targets (segmentation, unit vectors to the keypoints), and the
keypoint table by class.

    tf = HFFTransform(keypoints, image_size=(240, 320), depth_mode="filled", classes=meta.obj_ids)
    sample = tf(ShardDataset(shard)[n])                     # dict of tensors, see HFFTransform

The input depth modes are every method's (:mod:`tdof20.methods.data`). Vector origins — where a
pixel's training vector starts (``vector_origin``):

- ``restored`` (default): at the pixel's true 3D point (the restored depth back-projected),
  whatever the input mode; every visible object pixel with restored depth has a target;
- ``observed``: at the 3D point the network actually sees, the *input* depth back-projected
  (per ``depth_mode``; on glass often a point behind the surface, seen through it). Pixels without
  valid input depth get no target (no vector loss) and cast no 3D vote. The lines of the targets
  then meet at the keypoints from the very points 3D voting back-projects, so 3D voting + least
  squares (the paper's section 3.5) recovers the pose from exact vectors on any depth; both
  origins lie on the pixel's viewing ray, so bearing voting works with either.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from tdof20.errors import TdofError
from tdof20.methods.data import (DEFAULT_DEPTH_MODE, N_CLASSES, check_depth_mode, fill_depth_holes, resize_colour,
                                 resize_nearest, scale_intrinsics)
from tdof20.methods.hff6dof import geometry_map

VECTOR_ORIGINS = ("restored", "observed")


def class_lookup(classes: Sequence[int]) -> torch.Tensor:
    """(max id + 1,) int64: obj_id -> class index (1..n), 0 for objects not in ``classes``."""
    classes = [int(c) for c in classes]
    lut = torch.zeros(max(classes, default=0) + 1, dtype=torch.int64)
    lut[torch.tensor(classes, dtype=torch.int64)] = torch.arange(1, len(classes) + 1)
    return lut


def to_classes(ids: torch.Tensor, lut: torch.Tensor) -> torch.Tensor:
    """Object ids (any shape, 0 = background/padding) -> class indices through ``lut``."""
    ids = ids.long()
    inside = (ids >= 0) & (ids < len(lut))
    return torch.where(inside, lut[ids.clamp(0, len(lut) - 1)], torch.zeros_like(ids))


def check_vector_origin(origin: str) -> str:
    if origin not in VECTOR_ORIGINS:
        raise TdofError(f"unknown vector origin '{origin}' (valid: {', '.join(VECTOR_ORIGINS)})")
    return origin


def keypoint_table(keypoints: Mapping[int, np.ndarray], n_classes: int = N_CLASSES,
                   classes: Sequence[int] | None = None) -> torch.Tensor:
    """(n_classes, K, 3) float32 indexed by class: row c holds the keypoints of object
    ``classes[c - 1]`` (default: class = obj_id); rows of objects without keypoints are NaN."""
    K = len(next(iter(keypoints.values())))
    if classes is not None:
        classes = [int(c) for c in classes]
        table = torch.full((len(classes) + 1, K, 3), float("nan"))
        for c, obj_id in enumerate(classes, start=1):
            if obj_id in keypoints:
                table[c] = torch.from_numpy(np.array(keypoints[obj_id], dtype=np.float32))
        return table
    table = torch.full((n_classes, K, 3), float("nan"))
    for obj_id, kp in keypoints.items():
        if not 0 < int(obj_id) < n_classes:
            raise TdofError(f"object id {obj_id} outside 1..{n_classes - 1}")
        table[int(obj_id)] = torch.as_tensor(np.asarray(kp), dtype=torch.float32)
    return table


class HFFTransform:
    """A dataset item (a :class:`~tdof20.dataset.shards.ShardDataset` item or a
    :class:`~tdof20.methods.data.SceneImages` item) -> network inputs and targets at ``image_size`` (H, W).

    Output dict:

    - ``rgb`` (3,H,W) float in [0,1]; ``geo`` (6,H,W) :func:`geometry_map` of the input depth;
    - ``depth`` (H,W) the input depth in mm (per ``depth_mode``; 0 = none); ``K`` (3,3) scaled;
    - with ``targets`` (and labels in the item): ``seg`` (H,W) int64 obj_id per pixel (0 =
      background); ``vec`` (3K,H,W) unit vectors from each object pixel's true 3D point (restored
      depth) to its object's K keypoints in the ground-truth pose (0 elsewhere); ``mask`` (H,W) bool,
      the pixels where ``vec`` is defined (visible object pixels with restored depth; with
      ``vector_origin = "observed"`` the vectors start at the input depth's points instead, and
      only pixels with input depth have them);
    - ``scene_id``, ``im_id``; ``label`` (H,W) the resized ground-truth label whenever the item has one.

    ``classes``: the object id of each class 1..n (a dataset with any ids): labels and instance
    objects are mapped to class indices (objects outside the list become background), and a
    keypoint dict is tabled by class. None: class = obj_id (ids 1..20).
    """

    def __init__(self, keypoints: Mapping[int, np.ndarray] | torch.Tensor, image_size: Sequence[int],
                 depth_mode: str = DEFAULT_DEPTH_MODE, targets: bool = True, classes: Sequence[int] | None = None,
                 vector_origin: str = "restored"):
        self.lut = class_lookup(classes) if classes is not None else None
        self.kp_table = keypoints if isinstance(keypoints, torch.Tensor) else \
            keypoint_table(keypoints, classes=classes)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.depth_mode = check_depth_mode(depth_mode)
        self.targets = bool(targets)
        self.vector_origin = check_vector_origin(vector_origin)
        self.deferred = False

    def defer_to_device(self):
        """Hand the dense per-pixel part of this transform — hole filling, the geometry map, the
        vector targets: nearly all its time at 480x640 — to the returned stage, ``stage(batch) ->
        batch``, which the trainer runs on each collated batch on its device (a GPU is then not
        starved by CPU workers). The items become the resized frames (``depth_raw``,
        ``depth_origin``, ``instance``, ``obj``, ``R``, ``t`` besides rgb, K, label); the stage
        turns a batch of them into exactly the batch of the undeferred transform (the same
        operations, per sample, batched)."""
        self.deferred = True
        return self.device_stage

    def __call__(self, item: Mapping) -> dict:
        hw = self.image_size
        K = scale_intrinsics(item["K"], tuple(item["rgb"].shape[1:]), hw)
        raw = resize_nearest(item["depth"], hw)
        rest = item.get("depth_restored")
        restored = resize_nearest(rest, hw) if rest is not None else None
        out = {"rgb": resize_colour(item["rgb"], hw), "depth_raw": raw, "K": K,
               "scene_id": int(item["scene_id"]), "im_id": int(item["im_id"])}
        if self.depth_mode == "restored":
            if restored is None:
                raise TdofError("depth mode 'restored' needs the restored depth (depth_restored/)")
            out["depth_raw"] = restored  # the input depth as it is (input_depth)
        if "label" in item:
            label = item["label"] if self.lut is None else to_classes(item["label"], self.lut)
            out["label"] = resize_nearest(label, hw)
        if self.targets:
            observed = self.vector_origin == "observed"
            if "label" not in item or (restored is None and not observed):
                raise TdofError("training targets need labels and the restored depth")
            if not observed:
                out["depth_origin"] = restored
            out.update(instance=resize_nearest(item["instance"], hw),
                       obj=item["obj_id"] if self.lut is None else to_classes(item["obj_id"], self.lut),
                       R=torch.as_tensor(item["R"]), t=torch.as_tensor(item["t"]))
        if self.deferred:
            return out
        batch = {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in out.items()}
        return {k: v[0] if isinstance(v, torch.Tensor) else v for k, v in self.device_stage(batch).items()}

    def device_stage(self, batch: Mapping) -> dict:
        """The dense part of the transform on a batch of resized frames (see :meth:`defer_to_device`),
        on the batch's device: the input depth (holes filled in mode 'filled'), its geometry map and,
        with targets, the vector targets."""
        out = dict(batch)
        raw = out.pop("depth_raw")
        depth = fill_depth_holes(raw) if self.depth_mode == "filled" else raw
        out["depth"] = depth
        out["geo"] = geometry_map(depth, out["K"])
        if self.targets:
            origin = out.pop("depth_origin", None)
            out.update(self.vector_targets_batch(out["label"], out.pop("instance"), depth if origin is None else origin,
                                                 out["K"], out.pop("obj"), out.pop("R"), out.pop("t")))
        return out

    def vector_targets(self, label: torch.Tensor, instance: torch.Tensor, restored: torch.Tensor, K: torch.Tensor,
                       obj_id: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> dict:
        """Targets of one frame from the origin depth ``restored`` (the restored depth, or the input
        depth with ``vector_origin = "observed"``): pixels of visible instances where that depth is > 0."""
        out = self.vector_targets_batch(label[None], instance[None], restored[None], K[None], obj_id[None], R[None],
                                        t[None])
        return {k: v[0] for k, v in out.items()}

    def vector_targets_batch(self, label: torch.Tensor, instance: torch.Tensor, origin: torch.Tensor, K: torch.Tensor,
                             obj_id: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> dict:
        """:meth:`vector_targets` of a batch: label, instance, origin (B,H,W), K (B,3,3), obj_id (B,M)
        class indices, R (B,M,3,3), t (B,M,3) mm, on any device.

        Computed on the object pixels only (they cover a small part of a frame; the (H,W,K,3) field
        of the whole frame was most of the transform's time), with the very operations of
        :func:`~tdof20.methods.data.backproject` per pixel: the targets are those of the whole-frame
        computation, bit for bit."""
        B, H, W = label.shape
        dev = label.device
        table = self.kp_table.to(dev)
        nk = table.shape[1]
        obj = obj_id.long().clamp(0, table.shape[0] - 1)
        kp_cam = torch.einsum("bmij,bmkj->bmki", R.to(torch.float32), table[obj]) + t.to(torch.float32)[:, :, None]
        mask = (instance > 0) & (label > 0) & (origin > 0)
        bs, vs, us = mask.nonzero(as_tuple=True)
        z = origin[bs, vs, us].to(torch.float32)
        Kb = K.to(torch.float32)[bs]
        P = torch.stack([(us.to(torch.float32) - Kb[:, 0, 2]) * z / Kb[:, 0, 0],
                         (vs.to(torch.float32) - Kb[:, 1, 2]) * z / Kb[:, 1, 1], z], dim=-1)   # (n,3)
        inst = (instance[bs, vs, us].long() - 1).clamp_min(0)
        vec = F.normalize(kp_cam[bs, inst] - P[:, None], dim=-1, eps=1e-6)                # (n,K,3)
        ok = torch.isfinite(vec).all(-1).all(-1)
        field = torch.zeros(B, H, W, nk * 3, dtype=vec.dtype, device=dev)
        field[bs, vs, us] = torch.where(ok[:, None], vec.reshape(-1, nk * 3), torch.zeros((), dtype=vec.dtype,
                                                                                             device=dev))
        good = torch.zeros(B, H, W, dtype=torch.bool, device=dev)
        good[bs, vs, us] = ok
        return {"seg": label.long(), "vec": field.permute(0, 3, 1, 2).contiguous(), "mask": good}
