"""BOP scenes and object-model info, exactly as the BOP toolkit documents them.

A scene folder (``docs/bop_datasets_format.md`` of https://github.com/thodan/bop_toolkit)::

    scene_camera.json   {"<im_id>": {"cam_K": [9], "depth_scale": s, ["cam_R_w2c": [9], "cam_t_w2c": [3]]}}
    scene_gt.json       {"<im_id>": [{"obj_id": i, "cam_R_m2c": [9], "cam_t_m2c": [3]}, ...]}
    scene_gt_info.json  {"<im_id>": [{"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid",
                                      "px_count_visib", "visib_fract"}, ...]}
    rgb/{im_id:06d}.png  depth/{im_id:06d}.png
    mask/{im_id:06d}_{gt_id:06d}.png  mask_visib/{im_id:06d}_{gt_id:06d}.png   (uint8 0/255)

Rotations row-major, translations and depth in millimetres (depth image x depth_scale = mm);
``x_cam = R @ x_model + t``. ``gt_id`` is the index of the instance in the frame's scene_gt list.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.io import atomic_write_bytes, dumps_json, png_header, read_bytes, read_json, read_png, write_png

SCENE_CAMERA = "scene_camera.json"
SCENE_GT = "scene_gt.json"
SCENE_GT_INFO = "scene_gt_info.json"
MODELS_INFO = "models_info.json"
EMPTY_BBOX = [-1, -1, -1, -1]
_RESERVED_DIRS = ("rgb", "depth", "mask", "mask_visib")
_ROT_TOL = 1e-3


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def _flat(a: Any) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


def pose_to_bop(R: np.ndarray, t: np.ndarray, obj_id: int | None = None) -> dict:
    """(R (3,3), t (3,) mm) -> {"cam_R_m2c": 9 floats row-major, "cam_t_m2c": 3 floats}
    (with "obj_id" first when given)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3) or t.size != 3:
        raise ValueError(f"pose_to_bop needs R (3,3) and t (3,), got {R.shape} and {t.shape}")
    d = {} if obj_id is None else {"obj_id": int(obj_id)}
    d["cam_R_m2c"] = _flat(R)
    d["cam_t_m2c"] = _flat(t)
    return d


