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
from tdof20.methods.data import (DEFAULT_DEPTH_MODE, N_CLASSES, backproject, check_depth_mode, resize_frame,
                                 resize_nearest)
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

    def __call__(self, item: Mapping) -> dict:
        hw = self.image_size
        K, depth, rgb, restored = resize_frame(item, hw, self.depth_mode)
        out = {
            "rgb": rgb,
            "geo": geometry_map(depth[None], K[None])[0],
            "depth": depth,
            "K": K,
            "scene_id": int(item["scene_id"]), "im_id": int(item["im_id"]),
        }
        if "label" in item:
            label = item["label"] if self.lut is None else to_classes(item["label"], self.lut)
            out["label"] = resize_nearest(label, hw)
        if self.targets:
            observed = self.vector_origin == "observed"
            if "label" not in item or (restored is None and not observed):
                raise TdofError("training targets need labels and the restored depth")
            obj = item["obj_id"] if self.lut is None else to_classes(item["obj_id"], self.lut)
            out.update(self.vector_targets(out["label"], resize_nearest(item["instance"], hw),
                                           depth if observed else restored, K, obj, item["R"], item["t"]))
        return out

    def vector_targets(self, label: torch.Tensor, instance: torch.Tensor, restored: torch.Tensor, K: torch.Tensor,
                       obj_id: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> dict:
        """Targets from the origin depth ``restored`` (the restored depth, or the input depth with
        ``vector_origin = "observed"``): pixels of visible instances where that depth is > 0."""
        H, W = label.shape
        nk = self.kp_table.shape[1]
        obj = obj_id.long().clamp(0, self.kp_table.shape[0] - 1)
        kp_cam = torch.einsum("mij,mkj->mki", R.to(torch.float32), self.kp_table[obj]) + t.to(torch.float32)[:, None]
        mask = (instance > 0) & (label > 0) & (restored > 0)
        inst = (instance.long() - 1).clamp_min(0)
        P = backproject(restored, K)                                   # (H,W,3)
        d = kp_cam[inst] - P[:, :, None]                               # (H,W,K,3)
        vec = F.normalize(d, dim=-1, eps=1e-6)
        ok = mask & torch.isfinite(vec).all(-1).all(-1)
        vec = torch.where(ok[..., None, None], vec, torch.zeros_like(vec))
        return {"seg": label.long(), "vec": vec.reshape(H, W, nk * 3).permute(2, 0, 1).contiguous(), "mask": ok}
