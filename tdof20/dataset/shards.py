"""HDF5 shards: what training reads, packed from a dataset split, and a torch Dataset over them.

One file per (split, part), written by ``tdof20 dataset pack``. Per image ``n`` (all chunked one
image per chunk, LZF-compressed — fast to decode):

    rgb             (N,H,W,3) uint8    colour of the transparent phase
    depth           (N,H,W)   uint16   raw sensor depth (depth_scale mm per unit, 0 = none)
    depth_restored  (N,H,W)   uint16   restored depth (0 where the scene has none)
    label           (N,H,W)   uint16   semantic label: obj_id of the visible object, 0 = background
    instance        (N,H,W)   uint8    index of the visible instance + 1 (into the pose arrays), 0 = none
    obj_id          (N,M)     int16    object of each instance, 0 = padding (M = most instances in an image)
    R               (N,M,3,3) float32  cam_R_m2c
    t               (N,M,3)   float32  cam_t_m2c, mm
    visib_fract     (N,M)     float32
    K               (N,3,3)   float32
    depth_scale     (N,)      float32
    scene_id, im_id (N,)      int32

File attributes: split, part, dataset root, models_info (JSON text).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from tdof20.dataset.layouts.base import DatasetReader
from tdof20.errors import TdofError
from tdof20.formats.bop import METRES_BELOW_MM, median_distance_if_metres, read_models_info, read_scene
from tdof20.formats.io import check_output_file, read_png

#: the per-image arrays and their types (what pack_shard writes and ShardDataset accepts)
SHARD_DTYPES = {"rgb": np.uint8, "depth": np.uint16, "depth_restored": np.uint16, "label": np.uint16,
                "instance": np.uint8}
IMAGE_KEYS = tuple(SHARD_DTYPES)


def pack_shard(images: list[tuple[int, int]], source, out: str | Path, attrs: dict | None = None,
               models_dir: str | Path | None = None, progress_bar=None, split: str | None = None) -> Path:
    """Write the images (scene_id, im_id) of a dataset into one HDF5 file, atomically. ``source``:
    a :class:`~tdof20.dataset.layouts.base.DatasetReader` (its ``split`` folder; restored depth stored or
    rendered, see :meth:`~tdof20.dataset.layouts.base.DatasetReader.render_restored`) or a folder of BOP
    scenes ``{scene_id:06d}/`` (restored depth where depth_restored/ has it, else 0)."""
    reader = source if isinstance(source, DatasetReader) else None
    scenes_root = reader.root if reader is not None else Path(source)
    out = check_output_file(out, "the shard", "HDF5 file")
    if not images:
        a = attrs or {}
        what = f"the {a['split']} split's {a['part']} part" if "split" in a and "part" in a else "the list of images"
        raise TdofError(f"nothing to pack: {what} has no images", a.get("dataset", scenes_root))
    scenes = {}
    for sid in sorted({s for s, _ in images}):
        scenes[sid] = reader.scene(sid, split) if reader is not None else read_scene(scenes_root / f"{sid:06d}")

    def restored(sid: int, im: int) -> np.ndarray | None:
        if reader is not None:
            p = reader.restored_path(sid, im, split)
            return read_png(p, kind="depth") if p is not None else None
        p = scenes[sid].path / "depth_restored" / f"{im:06d}.png"
        return read_png(p, kind="depth") if p.exists() else None

    m = max(1, max(len(scenes[s].gt.get(i, [])) for s, i in images))
    first = scenes[images[0][0]]
    rgb0 = first.rgb(images[0][1])
    h, w = rgb0.shape[:2]
    n = len(images)
    tmp = out.with_name(f".{out.name}.tmp")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with h5py.File(tmp, "w") as f:
            def img(name, shape):
                return f.create_dataset(name, (n, *shape), dtype=SHARD_DTYPES[name], chunks=(1, *shape),
                                        compression="lzf")

            d_rgb = img("rgb", (h, w, 3))
            d_depth = img("depth", (h, w))
            d_rest = img("depth_restored", (h, w))
            d_label = img("label", (h, w))
            d_inst = img("instance", (h, w))
            obj = np.zeros((n, m), np.int16)
            R = np.zeros((n, m, 3, 3), np.float32)
            t = np.zeros((n, m, 3), np.float32)
            vis = np.zeros((n, m), np.float32)
            K = np.zeros((n, 3, 3), np.float32)
            ds = np.zeros(n, np.float32)
            for j, (sid, im) in enumerate(images):
                sc = scenes[sid]
                rgb = sc.rgb(im)
                if rgb.shape[:2] != (h, w):
                    raise TdofError(f"image {im} is {rgb.shape[1]}x{rgb.shape[0]}, the shard is {w}x{h}", sc.path / "rgb")
                d_rgb[j] = rgb
                d_depth[j] = sc.depth(im)
                rest = restored(sid, im)
                if rest is not None:
                    d_rest[j] = rest
                lab = np.zeros((h, w), SHARD_DTYPES["label"])
                ins = np.zeros((h, w), SHARD_DTYPES["instance"])
                for g, entry in enumerate(sc.gt.get(im, [])):
                    mv = sc.mask(im, g, visib=True)
                    lab[mv] = entry["obj_id"]
                    ins[mv] = g + 1
                    obj[j, g] = entry["obj_id"]
                    Rg, tg = sc.pose(im, g)
                    R[j, g], t[j, g] = Rg, tg
                    vis[j, g] = sc.gt_info[im][g].get("visib_fract", 1.0) if im in sc.gt_info else 1.0
                d_label[j] = lab
                d_inst[j] = ins
                K[j] = sc.K(im)
                ds[j] = sc.depth_scale(im)
                if progress_bar is not None:
                    progress_bar()
            for name, arr in (("obj_id", obj), ("R", R), ("t", t), ("visib_fract", vis), ("K", K), ("depth_scale", ds),
                              ("scene_id", np.array([s for s, _ in images], np.int32)),
                              ("im_id", np.array([i for _, i in images], np.int32))):
                f.create_dataset(name, data=arr)
            for k, v in (attrs or {}).items():
                f.attrs[k] = v
            if models_dir is not None:
                f.attrs["models_info"] = json.dumps({str(k): v for k, v in read_models_info(models_dir).items()})
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


class ShardDataset:
    """A torch Dataset over one HDF5 shard: item n is a dict of tensors (images channel-first for
    colour: ``rgb`` (3,H,W) uint8; depths float32 mm; ``label``/``instance`` int64; poses and K).
    The file opens lazily in each worker process (h5py handles must not cross a fork)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            with h5py.File(self.path, "r") as f:
                self._n = len(f["rgb"])
                self.attrs = dict(f.attrs)
                missing = [k for k in IMAGE_KEYS + ("obj_id", "R", "t", "K", "depth_scale") if k not in f]
                if not missing:
                    dtypes = {k: f[k].dtype for k in IMAGE_KEYS}
                    obj, R, t = f["obj_id"][:], f["R"][:], f["t"][:]
        except (OSError, KeyError) as e:
            raise TdofError(f"not a readable tdof20 shard ({e})", self.path) from None
        if missing:
            raise TdofError(f"not a tdof20 shard: missing {', '.join(missing)}", self.path)
        bad = [f"{k} is {dt}, {np.dtype(SHARD_DTYPES[k]).name} expected" for k, dt in dtypes.items()
               if dt != SHARD_DTYPES[k]]
        if bad:
            raise TdofError(f"not a tdof20 shard: {'; '.join(bad)}", self.path)
        used = obj > 0
        if not (np.isfinite(R[used]).all() and np.isfinite(t[used]).all()):
            raise TdofError("holds a pose that is not finite (NaN or inf in R or t)", self.path)
        med = median_distance_if_metres(t[used])
        if med is not None:
            raise TdofError(f"translations look like metres (median |t| {med:.4g}, under {METRES_BELOW_MM:g} mm): t "
                            "must be in millimetres", self.path)
        self._f = None

    def __len__(self) -> int:
        return self._n

    def _file(self) -> h5py.File:
        if self._f is None:
            self._f = h5py.File(self.path, "r")
        return self._f

    def __getitem__(self, n: int) -> dict:
        import torch

        if not 0 <= n < self._n:
            raise IndexError(n)
        f = self._file()
        s = float(f["depth_scale"][n])
        return {
            "rgb": torch.from_numpy(np.ascontiguousarray(f["rgb"][n].transpose(2, 0, 1))),
            "depth": torch.from_numpy(f["depth"][n].astype(np.float32) * s),
            "depth_restored": torch.from_numpy(f["depth_restored"][n].astype(np.float32) * s),
            "label": torch.from_numpy(f["label"][n].astype(np.int64)),
            "instance": torch.from_numpy(f["instance"][n].astype(np.int64)),
            "obj_id": torch.from_numpy(f["obj_id"][n].astype(np.int64)),
            "R": torch.from_numpy(f["R"][n]), "t": torch.from_numpy(f["t"][n]),
            "K": torch.from_numpy(f["K"][n]),
            "scene_id": int(f["scene_id"][n]), "im_id": int(f["im_id"][n]),
        }

    def __getstate__(self) -> dict:
        d = dict(self.__dict__)
        d["_f"] = None
        return d