def pose_from_bop(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """A scene_gt entry (or any dict with cam_R_m2c / cam_t_m2c) -> (R (3,3), t (3,) mm)."""
    R = np.asarray(entry["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
    t = np.asarray(entry["cam_t_m2c"], dtype=np.float64).reshape(3)
    return R, t


def bbox_from_mask(mask: np.ndarray) -> list[int]:
    """BOP 2D box [x, y, w, h] of a mask's pixels, with w = x_max - x_min and h = y_max - y_min
    as ``bop_toolkit_lib.misc.calc_2d_bbox`` computes it; [-1, -1, -1, -1] for an empty mask."""
    ys, xs = np.nonzero(np.asarray(mask, dtype=bool))
    if len(xs) == 0:
        return list(EMPTY_BBOX)
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0, int(ys.max()) - y0]


def _visib_inside(full: np.ndarray, visib: np.ndarray) -> np.ndarray:
    """The visible part clipped to the silhouette. A few stray pixels outside it (a renderer's
    edge rays hitting in one cast and missing in the other) are dropped; many are a mistake."""
    outside = int(np.count_nonzero(visib & ~full))
    if outside == 0:
        return visib
    if outside > max(5, 0.02 * int(visib.sum())):
        raise ValueError(f"mask_visib has {outside} pixels outside mask_full: the visible part must lie "
                         f"inside the silhouette (masks swapped?)")
    return visib & full


def gt_info_from_masks(mask_full: np.ndarray, mask_visib: np.ndarray, depth: np.ndarray | None = None) -> dict:
    """One scene_gt_info entry from an instance's full silhouette and visible part (H,W) bool.

    px_count_valid counts silhouette pixels with a depth measurement (depth > 0), as BOP defines
    it; 0 when no depth image is given. visib_fract = px_count_visib / px_count_all (0.0 if empty).
    A few mask_visib pixels outside mask_full (<= max(5, 2%)) are dropped; more -> ValueError.
    """
    full = np.asarray(mask_full, dtype=bool)
    visib = np.asarray(mask_visib, dtype=bool)
    if full.ndim != 2 or visib.shape != full.shape:
        raise ValueError(f"masks must be two (H,W) arrays of one shape, got {full.shape} and {visib.shape}")
    visib = _visib_inside(full, visib)
    n_all = int(full.sum())
    n_visib = int(visib.sum())
    if depth is None:
        n_valid = 0
    else:
        d = np.asarray(depth)
        if d.shape != full.shape:
            raise ValueError(f"depth is {d.shape}, masks are {full.shape}")
        n_valid = int(np.count_nonzero(full & (d > 0)))
    return {
        "bbox_obj": bbox_from_mask(full),
        "bbox_visib": bbox_from_mask(visib),
        "px_count_all": n_all,
        "px_count_valid": n_valid,
        "px_count_visib": n_visib,
        "visib_fract": float(n_visib / n_all) if n_all > 0 else 0.0,
    }


def dumps_bop_json(content: dict) -> str:
    """BOP toolkit layout: one line per top-level key (sorted numerically), compact values."""
    keys = sorted(content, key=lambda k: (0, int(k)) if str(k).lstrip("-").isdigit() else (1, str(k)))
    lines = [f"  {json.dumps(str(k))}: {dumps_json(content[k], indent=None)}" for k in keys]
    return "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}\n"


def _write_bop_json(path: Path, content: dict) -> None:
    atomic_write_bytes(path, dumps_bop_json(content).encode(), fsync=True)


# ---------------------------------------------------------------------------------------------
# validation (one-line TdofError naming the file)
# ---------------------------------------------------------------------------------------------
def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _nums(path: Path, v: Any, n: int, where: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        got = len(v) if isinstance(v, list) else type(v).__name__
        raise TdofError(f"{where} must be {n} numbers, got {got}", path)
    if not all(_is_num(x) for x in v):
        raise TdofError(f"{where} must hold finite numbers only", path)
    return np.asarray(v, dtype=np.float64)


def _rot(path: Path, v: Any, where: str) -> np.ndarray:
    R = _nums(path, v, 9, where).reshape(3, 3)
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > _ROT_TOL or np.linalg.det(R) < 0:
        raise TdofError(f"{where} is not a rotation matrix (|R R^T - I| = {err:.2g}, det {np.linalg.det(R):.3g})", path)
    return R


def _top(path: Path, data: Any) -> dict[int, Any]:
    if not isinstance(data, dict):
        raise TdofError(f"must hold a JSON object keyed by image id, got {type(data).__name__}", path)
    out = {}
    for k, v in data.items():
        try:
            i = int(k)
        except ValueError:
            raise TdofError(f"key {k!r} is not an integer id", path) from None
        if i < 0 or str(i) != str(k).strip():
            raise TdofError(f"key {k!r} is not a non-negative integer id", path)
        out[i] = v
    return out


def _parse_camera(path: Path, data: Any) -> dict[int, dict]:
    out = {}
    for im_id, e in _top(path, data).items():
        w = f"image {im_id}"
        if not isinstance(e, dict):
            raise TdofError(f"{w}: entry must be an object, got {type(e).__name__}", path)
        if "cam_K" not in e:
            raise TdofError(f"{w}: missing field 'cam_K'", path)
        if "depth_scale" not in e:
            raise TdofError(f"{w}: missing field 'depth_scale'", path)
        cam = copy.deepcopy(e)
        K = _nums(path, e["cam_K"], 9, f"{w}: cam_K").reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.any(K[2] != [0, 0, 1]):
            raise TdofError(f"{w}: cam_K is not an intrinsic matrix (fx, fy > 0, last row 0 0 1)", path)
        cam["cam_K"] = K
        ds = e["depth_scale"]
        if not _is_num(ds) or ds <= 0:
            raise TdofError(f"{w}: depth_scale must be a number > 0, got {ds!r}", path)
        cam["depth_scale"] = float(ds)
        if ("cam_R_w2c" in e) != ("cam_t_w2c" in e):
            raise TdofError(f"{w}: cam_R_w2c and cam_t_w2c must be given together", path)
        if "cam_R_w2c" in e:
            cam["cam_R_w2c"] = _rot(path, e["cam_R_w2c"], f"{w}: cam_R_w2c")
            cam["cam_t_w2c"] = _nums(path, e["cam_t_w2c"], 3, f"{w}: cam_t_w2c")
        out[im_id] = cam
    return out


def _parse_gt(path: Path, data: Any) -> dict[int, list[dict]]:
    out = {}
    for im_id, lst in _top(path, data).items():
        if not isinstance(lst, list):
            raise TdofError(f"image {im_id}: must be a list of instances, got {type(lst).__name__}", path)
        items = []
        for gt_id, e in enumerate(lst):
            w = f"image {im_id} instance {gt_id}"
            if not isinstance(e, dict):
                raise TdofError(f"{w}: must be an object, got {type(e).__name__}", path)
            for k in ("obj_id", "cam_R_m2c", "cam_t_m2c"):
                if k not in e:
                    raise TdofError(f"{w}: missing field '{k}'", path)
            if not _is_int(e["obj_id"]) or e["obj_id"] < 1:
                raise TdofError(f"{w}: obj_id must be an integer >= 1, got {e['obj_id']!r}", path)
            g = copy.deepcopy(e)
            g["cam_R_m2c"] = _rot(path, e["cam_R_m2c"], f"{w}: cam_R_m2c")
            g["cam_t_m2c"] = _nums(path, e["cam_t_m2c"], 3, f"{w}: cam_t_m2c")
            items.append(g)
        out[im_id] = items
    return out


_GT_INFO_INT = ("px_count_all", "px_count_valid", "px_count_visib")


def _parse_gt_info(path: Path, data: Any) -> dict[int, list[dict]]:
    out = {}
    for im_id, lst in _top(path, data).items():
        if not isinstance(lst, list):
            raise TdofError(f"image {im_id}: must be a list of instances, got {type(lst).__name__}", path)
        for gt_id, e in enumerate(lst):
            w = f"image {im_id} instance {gt_id}"
            if not isinstance(e, dict):
                raise TdofError(f"{w}: must be an object, got {type(e).__name__}", path)
            for k in ("bbox_obj", "bbox_visib"):
                if k in e and (not isinstance(e[k], list) or len(e[k]) != 4 or not all(_is_num(x) for x in e[k])):
                    raise TdofError(f"{w}: {k} must be 4 numbers [x, y, w, h], got {e[k]!r}", path)
            for k in _GT_INFO_INT:
                if k in e and (not _is_int(e[k]) or e[k] < 0):
                    raise TdofError(f"{w}: {k} must be an integer >= 0, got {e[k]!r}", path)
            if "visib_fract" in e and (not _is_num(e["visib_fract"]) or not 0 <= e["visib_fract"] <= 1):
                raise TdofError(f"{w}: visib_fract must be a number in 0..1, got {e['visib_fract']!r}", path)
        out[im_id] = copy.deepcopy(lst)
    return out


# ---------------------------------------------------------------------------------------------
# reading a scene
# ---------------------------------------------------------------------------------------------
def _im(im_id: int) -> str:
    return f"{int(im_id):06d}.png"


def _mask_name(im_id: int, gt_id: int) -> str:
    return f"{int(im_id):06d}_{int(gt_id):06d}.png"


COLOUR_SUFFIXES = (".png", ".jpg", ".jpeg")


def colour_path(folder: str | Path, im_id: int) -> Path:
    """The colour image ``{im_id:06d}`` of ``folder``: .png, else .jpg / .jpeg when one exists
    (the .png name when none does, so that a missing image is reported under it)."""
    folder = Path(folder)
    stem = f"{int(im_id):06d}"
    for suffix in COLOUR_SUFFIXES:
        p = folder / (stem + suffix)
        if p.exists():
            return p
    return folder / (stem + ".png")


def read_colour(path: str | Path) -> np.ndarray:
    """(H,W,3) uint8 RGB of a PNG (checked, :func:`read_png`) or a JPEG (OpenCV); a missing or
    undecodable file is one TdofError naming it."""
    p = Path(path)
    if p.suffix.lower() == ".png":
        return read_png(p, kind="rgb")
    import cv2

    data = np.frombuffer(read_bytes(p, "colour image"), np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        raise TdofError("cannot be decoded as a JPEG colour image", p)
    return np.ascontiguousarray(img[:, :, ::-1])


@dataclass
class BopScene:
    """A BOP scene read from disk. camera[im_id] = {"cam_K" (3,3), "depth_scale", optional
    "cam_R_w2c" (3,3) / "cam_t_w2c" (3,)}; gt[im_id] = [{"obj_id", "cam_R_m2c" (3,3),
    "cam_t_m2c" (3,) mm}]; gt_info[im_id] = [BOP gt_info dicts] (empty if the file is absent)."""

    path: Path
    camera: dict[int, dict]
    gt: dict[int, list[dict]] = field(default_factory=dict)
    gt_info: dict[int, list[dict]] = field(default_factory=dict)

    def im_ids(self) -> list[int]:
        return sorted(self.camera)

    def K(self, im_id: int) -> np.ndarray:
        return self._cam(im_id)["cam_K"]

    def depth_scale(self, im_id: int) -> float:
        return float(self._cam(im_id)["depth_scale"])

    def pose(self, im_id: int, gt_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(R (3,3), t (3,) mm) of instance ``gt_id`` in image ``im_id``."""
        insts = self.gt.get(im_id)
        if insts is None or not 0 <= gt_id < len(insts):
            raise TdofError(f"image {im_id} has no ground-truth instance {gt_id}", self.path / SCENE_GT)
        return pose_from_bop(insts[gt_id])

    def mask(self, im_id: int, gt_id: int, visib: bool = False) -> np.ndarray:
        """(H,W) bool silhouette (visib=False) or visible part (visib=True) of an instance."""
        sub = "mask_visib" if visib else "mask"
        return read_png(self.path / sub / _mask_name(im_id, gt_id), kind="mask") > 0

    def rgb_path(self, im_id: int) -> Path:
        """``rgb/{im_id:06d}.png``, or ``.jpg`` when only that exists (BOP allows both)."""
        return colour_path(self.path / "rgb", im_id)

    def rgb(self, im_id: int) -> np.ndarray:
        """(H,W,3) uint8 RGB (a PNG or a JPEG)."""
        return read_colour(self.rgb_path(im_id))

    def depth(self, im_id: int) -> np.ndarray:
        """(H,W) uint16 depth in ``depth_scale`` mm units (0 = no depth)."""
        return read_png(self.path / "depth" / _im(im_id), kind="depth")

    def depth_mm(self, im_id: int) -> np.ndarray:
        """(H,W) float32 depth in millimetres."""
        return self.depth(im_id).astype(np.float32) * np.float32(self.depth_scale(im_id))

    def image(self, name: str, im_id: int) -> np.ndarray:
        """Any other per-image PNG written as ``<name>/{im_id:06d}.png``."""
        return read_png(self.path / name / _im(im_id))

    def _cam(self, im_id: int) -> dict:
        if im_id not in self.camera:
            raise TdofError(f"no image {im_id} in this scene", self.path / SCENE_CAMERA)
        return self.camera[im_id]


def read_scene(scene_dir: str | Path, require_gt: bool = True) -> BopScene:
    """Read a BOP scene folder; scene_camera.json (and scene_gt.json unless ``require_gt`` is
    False) must exist; scene_gt_info.json is read when present. Problems -> TdofError naming the file."""
    d = Path(scene_dir)
    if not d.is_dir():
        raise TdofError("no such scene folder", d)
    camera = _parse_camera(d / SCENE_CAMERA, read_json(d / SCENE_CAMERA))
    gt: dict[int, list[dict]] = {}
    if require_gt or (d / SCENE_GT).exists():
        gt = _parse_gt(d / SCENE_GT, read_json(d / SCENE_GT))
    gt_info: dict[int, list[dict]] = {}
    if (d / SCENE_GT_INFO).exists():
        gt_info = _parse_gt_info(d / SCENE_GT_INFO, read_json(d / SCENE_GT_INFO))
    for im_id in gt:
        if im_id not in camera:
            raise TdofError(f"image {im_id} has ground truth but no camera entry in {SCENE_CAMERA}", d / SCENE_GT)
    for im_id, lst in gt_info.items():
        if im_id in gt and len(lst) != len(gt[im_id]):
            raise TdofError(f"image {im_id} lists {len(lst)} instances, {SCENE_GT} lists {len(gt[im_id])}",
                            d / SCENE_GT_INFO)
    return BopScene(d, camera, gt, gt_info)


def check_scene_images(scene: BopScene, depth_dirs: Iterable[str] = ("depth_opaque", "depth_restored")) -> tuple[int, int]:
    """Check every image of a scene from its PNG header, without decoding: ``rgb/`` and
    ``depth/`` for each image of scene_camera.json, ``mask/`` and ``mask_visib/`` for each
    instance of scene_gt.json, and the images present in each of ``depth_dirs`` (optional
    16-bit depths). Each must be a PNG (a JPEG named .png is refused) of its kind: colour 8-bit
    RGB(A), depths 16-bit grey, masks grey; all of one size, with each image's principal point
    (cam_K) inside it. Returns (height, width); a problem is a TdofError naming the file."""
    d = scene.path
    size: tuple[int, int] | None = None
    first: Path | None = None

    def check(path: Path, kind: str, why: str) -> None:
        nonlocal size, first
        if not path.is_file():
            raise TdofError(f"file not found: {why}", path)
        hw = png_header(path, kind)
        if size is None:
            size, first = hw, path
        elif hw != size:
            raise TdofError(f"the image is {hw[1]}x{hw[0]} (width x height), {first.relative_to(d)} is "
                            f"{size[1]}x{size[0]}: every image of a scene must have one size", path)

    for im_id in scene.im_ids():
        why = f"{SCENE_CAMERA} lists image {im_id}"
        check(d / "rgb" / _im(im_id), "rgb", why)
        check(d / "depth" / _im(im_id), "depth", why)
        for sub in depth_dirs:
            if (d / sub / _im(im_id)).exists():
                check(d / sub / _im(im_id), "depth", why)
        for gt_id in range(len(scene.gt.get(im_id, ()))):
            why = f"{SCENE_GT} lists instance {gt_id} of image {im_id}"
            check(d / "mask" / _mask_name(im_id, gt_id), "mask", why)
            check(d / "mask_visib" / _mask_name(im_id, gt_id), "mask", why)
        h, w = size
        cx, cy = scene.K(im_id)[0, 2], scene.K(im_id)[1, 2]
        if not (0 < cx < w and 0 < cy < h):
            raise TdofError(f"image {im_id}: the principal point (cx, cy) = ({cx:g}, {cy:g}) of cam_K lies outside "
                            f"its {w}x{h} images: cam_K does not belong to them", d / SCENE_CAMERA)
    if size is None:
        raise TdofError("has no images (scene_camera.json lists none)", d)
    return size


# ---------------------------------------------------------------------------------------------
# writing a scene
# ---------------------------------------------------------------------------------------------
class BopSceneWriter:
    """Write a BOP scene frame by frame. Images are written (atomically) by :meth:`add_frame`;
    the three JSON files by :meth:`flush` (atomically, merged with what is already on disk, so a
    resumed writer keeps earlier frames; this writer's entries win). Use as a context manager to
    flush on exit. Flushing re-reads the JSON files: flush every few hundred frames, not each one.
    """

    def __init__(self, scene_dir: str | Path, png_compression: int = 1):
        self.path = Path(scene_dir)
        self.png_compression = png_compression
        self.camera: dict[int, dict] = {}
        self.gt: dict[int, list[dict]] = {}
        self.gt_info: dict[int, list[dict]] = {}

    def add_frame(self, im_id: int, cam_K: np.ndarray, depth_scale: float,
                  poses: Iterable[tuple[int, np.ndarray, np.ndarray]],
                  masks_full: list[np.ndarray], masks_visib: list[np.ndarray],
                  rgb: np.ndarray | None = None, depth: np.ndarray | None = None,
                  T_w2c: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None) -> list[dict]:
        """Add image ``im_id``: poses [(obj_id, R (3,3), t (3,) mm)], one full and one visible
        (H,W) bool mask per pose (same order: gt_id = index), optional rgb (H,W,3) uint8, depth
        (H,W) uint16 (``depth_scale`` mm per unit), T_w2c (4,4) world -> camera, and extra
        images {name: (H,W[,3]) array} written to ``<name>/{im_id:06d}.png``. Returns the gt_info list."""
        im_id = int(im_id)
        if im_id < 0:
            raise ValueError(f"im_id must be >= 0, got {im_id}")
        poses = list(poses)
        if not (len(poses) == len(masks_full) == len(masks_visib)):
            raise ValueError(f"need one full and one visible mask per pose: {len(poses)} poses, "
                             f"{len(masks_full)} masks, {len(masks_visib)} visible masks")
        K = np.asarray(cam_K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"cam_K must be (3,3), got {K.shape}")
        if not (float(depth_scale) > 0):
            raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
        shape = None
        for name, img in (("rgb", rgb), ("depth", depth), *(("mask", m) for m in masks_full),
                          *(("mask_visib", m) for m in masks_visib), *(extra or {}).items()):
            if img is not None:
                hw = np.shape(img)[:2]
                if shape is None:
                    shape = hw
                elif hw != shape:
                    raise ValueError(f"{name} image is {hw}, other images of frame {im_id} are {shape}")
        if rgb is not None and (np.shape(rgb)[2:] != (3,) or np.asarray(rgb).dtype != np.uint8):
            raise ValueError(f"rgb must be (H,W,3) uint8, got {np.shape(rgb)} {np.asarray(rgb).dtype}")
        if depth is not None and (np.ndim(depth) != 2 or np.asarray(depth).dtype != np.uint16):
            raise ValueError(f"depth must be (H,W) uint16, got {np.shape(depth)} {np.asarray(depth).dtype}")
        for name in (extra or {}):
            if name in _RESERVED_DIRS or not name or "/" in name or "\\" in name or name.startswith("."):
                raise ValueError(f"extra image name {name!r} is reserved or not a plain folder name")

        gt_list, info_list = [], []
        masks_full = [np.asarray(m, dtype=bool) for m in masks_full]
        masks_visib = [_visib_inside(mf, np.asarray(mv, dtype=bool)) for mf, mv in zip(masks_full, masks_visib)]
        for gt_id, ((obj_id, R, t), mf, mv) in enumerate(zip(poses, masks_full, masks_visib)):
            gt_list.append(pose_to_bop(R, t, obj_id=int(obj_id)))
            info_list.append(gt_info_from_masks(mf, mv, depth))
        cam = {"cam_K": _flat(K), "depth_scale": float(depth_scale)}
        if T_w2c is not None:
            T = np.asarray(T_w2c, dtype=np.float64).reshape(4, 4)
            cam["cam_R_w2c"] = _flat(T[:3, :3])
            cam["cam_t_w2c"] = _flat(T[:3, 3])

        c = self.png_compression
        if rgb is not None:
            write_png(self.path / "rgb" / _im(im_id), np.asarray(rgb), c)
        if depth is not None:
            write_png(self.path / "depth" / _im(im_id), np.asarray(depth), c)
        for gt_id, (mf, mv) in enumerate(zip(masks_full, masks_visib)):
            write_png(self.path / "mask" / _mask_name(im_id, gt_id), mf.astype(np.uint8) * 255, c)
            write_png(self.path / "mask_visib" / _mask_name(im_id, gt_id), mv.astype(np.uint8) * 255, c)
        for sub in ("mask", "mask_visib"):  # a re-written frame with fewer instances: drop stale masks
            gt_id = len(poses)
            while (p := self.path / sub / _mask_name(im_id, gt_id)).exists():
                p.unlink()
                gt_id += 1
        for name, img in (extra or {}).items():
            a = np.asarray(img)
            if a.dtype == bool:
                a = a.astype(np.uint8) * 255
            write_png(self.path / name / _im(im_id), a, c)

        self.camera[im_id] = cam
        self.gt[im_id] = gt_list
        self.gt_info[im_id] = info_list
        return info_list

    def flush(self) -> None:
        """Write scene_camera.json, scene_gt.json, scene_gt_info.json atomically, merged with the
        entries already on disk (this writer's entries replace those of the same im_id)."""
        self.path.mkdir(parents=True, exist_ok=True)
        for name, mine, parse in ((SCENE_CAMERA, self.camera, _parse_camera), (SCENE_GT, self.gt, _parse_gt),
                                  (SCENE_GT_INFO, self.gt_info, _parse_gt_info)):
            p = self.path / name
            merged: dict[int, Any] = {}
            if p.exists():
                raw = read_json(p)
                parse(p, raw)  # refuse to merge into a malformed file
                merged = _top(p, raw)
            merged.update(mine)
            _write_bop_json(p, {str(k): merged[k] for k in sorted(merged)})

    def __enter__(self) -> "BopSceneWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.flush()


# ---------------------------------------------------------------------------------------------
# models_info.json
# ---------------------------------------------------------------------------------------------
_MODEL_NUM = ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


def _check_model_entry(path: Path, obj_id: int, e: Any) -> None:
    w = f"object {obj_id}"
    if not isinstance(e, dict):
        raise TdofError(f"{w}: entry must be an object, got {type(e).__name__}", path)
    if "diameter" not in e:
        raise TdofError(f"{w}: missing field 'diameter'", path)
    if not _is_num(e["diameter"]) or e["diameter"] <= 0:
        raise TdofError(f"{w}: diameter must be a number > 0 (mm), got {e['diameter']!r}", path)
    for k in _MODEL_NUM:
        if k in e and not _is_num(e[k]):
            raise TdofError(f"{w}: {k} must be a finite number, got {e[k]!r}", path)
        if k.startswith("size") and k in e and e[k] < 0:
            raise TdofError(f"{w}: {k} must be >= 0, got {e[k]!r}", path)
    sd = e.get("symmetries_discrete", [])
    if not isinstance(sd, list):
        raise TdofError(f"{w}: symmetries_discrete must be a list of 16-number transforms", path)
    for i, s in enumerate(sd):
        T = _nums(path, s, 16, f"{w}: symmetries_discrete[{i}]").reshape(4, 4)
        _rot(path, _flat(T[:3, :3]), f"{w}: symmetries_discrete[{i}] rotation")
    sc = e.get("symmetries_continuous", [])
    if not isinstance(sc, list):
        raise TdofError(f"{w}: symmetries_continuous must be a list of {{axis, offset}}", path)
    for i, s in enumerate(sc):
        if not isinstance(s, dict) or "axis" not in s or "offset" not in s:
            raise TdofError(f"{w}: symmetries_continuous[{i}] must be an object with 'axis' and 'offset'", path)
        if np.linalg.norm(_nums(path, s["axis"], 3, f"{w}: symmetries_continuous[{i}].axis")) == 0:
            raise TdofError(f"{w}: symmetries_continuous[{i}].axis has zero length", path)
        _nums(path, s["offset"], 3, f"{w}: symmetries_continuous[{i}].offset")


def _models_info_path(path: str | Path) -> Path:
    p = Path(path)
    return p if p.suffix == ".json" else p / MODELS_INFO


def write_models_info(dir: str | Path, infos: dict[int, dict]) -> Path:
    """Validate and write ``<dir>/models_info.json`` ({"<obj_id>": {"diameter": mm, "min_x", ...,
    "size_z", optional "symmetries_discrete", "symmetries_continuous"}}) atomically."""
    path = _models_info_path(dir)
    content = {}
    for obj_id, e in infos.items():
        e = json.loads(dumps_json(e, indent=None))
        _check_model_entry(path, int(obj_id), e)
        content[str(int(obj_id))] = e
    _write_bop_json(path, content)
    return path


def read_models_info(path: str | Path) -> dict[int, dict]:
    """Read ``models_info.json`` (give the models folder or the file) -> {obj_id: entry}."""
    p = _models_info_path(path)
    data = read_json(p)
    if not isinstance(data, dict):
        raise TdofError(f"must hold a JSON object keyed by object id, got {type(data).__name__}", p)
    out = {}
    for k, e in data.items():
        try:
            obj_id = int(k)
        except ValueError:
            raise TdofError(f"key {k!r} is not an integer object id", p) from None
        _check_model_entry(p, obj_id, e)
        out[obj_id] = e
    return out


# ---------------------------------------------------------------------------------------------
# model meshes (obj_{id:06d}.ply)
# ---------------------------------------------------------------------------------------------
#: poses whose median |t| is under this (mm) were written in metres: nothing is posed 1 cm from
#: the camera (dataset build and the training shards refuse them)
METRES_BELOW_MM = 10.0


def median_distance_if_metres(t: np.ndarray) -> float | None:
    """The median |t| (mm) of translations ``t`` (N,3) when it is under METRES_BELOW_MM — the poses
    are in metres —, else None (also for none)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    if not len(t):
        return None
    med = float(np.median(np.linalg.norm(t, axis=1)))
    return med if med < METRES_BELOW_MM else None


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """``<models_dir>/obj_{obj_id:06d}.ply``."""
    return Path(models_dir) / f"obj_{int(obj_id):06d}.ply"


def read_model_mesh(path: str | Path, need_faces: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read a model (PLY/OBJ/STL, mm) -> vertices (V,3) float64, faces (F,3) int64. One reader
    for every stage; a missing, unreadable, empty or non-finite model raises TdofError naming the
    file (``need_faces=False`` accepts a point cloud: faces then has shape (0,3))."""
    import io

    import trimesh
    from trimesh.resolvers import FilePathResolver

    p = Path(path)
    data = read_bytes(p, "model file")
    try:
        geom = trimesh.load(io.BytesIO(data), file_type=p.suffix.lstrip(".").lower() or None, process=False,
                            resolver=FilePathResolver(str(p)))
    except Exception as e:  # trimesh raises many types on bad files
        raise TdofError(f"cannot read the model ({type(e).__name__}: {e})", p) from None
    if isinstance(geom, trimesh.Scene):
        geom = geom.to_geometry() if len(geom.geometry) else None
    V = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    F = np.asarray(getattr(geom, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(V) == 0:
        raise TdofError("the model has no vertices", p)
    if not np.isfinite(V).all():
        raise TdofError("the model has NaN or inf vertices", p)
    if need_faces and len(F) == 0:
        raise TdofError("the model has no faces (a triangle mesh is needed)", p)
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise TdofError("the model's faces index vertices that do not exist", p)
    return V, F


def write_model_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a model atomically as binary little-endian PLY with vertex normals (mm), the form
    the BOP toolkit and trimesh read."""
    import trimesh

    tm = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)
    p = Path(path)
    atomic_write_bytes(p, trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True))
    return p


__all__ = [
    "SCENE_CAMERA", "SCENE_GT", "SCENE_GT_INFO", "MODELS_INFO", "EMPTY_BBOX", "BopScene",
    "BopSceneWriter", "read_scene", "check_scene_images", "gt_info_from_masks", "bbox_from_mask", "pose_to_bop",
    "pose_from_bop", "write_models_info", "read_models_info", "dumps_bop_json", "model_path",
    "read_model_mesh", "write_model_mesh", "colour_path", "read_colour", "COLOUR_SUFFIXES",
]
