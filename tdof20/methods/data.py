"""The data every method shares: the input depth modes, the dataset's objects as a method's meta,
model keypoints, resizing a frame to the network's size, the datasets (a packed shard's items passed
through a method's transform, images read straight from a dataset root) and batching.

    meta = dataset_meta(ds, dataset_classes(ds.obj_ids, ds.uses_catalog_ids), (240, 320))
    K, depth, rgb, restored = resize_frame(item, (240, 320), "filled")   # what each transform starts from
    data = TransformedDataset(ShardDataset(shard), method.transform(cfg, meta, train=True))
    batch = collate([data[0], data[1]])

Depth modes — which depth a method sees (``depth_mode`` of an RGB-D method's config):

======== ================================================================ =========================
mode     input depth                                                      protocols
======== ================================================================ =========================
raw      the sensor's depth as recorded, holes left at 0                  every protocol
filled   the sensor's depth with holes filled from valid neighbours        every protocol
         (:func:`fill_depth_holes`)
restored the restored depth (depth of the objects' models composited       none for a submission:
         into the scene: derived from the ground-truth poses)             an upper bound only
======== ================================================================ =========================

The paper's protocol feeds the network the real, noisy transparent depth at test time, so
``restored`` is privileged information — use it only to measure how much the depth costs
(docs/hff6dof.md).

No network is imported here: a method's own data pieces live in its modules (HFF6DoF's transform
and vector targets: :mod:`tdof20.methods.hff6dof_data`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tdof20.dataset.reader import open_dataset
from tdof20.errors import TdofError
from tdof20.formats import read_models_info
from tdof20.formats.bop import model_path, read_model_mesh
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.methods.base import MethodMeta
from tdof20.objects.keypoints import KEYPOINT_SAMPLES, KEYPOINT_SEED, N_KEYPOINTS, surface_keypoints

DEPTH_MODES = ("raw", "filled", "restored")
#: the input depth used unless told otherwise (the result of the comparison in docs/hff6dof.md)
DEFAULT_DEPTH_MODE = "filled"
N_CLASSES = 21          # a run without a class list: background + objects 1..20, class = obj_id


def identity_classes(n_classes: int = N_CLASSES) -> list[int]:
    """The class list of a run recorded without one (ids 1..n_classes-1, class c = object c)."""
    return list(range(1, int(n_classes)))


def dataset_classes(obj_ids: Sequence[int], uses_catalog_ids: bool = False) -> list[int]:
    """The object id of each class 1..n (class 0 = background) a run trains on a dataset with
    these objects: a dataset whose ids are the catalog's (``uses_catalog_ids``: the tdof20 layout)
    within ids 1..20 keeps the catalog's 20 classes (class = obj_id, comparable runs); any other
    dataset its own objects in ascending order."""
    ids = sorted({int(o) for o in obj_ids})
    if uses_catalog_ids and ids and min(ids) >= 1 and max(ids) <= N_CLASSES - 1:
        return identity_classes()
    return ids


def check_depth_mode(mode: str) -> str:
    if mode not in DEPTH_MODES:
        raise TdofError(f"unknown depth mode '{mode}' (valid: {', '.join(DEPTH_MODES)})")
    return mode


def dataset_meta(ds, classes: Sequence[int], image_size: Sequence[int], n_model_points: int = 500,
                 seed: int = 0):
    """The :class:`~tdof20.methods.base.MethodMeta` a method trains with on dataset ``ds`` (an
    opened :class:`tdof20.dataset.reader.Dataset`): the objects ``classes`` in class order, their
    keypoints (the dataset's), diameters and symmetries (models_info.json: symmetric when it
    lists discrete or continuous symmetries), ``n_model_points`` area-uniform surface samples of
    each model (deterministic in ``seed``) and the network input size."""
    ids = [int(o) for o in classes]
    info = ds.models_info
    own = [o for o in ids if o in info]
    missing = [o for o in ids if o not in info]
    if missing and not ds.uses_catalog_ids:
        raise TdofError(f"models_info.json lacks objects {missing}", ds.models_dir)
    # a dataset of the catalog's ids keeps its 20 classes: the objects it does not hold come from the catalog
    cat = MethodMeta.from_catalog(missing, image_size, n_model_points, seed) if missing else None
    kps = ds.keypoints(own) if own else {}
    pts = {}
    for o in own:
        V, F = read_model_mesh(model_path(ds.models_dir, o))
        pts[o] = sample_mesh_surface(V, F, int(n_model_points), seed)

    def pick(table: dict, o: int, cat_table):
        return table[o] if o in table else cat_table[o]

    return MethodMeta(obj_ids=tuple(ids), keypoints={o: pick(kps, o, cat and cat.keypoints) for o in ids},
                      diameters={o: float(info[o]["diameter"]) if o in info else cat.diameters[o] for o in ids},
                      symmetric={o: bool(info[o].get("symmetries_discrete") or info[o].get("symmetries_continuous"))
                                 if o in info else cat.symmetric[o] for o in ids},
                      model_points={o: pick(pts, o, cat and cat.model_points) for o in ids},
                      image_size=tuple(int(v) for v in image_size))


# --------------------------------------------------------------------------------------------
# keypoints


def model_keypoints(models_dir: str | Path, obj_ids: Sequence[int] | None = None, k: int = N_KEYPOINTS,
                    n_samples: int = KEYPOINT_SAMPLES, seed: int = KEYPOINT_SEED) -> dict[int, np.ndarray]:
    # (a dataset's keypoints, keypoints.json first: tdof20.dataset.reader.Dataset.keypoints)
    """Keypoints {obj_id: (k,3) mm} of the dataset's models (``ROOT/models/obj_{id:06d}.ply``,
    read with trimesh); every object of models_info.json unless ``obj_ids`` is given."""
    models_dir = Path(models_dir)
    ids = sorted(read_models_info(models_dir)) if obj_ids is None else [int(o) for o in obj_ids]
    out = {}
    for obj_id in ids:
        V, F = read_model_mesh(model_path(models_dir, obj_id))  # keypoints are sampled on the surface
        out[obj_id] = surface_keypoints(V, F, k, n_samples, seed)
    return out


def keypoints_to_json(keypoints: Mapping[int, np.ndarray]) -> dict[str, list]:
    return {str(k): np.asarray(v, dtype=float).round(6).tolist() for k, v in sorted(keypoints.items())}


def keypoints_from_json(d: Mapping[str, list]) -> dict[int, np.ndarray]:
    return {int(k): np.asarray(v, dtype=np.float64) for k, v in d.items()}


# --------------------------------------------------------------------------------------------
# resizing and geometry


def scale_intrinsics(K: torch.Tensor, src_hw: Sequence[int], dst_hw: Sequence[int]) -> torch.Tensor:
    """K (..,3,3) of an image resized from src_hw to dst_hw (pixel centres at integer coordinates,
    the BOP convention: u' = (u + 0.5) * s - 0.5)."""
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    K = K.clone().to(torch.float32)
    K[..., 0, 0] *= sx
    K[..., 0, 1] *= sx
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 1] *= sy
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def resize_colour(rgb: torch.Tensor, hw: Sequence[int]) -> torch.Tensor:
    """(3,H,W) uint8 -> (3,h,w) float in [0,1]: area averaging when shrinking, bilinear otherwise."""
    x = rgb.to(torch.float32)[None] / 255.0
    if tuple(x.shape[2:]) != tuple(hw):
        shrink = hw[0] <= x.shape[2] and hw[1] <= x.shape[3]
        x = F.interpolate(x, size=tuple(hw), mode="area") if shrink else \
            F.interpolate(x, size=tuple(hw), mode="bilinear", align_corners=False)
    return x[0].clamp_(0.0, 1.0)


