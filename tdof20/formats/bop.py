"""BOP scenes, exactly as the BOP toolkit documents them (object models: :mod:`tdof20.formats.bop_models`).

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop_json import (MAX_ID, bop_json_line, by_image_id, check_nums, check_rotation, dumps_bop_json,
                                     flat, is_int, is_num, join_bop_json, write_bop_text)
from tdof20.formats.bop_models import (MODELS_INFO, model_path, read_model_mesh, read_models_info, write_model_mesh,
                                       write_models_info)
from tdof20.formats.io import png_header, read_bytes, read_json, read_png, write_png

SCENE_CAMERA = "scene_camera.json"
SCENE_GT = "scene_gt.json"
SCENE_GT_INFO = "scene_gt_info.json"
EMPTY_BBOX = [-1, -1, -1, -1]
_RESERVED_DIRS = ("rgb", "depth", "mask", "mask_visib")


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def pose_to_bop(R: np.ndarray, t: np.ndarray, obj_id: int | None = None) -> dict:
    """(R (3,3), t (3,) mm) -> {"cam_R_m2c": 9 floats row-major, "cam_t_m2c": 3 floats}
    (with "obj_id" first when given)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3) or t.size != 3:
        raise ValueError(f"pose_to_bop needs R (3,3) and t (3,), got {R.shape} and {t.shape}")
    d = {} if obj_id is None else {"obj_id": int(obj_id)}
    d["cam_R_m2c"] = flat(R)
    d["cam_t_m2c"] = flat(t)
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


# ---------------------------------------------------------------------------------------------
# validation (one-line TdofError naming the file)
# ---------------------------------------------------------------------------------------------

def _parse_camera(path: Path, data: Any) -> dict[int, dict]:
    out = {}
    for im_id, e in by_image_id(path, data).items():
        w = f"image {im_id}"
        if not isinstance(e, dict):
            raise TdofError(f"{w}: entry must be an object, got {type(e).__name__}", path)
        if "cam_K" not in e:
            raise TdofError(f"{w}: missing field 'cam_K'", path)
        if "depth_scale" not in e:
            raise TdofError(f"{w}: missing field 'depth_scale'", path)
        cam = copy.deepcopy(e)
        K = check_nums(path, e["cam_K"], 9, f"{w}: cam_K").reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.any(K[2] != [0, 0, 1]):
            raise TdofError(f"{w}: cam_K is not an intrinsic matrix (fx, fy > 0, last row 0 0 1)", path)
        cam["cam_K"] = K
        ds = e["depth_scale"]
        if not is_num(ds) or ds <= 0:
            raise TdofError(f"{w}: depth_scale must be a number > 0, got {ds!r}", path)
        cam["depth_scale"] = float(ds)
        if ("cam_R_w2c" in e) != ("cam_t_w2c" in e):
            raise TdofError(f"{w}: cam_R_w2c and cam_t_w2c must be given together", path)
        if "cam_R_w2c" in e:
            cam["cam_R_w2c"] = check_rotation(path, e["cam_R_w2c"], f"{w}: cam_R_w2c")
            cam["cam_t_w2c"] = check_nums(path, e["cam_t_w2c"], 3, f"{w}: cam_t_w2c")
        out[im_id] = cam
    return out


def _parse_gt(path: Path, data: Any) -> dict[int, list[dict]]:
    out = {}
    for im_id, lst in by_image_id(path, data).items():
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
            if not is_int(e["obj_id"]) or not 1 <= e["obj_id"] <= MAX_ID:
                raise TdofError(f"{w}: obj_id must be an integer from 1 to {MAX_ID}, got {e['obj_id']!r}", path)
            g = copy.deepcopy(e)
            g["cam_R_m2c"] = check_rotation(path, e["cam_R_m2c"], f"{w}: cam_R_m2c")
            g["cam_t_m2c"] = check_nums(path, e["cam_t_m2c"], 3, f"{w}: cam_t_m2c")
            items.append(g)
        out[im_id] = items
    return out


_GT_INFO_INT = ("px_count_all", "px_count_valid", "px_count_visib")


