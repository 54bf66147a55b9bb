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

File attributes: split, part, dataset root, models_info (JSON text); a shard a training packs also
``dataset_sha256`` (tdof20.methods.train_data.dataset_digest: what it was made from).
Opening one (:class:`ShardDataset`) checks its per-instance arrays are plausible
(:func:`check_plausible`); a damaged chunk read later is one line naming the shard and the array.
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


#: a translation beyond this (mm) is not a pose on a table (100 m)
T_MAX_MM = 1e5


def _array(f: h5py.File, name: str, path: Path) -> np.ndarray:
    try:
        return f[name][:]
    except (OSError, ValueError) as e:
        raise TdofError(f"its array {name} cannot be read (damaged: {(str(e).splitlines() or [''])[0][:60]})",
                        path) from None


def check_plausible(path: Path, obj: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                    depth_scale: np.ndarray, models_info: str | None = None) -> None:
    """One-line TdofError naming the shard, the array and the first bad index when the per-instance
    arrays are not poses (R not a rotation, |t| beyond :data:`T_MAX_MM`), an obj_id is negative or not
    in the shard's models_info, or K / depth_scale is not a camera (NaN, fx/fy <= 0, last row not
    0 0 1, scale <= 0). Vectorised over the small per-instance arrays (the images are not read)."""
    def first(bad: np.ndarray) -> str:
        return ", ".join(str(int(v)) for v in np.argwhere(bad)[0])

    used = obj > 0
    if (obj < 0).any():
        raise TdofError(f"its array obj_id holds a negative id at [{first(obj < 0)}]", path)
    if models_info:
        try:
            known = {int(k) for k in json.loads(models_info)}
        except (ValueError, TypeError):
            known = None
        if known:
            unknown = used & ~np.isin(obj, sorted(known))
            if unknown.any():
                i = tuple(np.argwhere(unknown)[0])
                raise TdofError(f"its array obj_id holds {int(obj[i])} at [{first(unknown)}], an object its "
                                "models_info does not have", path)
    if used.any():
        RtR = np.einsum("...ji,...jk->...ik", R, R)
        err = np.abs(RtR - np.eye(3, dtype=np.float32)).max(axis=(-2, -1))
        det = np.linalg.det(R.astype(np.float64))
        bad = used & ((err > 1e-2) | (det < 0))
        if bad.any():
            raise TdofError(f"its array R is not a rotation at [{first(bad)}] (R^T R differs from I by "
                            f"{err[tuple(np.argwhere(bad)[0])]:.3g}, det {det[tuple(np.argwhere(bad)[0])]:.3g})", path)
        far = used & (np.linalg.norm(t.astype(np.float64), axis=-1) > T_MAX_MM)
        if far.any():
            raise TdofError(f"its array t is beyond {T_MAX_MM:g} mm at [{first(far)}]", path)
    badk = ~np.isfinite(K).all(axis=(1, 2)) | (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0) | \
        (np.abs(K[:, 2] - np.array([0, 0, 1], np.float32)).max(axis=1) > 1e-6)
    if badk.any():
        raise TdofError(f"its array K is not a camera matrix at [{first(badk)}] (NaN, fx/fy <= 0 or last row "
                        "not 0 0 1)", path)
    bads = ~np.isfinite(depth_scale) | (depth_scale <= 0)
    if bads.any():
        raise TdofError(f"its array depth_scale is not a positive number at [{first(bads)}]", path)


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
                    obj, R, t = _array(f, "obj_id", self.path), _array(f, "R", self.path), _array(f, "t", self.path)
                    K = _array(f, "K", self.path)
                    scale = _array(f, "depth_scale", self.path)
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
        check_plausible(self.path, obj, R, t, K, scale, self.attrs.get("models_info"))
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

        def get(name):  # a damaged compressed chunk: one line naming the shard and the array
            try:
                return f[name][n]
            except (OSError, ValueError) as e:
                raise TdofError(f"its array {name} cannot be read at image {n} (damaged: "
                                f"{(str(e).splitlines() or [''])[0][:60]})", self.path) from None

        s = float(get("depth_scale"))
        return {
            "rgb": torch.from_numpy(np.ascontiguousarray(get("rgb").transpose(2, 0, 1))),
            "depth": torch.from_numpy(get("depth").astype(np.float32) * s),
            "depth_restored": torch.from_numpy(get("depth_restored").astype(np.float32) * s),
            "label": torch.from_numpy(get("label").astype(np.int64)),
            "instance": torch.from_numpy(get("instance").astype(np.int64)),
            "obj_id": torch.from_numpy(get("obj_id").astype(np.int64)),
            "R": torch.from_numpy(get("R")), "t": torch.from_numpy(get("t")),
            "K": torch.from_numpy(get("K")),
            "scene_id": int(get("scene_id")), "im_id": int(get("im_id")),
        }

    def __getstate__(self) -> dict:
        d = dict(self.__dict__)
        d["_f"] = None
        return d