def resize_nearest(img: torch.Tensor, hw: Sequence[int]) -> torch.Tensor:
    """(H,W) any dtype -> (h,w), nearest neighbour at pixel centres (no mixing of depths or labels)."""
    if tuple(img.shape) == tuple(hw):
        return img
    x = img[None, None].to(torch.float32)
    return F.interpolate(x, size=tuple(hw), mode="nearest-exact")[0, 0].to(img.dtype)


def backproject(depth_mm: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(H,W) depth in mm and K (3,3) -> (H,W,3) camera-frame points in mm (0 where depth is 0)."""
    H, W = depth_mm.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    z = depth_mm.to(torch.float32)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return torch.stack([x, y, z], dim=-1)


def fill_depth_holes(depth_mm: torch.Tensor, iterations: int = 8, kernel: int = 5) -> torch.Tensor:
    """Fill missing depth (0) by repeatedly averaging valid neighbours (``kernel`` x ``kernel``
    window, ``iterations`` passes): (B,H,W) -> (B,H,W). Valid pixels are kept as they are; holes
    wider than about iterations * kernel / 2 pixels stay 0. A cheap, differentiation-free option for
    the glass pixels whose depth the sensor lost."""
    squeeze = depth_mm.dim() == 2
    d = (depth_mm[None] if squeeze else depth_mm).to(torch.float32)[:, None]
    valid = (d > 0).to(d.dtype)
    for _ in range(iterations):
        s = F.avg_pool2d(d * valid, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
        c = F.avg_pool2d(valid, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
        fill = (valid == 0) & (c > 0)
        if not bool(fill.any()):  # nothing left to fill: the remaining passes would change nothing
            break
        d = torch.where(fill, s / c.clamp_min(1e-12), d)
        valid = torch.maximum(valid, fill.to(d.dtype))
    d = d[:, 0]
    return d[0] if squeeze else d


def input_depth(raw_mm: torch.Tensor, restored_mm: torch.Tensor | None, mode: str) -> torch.Tensor:
    """The depth (H,W) mm the network sees (and a method's pose recovery uses), per depth mode."""
    if mode == "raw":
        return raw_mm
    if mode == "filled":
        return fill_depth_holes(raw_mm)
    if mode == "restored":
        if restored_mm is None:
            raise TdofError("depth mode 'restored' needs the restored depth (depth_restored/)")
        return restored_mm
    raise TdofError(f"unknown depth mode '{mode}' (valid: {', '.join(DEPTH_MODES)})")


# --------------------------------------------------------------------------------------------
# the shared part of the transforms, the datasets


def resize_frame(item: Mapping, hw: Sequence[int], depth_mode: str) -> tuple:
    """A dataset item at the network's size ``hw`` (H, W), the part every method's transform shares:
    (K scaled (3,3), the input depth of ``depth_mode`` in mm (H,W), colour (3,H,W) in [0,1], the
    restored depth (H,W) or None when the item has none)."""
    hw = (int(hw[0]), int(hw[1]))
    K = scale_intrinsics(item["K"], tuple(item["rgb"].shape[1:]), hw)
    raw = resize_nearest(item["depth"], hw)
    rest = item.get("depth_restored")
    restored = resize_nearest(rest, hw) if rest is not None else None
    return K, input_depth(raw, restored, depth_mode), resize_colour(item["rgb"], hw), restored


class TransformedDataset(torch.utils.data.Dataset):
    """``base[n]`` passed through ``transform`` (picklable for DataLoader workers)."""

    def __init__(self, base, transform):
        self.base = base
        self.transform = transform

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, n: int) -> dict:
        return self.transform(self.base[n])


class SceneImages(torch.utils.data.Dataset):
    """Images (scene_id, im_id) read straight from a dataset root of either layout (through
    :func:`tdof20.dataset.reader.open_dataset`; ``split``: a BOP dataset's split folder), as items
    in the layout of :class:`~tdof20.dataset.shards.ShardDataset` (what the transforms
    take): rgb, depth, K, depth_restored (``restored``: stored, else rendered once and cached;
    None without ``restored``), and the labels (label, instance, obj_id, R, t) when ``labels``."""

    def __init__(self, root: str | Path, images: Sequence[tuple[int, int]], labels: bool = False,
                 restored: bool = True, split: str | None = None, cache_dir: str | Path | None = None):
        self.root = Path(root)
        self.images = [(int(s), int(i)) for s, i in images]
        self.labels = bool(labels)
        self.restored = bool(restored)
        self.split = split
        self.cache_dir = cache_dir
        self._ds = None

    def __len__(self) -> int:
        return len(self.images)

    def dataset(self):
        if self._ds is None:
            self._ds = open_dataset(self.root, self.split, cache_dir=self.cache_dir)
        return self._ds

    def __getitem__(self, n: int) -> dict:
        sid, im = self.images[n]
        ds = self.dataset()
        sc = ds.scene(sid)
        rgb = sc.rgb(im)
        depth = sc.depth_mm(im).astype(np.float32)
        restored = ds.depth_mm(sid, im, "restored") if self.restored else None
        item = {"rgb": torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))),
                "depth": torch.from_numpy(depth),
                "depth_restored": torch.from_numpy(restored) if restored is not None else None,
                "K": torch.from_numpy(np.asarray(sc.K(im), dtype=np.float32)), "scene_id": sid, "im_id": im}
        if self.labels:
            h, w = depth.shape
            lab = np.zeros((h, w), np.int64)
            ins = np.zeros((h, w), np.int64)
            gts = sc.gt.get(im, [])
            obj = np.zeros(max(1, len(gts)), np.int64)
            R = np.zeros((max(1, len(gts)), 3, 3), np.float32)
            t = np.zeros((max(1, len(gts)), 3), np.float32)
            for g, entry in enumerate(gts):
                mv = sc.mask(im, g, visib=True)
                lab[mv] = entry["obj_id"]
                ins[mv] = g + 1
                obj[g] = entry["obj_id"]
                R[g], t[g] = sc.pose(im, g)
            item.update(label=torch.from_numpy(lab), instance=torch.from_numpy(ins), obj_id=torch.from_numpy(obj),
                        R=torch.from_numpy(R), t=torch.from_numpy(t))
        return item

    def __getstate__(self) -> dict:
        d = dict(self.__dict__)
        d["_ds"] = None
        return d


def worker_init(_worker_id: int) -> None:
    """DataLoader worker start: one intra-op thread (the transform's tensors are small; several
    threads per worker only fight the training process for the cores)."""
    torch.set_num_threads(1)


def collate(batch: list[dict]) -> dict:
    """Stack the tensors of a list of transformed samples; ints become int64 tensors."""
    out = {}
    for k in batch[0]:
        v = batch[0][k]
        if isinstance(v, torch.Tensor):
            out[k] = torch.stack([b[k] for b in batch])
        else:
            out[k] = torch.tensor([b[k] for b in batch])
    return out