def _parse_gt_info(path: Path, data: Any) -> dict[int, list[dict]]:
    out = {}
    for im_id, lst in by_image_id(path, data).items():
        if not isinstance(lst, list):
            raise TdofError(f"image {im_id}: must be a list of instances, got {type(lst).__name__}", path)
        for gt_id, e in enumerate(lst):
            w = f"image {im_id} instance {gt_id}"
            if not isinstance(e, dict):
                raise TdofError(f"{w}: must be an object, got {type(e).__name__}", path)
            for k in ("bbox_obj", "bbox_visib"):
                if k in e and (not isinstance(e[k], list) or len(e[k]) != 4 or not all(is_num(x) for x in e[k])):
                    raise TdofError(f"{w}: {k} must be 4 numbers [x, y, w, h], got {e[k]!r}", path)
            for k in _GT_INFO_INT:
                if k in e and (not is_int(e[k]) or e[k] < 0):
                    raise TdofError(f"{w}: {k} must be an integer >= 0, got {e[k]!r}", path)
            if "visib_fract" in e and (not is_num(e["visib_fract"]) or not 0 <= e["visib_fract"] <= 1):
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
    _check_across(d, camera, gt, gt_info)
    return BopScene(d, camera, gt, gt_info)


def _check_across(d: Path, camera: dict[int, Any], gt: dict[int, list], gt_info: dict[int, list]) -> None:
    """The three files of scene ``d`` agree: every image with ground truth has a camera entry, and
    gt_info lists as many instances as scene_gt."""
    for im_id in gt:
        if im_id not in camera:
            raise TdofError(f"image {im_id} has ground truth but no camera entry in {SCENE_CAMERA}", d / SCENE_GT)
    for im_id, lst in gt_info.items():
        if im_id in gt and len(lst) != len(gt[im_id]):
            raise TdofError(f"image {im_id} lists {len(lst)} instances, {SCENE_GT} lists {len(gt[im_id])}",
                            d / SCENE_GT_INFO)


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
_SCENE_FILES = ((SCENE_CAMERA, _parse_camera), (SCENE_GT, _parse_gt), (SCENE_GT_INFO, _parse_gt_info))
# the order flush writes them: scene_camera.json, the file that lists the images, last
_FLUSH_ORDER = (SCENE_GT_INFO, SCENE_GT, SCENE_CAMERA)


def drop_stale_masks(scene_dir: str | Path, im_id: int, n_instances: int) -> None:
    """Remove the masks of instances ``gt_id >= n_instances`` of image ``im_id`` (left by an
    earlier write of the frame with more instances)."""
    for sub in ("mask", "mask_visib"):
        gt_id = n_instances
        while (p := Path(scene_dir) / sub / _mask_name(im_id, gt_id)).exists():
            p.unlink()
            gt_id += 1


