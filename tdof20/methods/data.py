"""HFF6DoF data: model keypoints, the input depth modes, and the transform from a dataset item to
network inputs and training targets.

    kps = model_keypoints(ROOT / "models")                  # {obj_id: (9,3) mm}
    tf = HFFTransform(kps, image_size=(240, 320), depth_mode="filled")
    sample = tf(ShardDataset(shard)[n])                     # dict of tensors, see HFFTransform

Depth modes — which depth the network sees (the geometry map) and which 3D points vote at test time:

======== ================================================================ =========================
mode     input depth                                                      protocols
======== ================================================================ =========================
raw      the sensor's depth as recorded, holes left at 0 (pixels without   every protocol
         depth do not vote)
filled   the sensor's depth with holes filled from valid neighbours        every protocol
         (:func:`~tdof20.methods.hff6dof.fill_depth_holes`); pixels still
         without depth do not vote
restored the restored depth (depth of the objects' models composited       none for a submission:
         into the scene: derived from the ground-truth poses)             an upper bound only
======== ================================================================ =========================

The paper's protocol feeds the network the real, noisy transparent depth at test time, so
``restored`` is privileged information — use it only to measure how much the depth costs
(docs/hff6dof.md).

Vector origins — where a pixel's training vector starts (``vector_origin``):

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
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tdof20.dataset.splits import HARD_TEST_MULTI, _hard_train_multi
from tdof20.errors import TdofError
from tdof20.methods.hff6dof import fill_depth_holes, geometry_map
from tdof20.objects.keypoints import KEYPOINT_SAMPLES, KEYPOINT_SEED, N_KEYPOINTS, surface_keypoints

DEPTH_MODES = ("raw", "filled", "restored")
VECTOR_ORIGINS = ("restored", "observed")
#: the input depth used unless told otherwise (the result of the comparison in docs/hff6dof.md)
DEFAULT_DEPTH_MODE = "filled"
N_CLASSES = 21          # a run without a class list: background + objects 1..20, class = obj_id


def identity_classes(n_classes: int = N_CLASSES) -> list[int]:
    """The class list of a run recorded without one (ids 1..n_classes-1, class c = object c)."""
    return list(range(1, int(n_classes)))


def dataset_classes(obj_ids: Sequence[int], layout: str = "bop") -> list[int]:
    """The object id of each class 1..n (class 0 = background) a run trains on a dataset with
    these objects: a tdof20 dataset within the catalog's ids 1..20 keeps the catalog's 20 classes
    (class = obj_id, comparable runs); any other dataset its own objects in ascending order."""
    ids = sorted({int(o) for o in obj_ids})
    if layout == "tdof20" and ids and min(ids) >= 1 and max(ids) <= N_CLASSES - 1:
        return identity_classes()
    return ids


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


def check_depth_mode(mode: str) -> str:
    if mode not in DEPTH_MODES:
        raise TdofError(f"unknown depth mode '{mode}' (valid: {', '.join(DEPTH_MODES)})")
    return mode


#: what each part of a split takes (tdof20.dataset.splits), for the message when it is empty
SPLIT_PART_SCENES = {
    ("simple", "train"): "the single-object scenes' frames outside the test arcs",
    ("simple", "test"): "one arc of turntable steps per arm position of the single-object scenes",
    ("hard", "train"): f"the single-object scenes and multi-object scenes {_hard_train_multi()}",
    ("hard", "test"): "multi-object scenes " + ", ".join(f"{m:02d}" for m in HARD_TEST_MULTI),
}


def split_part_images(dataset_root: str | Path, split: str, part: str, purpose: str) -> list[tuple[int, int]]:
    """(scene_id, im_id) of ``split``/``part`` of the dataset (either layout); a one-line TdofError
    naming the split, the part and the dataset root when the part is empty (``purpose``: 'train
    on', 'predict')."""
    from tdof20.dataset.build import split_images
    from tdof20.dataset.reader import open_dataset

    ds = open_dataset(dataset_root)
    if ds.layout == "bop":
        images = ds.frames(split, part)
        if not images:
            raise TdofError(f"the split folder {ds.check_split(split)}/ of this dataset has no "
                            f"{'images' if part == 'train' else 'test images'}: nothing to {purpose}", dataset_root)
        return images
    images = split_images(dataset_root, split, part)
    if not images:
        takes = SPLIT_PART_SCENES.get((split, part), "")
        raise TdofError(f"the {split} split's {part} part of this dataset is empty (splits/{split}_{part}.json "
                        f"lists no images{'; it takes ' + takes if takes else ''}): nothing to {purpose}",
                        dataset_root)
    return images


def dataset_meta(ds, classes: Sequence[int], image_size: Sequence[int], n_model_points: int = 500,
                 seed: int = 0):
    """The :class:`~tdof20.methods.base.MethodMeta` a method trains with on dataset ``ds`` (an
    opened :class:`tdof20.dataset.reader.Dataset`): the objects ``classes`` in class order, their
    keypoints (the dataset's), diameters and symmetries (models_info.json: symmetric when it
    lists discrete or continuous symmetries), ``n_model_points`` area-uniform surface samples of
    each model (deterministic in ``seed``) and the network input size."""
    from tdof20.formats.bop import model_path, read_model_mesh
    from tdof20.geometry.sampling import sample_mesh_surface
    from tdof20.methods.base import MethodMeta

    ids = [int(o) for o in classes]
    info = ds.models_info
    own = [o for o in ids if o in info]
    missing = [o for o in ids if o not in info]
    if missing and ds.layout != "tdof20":
        raise TdofError(f"models_info.json lacks objects {missing}", ds.models_dir)
    # a tdof20 dataset keeps the catalog's 20 classes: the objects it does not hold come from the catalog
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
    from tdof20.formats import read_models_info
    from tdof20.formats.bop import model_path, read_model_mesh

    models_dir = Path(models_dir)
    ids = sorted(read_models_info(models_dir)) if obj_ids is None else [int(o) for o in obj_ids]
    out = {}
    for obj_id in ids:
        V, F = read_model_mesh(model_path(models_dir, obj_id))  # keypoints are sampled on the surface
        out[obj_id] = surface_keypoints(V, F, k, n_samples, seed)
    return out


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


def input_depth(raw_mm: torch.Tensor, restored_mm: torch.Tensor | None, mode: str) -> torch.Tensor:
    """The depth (H,W) mm the network sees and the voting uses, per depth mode."""
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
# the transform


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


class HFFTransform:
    """A dataset item (a :class:`~tdof20.dataset.shards.ShardDataset` item or a
    :class:`SceneImages` item) -> network inputs and targets at ``image_size`` (H, W).

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
    in the layout of :class:`~tdof20.dataset.shards.ShardDataset` (what :class:`HFFTransform`
    takes): rgb, depth, K, depth_restored (``restored``: stored, else rendered once and cached;
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
        from tdof20.dataset.reader import open_dataset

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