class BopSceneWriter:
    """Write a BOP scene frame by frame, resumably: the one writer of scene folders.

    Opening a writer reads the entries of the three JSON files already in the folder (a malformed
    scene is refused: TdofError naming the file), so a resumed writer keeps the earlier frames.
    A frame is added by :meth:`add_frame` (which also writes its images, atomically) or, when its
    images were written elsewhere (e.g. by worker processes), by :meth:`put` with its entries;
    :meth:`drop` removes a frame's entries. :attr:`camera`, :attr:`gt` and :attr:`gt_info` hold
    every entry {im_id: JSON value}, earlier and new. :meth:`flush` rewrites the three files whole
    and atomically when something changed (each entry is serialised once, when added, so a flush
    costs a join and a write; flush every few seconds or hundred frames, not after each one). Use
    as a context manager to flush on exit. One writer per scene folder at a time.
    """

    def __init__(self, scene_dir: str | Path, png_compression: int = 1):
        self.path = Path(scene_dir)
        self.png_compression = png_compression
        self.camera: dict[int, dict] = {}
        self.gt: dict[int, list[dict]] = {}
        self.gt_info: dict[int, list[dict]] = {}
        self._entries = {SCENE_CAMERA: self.camera, SCENE_GT: self.gt, SCENE_GT_INFO: self.gt_info}
        self._lines: dict[str, dict[int, str]] = {name: {} for name in self._entries}
        self._dirty = False
        parsed: dict[str, dict] = {}
        for name, parse in _SCENE_FILES:
            p = self.path / name
            if not p.exists():
                continue
            raw = read_json(p)
            parsed[name] = parse(p, raw)  # refuse to merge into a malformed file
            for im_id, v in by_image_id(p, raw).items():
                self._entries[name][im_id] = v
                self._lines[name][im_id] = bop_json_line(im_id, v)
        if SCENE_CAMERA in parsed:
            _check_across(self.path, parsed[SCENE_CAMERA], parsed.get(SCENE_GT, {}), parsed.get(SCENE_GT_INFO, {}))

    def has(self, im_id: int) -> bool:
        """Whether image ``im_id`` has an entry in each of the three files."""
        return all(im_id in e for e in self._entries.values())

    def has_any(self, im_id: int) -> bool:
        """Whether image ``im_id`` has an entry in any of the three files."""
        return any(im_id in e for e in self._entries.values())

    def put(self, im_id: int, camera: dict, gt: list[dict], gt_info: list[dict]) -> None:
        """Set the entries of image ``im_id`` (replacing any): its scene_camera entry, and its
        scene_gt and scene_gt_info lists (one item per instance, gt_id = index), all JSON values."""
        im_id = int(im_id)
        for name, v in zip(self._entries, (camera, gt, gt_info)):
            self._entries[name][im_id] = v
            self._lines[name][im_id] = bop_json_line(im_id, v)
        self._dirty = True

    def drop(self, im_id: int) -> None:
        """Remove the entries of image ``im_id`` (its files stay: the caller removes them)."""
        for name, entries in self._entries.items():
            if entries.pop(im_id, None) is not None:
                self._lines[name].pop(im_id, None)
                self._dirty = True

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
        cam = {"cam_K": flat(K), "depth_scale": float(depth_scale)}
        if T_w2c is not None:
            T = np.asarray(T_w2c, dtype=np.float64).reshape(4, 4)
            cam["cam_R_w2c"] = flat(T[:3, :3])
            cam["cam_t_w2c"] = flat(T[:3, 3])

        c = self.png_compression
        if rgb is not None:
            write_png(self.path / "rgb" / _im(im_id), np.asarray(rgb), c)
        if depth is not None:
            write_png(self.path / "depth" / _im(im_id), np.asarray(depth), c)
        for gt_id, (mf, mv) in enumerate(zip(masks_full, masks_visib)):
            write_png(self.path / "mask" / _mask_name(im_id, gt_id), mf.astype(np.uint8) * 255, c)
            write_png(self.path / "mask_visib" / _mask_name(im_id, gt_id), mv.astype(np.uint8) * 255, c)
        drop_stale_masks(self.path, im_id, len(poses))  # a re-written frame with fewer instances
        for name, img in (extra or {}).items():
            a = np.asarray(img)
            if a.dtype == bool:
                a = a.astype(np.uint8) * 255
            write_png(self.path / name / _im(im_id), a, c)

        self.put(im_id, cam, gt_list, info_list)
        return info_list

    def flush(self) -> None:
        """Write scene_camera.json, scene_gt.json and scene_gt_info.json whole, atomically and
        synced, when an entry changed since the last flush (scene_camera.json last)."""
        if not self._dirty:
            return
        for name in _FLUSH_ORDER:
            lines = self._lines[name]
            write_bop_text(self.path / name, join_bop_json([lines[k] for k in sorted(lines)]))
        self._dirty = False

    def __enter__(self) -> "BopSceneWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.flush()


# ---------------------------------------------------------------------------------------------
# poses in metres
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


__all__ = [
    "SCENE_CAMERA", "SCENE_GT", "SCENE_GT_INFO", "EMPTY_BBOX", "BopScene", "BopSceneWriter", "read_scene",
    "check_scene_images", "gt_info_from_masks", "bbox_from_mask", "pose_to_bop", "pose_from_bop", "drop_stale_masks",
    "dumps_bop_json", "colour_path", "read_colour", "COLOUR_SUFFIXES", "METRES_BELOW_MM", "median_distance_if_metres",
    # object models, from tdof20.formats.bop_models (kept importable from here)
    "MODELS_INFO", "write_models_info", "read_models_info", "model_path", "read_model_mesh", "write_model_mesh",
]
