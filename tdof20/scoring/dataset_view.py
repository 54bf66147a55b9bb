"""The dataset as scoring reads it (:class:`DatasetView`, over any layout's reader) and the test
targets scored against (:class:`Targets`): scene cameras and ground-truth poses read vectorised
and checked, models and renderers on demand, targets checked against the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.results import ID_MAX
from tdof20.errors import TdofError
from tdof20.formats.bop import MODELS_INFO, model_path, read_model_mesh, read_models_info
from tdof20.formats.io import decode_png, png_header, read_bytes, read_json
from tdof20.scoring import metrics as M
from tdof20.scoring.evaluation import VISIB_MIN


@dataclass
class SceneData:
    """What scoring reads of a scene: cam_K per image and ground-truth poses per image."""

    K: dict[int, np.ndarray]
    gt: dict[int, list[tuple[int, np.ndarray, np.ndarray]]]  # im_id -> [(obj_id, R, t)]
    t_all: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # every instance's t
    depth_scale: dict[int, Any] = field(default_factory=dict)  # im_id -> mm per depth unit (as written; 1.0 if absent)

    def count(self, im_id: int, obj_id: int) -> int:
        return sum(1 for o, _, _ in self.gt.get(im_id, ()) if o == obj_id)


def _numbers(path: Path, values: list, n: int, what: str) -> np.ndarray:
    """(len(values), n) float64 from lists of n finite numbers; one-line error naming ``what``."""
    try:
        arr = np.array(values, dtype=np.float64)
    except (ValueError, TypeError):
        arr = None
    if arr is None or arr.ndim != 2 or arr.shape[1] != n:
        for k, v in enumerate(values):
            if not isinstance(v, list) or len(v) != n or not all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
                raise TdofError(f"{what(k)} must be {n} numbers", path)
        raise TdofError(f"{what(0)}: malformed numbers", path)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise TdofError(f"{what(int(np.argmax(bad)))} holds NaN or inf", path)
    return arr


def _scene_data(scene_dir: Path) -> SceneData:
    """Read and check scene_camera.json (cam_K) and scene_gt.json (poses) of a BOP scene
    (vectorised; one-line errors naming the file, the image and the instance)."""
    if not scene_dir.is_dir():
        raise TdofError("no such scene folder", scene_dir)
    cpath, gpath = scene_dir / "scene_camera.json", scene_dir / "scene_gt.json"
    cam, gt = read_json(cpath), read_json(gpath)
    for path, d in ((cpath, cam), (gpath, gt)):
        if not isinstance(d, dict):
            raise TdofError(f"must hold a JSON object keyed by image id, got {type(d).__name__}", path)
        for k in d:
            if not (isinstance(k, str) and k.isdigit()):
                raise TdofError(f"key {k!r} is not an image id", path)
    cim = [int(k) for k in cam]
    for i, k in zip(cim, cam):
        if not isinstance(cam[k], dict) or "cam_K" not in cam[k]:
            raise TdofError(f"image {i}: missing field 'cam_K'", cpath)
    Ks = _numbers(cpath, [cam[k]["cam_K"] for k in cam], 9, lambda j: f"image {cim[j]}: cam_K").reshape(-1, 3, 3)
    badK = (Ks[:, 0, 0] <= 0) | (Ks[:, 1, 1] <= 0) | np.any(Ks[:, 2] != [0, 0, 1], axis=1)
    if badK.any():
        raise TdofError(f"image {cim[int(np.argmax(badK))]}: cam_K is not an intrinsic matrix", cpath)
    where, objs, Rs, ts = [], [], [], []
    for k, lst in gt.items():
        i = int(k)
        if not isinstance(lst, list):
            raise TdofError(f"image {i}: must be a list of instances", gpath)
        for n, e in enumerate(lst):
            if not isinstance(e, dict) or not all(f in e for f in ("obj_id", "cam_R_m2c", "cam_t_m2c")):
                raise TdofError(f"image {i} instance {n}: needs obj_id, cam_R_m2c and cam_t_m2c", gpath)
            o = e["obj_id"]
            if isinstance(o, bool) or not isinstance(o, int) or o < 1:
                raise TdofError(f"image {i} instance {n}: obj_id must be an integer >= 1, got {o!r}", gpath)
            where.append((i, n))
            objs.append(o)
            Rs.append(e["cam_R_m2c"])
            ts.append(e["cam_t_m2c"])
    what = lambda j: f"image {where[j][0]} instance {where[j][1]}"  # noqa: E731
    R = _numbers(gpath, Rs, 9, lambda j: what(j) + ": cam_R_m2c").reshape(-1, 3, 3) if Rs else np.zeros((0, 3, 3))
    t = _numbers(gpath, ts, 3, lambda j: what(j) + ": cam_t_m2c") if ts else np.zeros((0, 3))
    if len(R):
        err = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).reshape(-1, 9).max(axis=1)
        bad = (err > 1e-3) | (np.linalg.det(R) <= 0)
        if bad.any():
            raise TdofError(f"{what(int(np.argmax(bad)))}: cam_R_m2c is not a rotation matrix", gpath)
    Kd = dict(zip(cim, Ks))
    scales = {i: cam[k].get("depth_scale", 1.0) for i, k in zip(cim, cam)}  # checked when a depth is read
    gtd: dict[int, list] = {int(k): [] for k in gt}
    for j, (i, _) in enumerate(where):
        if i not in Kd:
            raise TdofError(f"image {i} has ground truth but no camera entry", gpath)
        gtd[i].append((objs[j], R[j], t[j]))
    return SceneData(Kd, gtd, t, scales)


def decode_depth(data: bytes, path: Path) -> np.ndarray:
    """A depth PNG's (H,W) uint16 values: :func:`tdof20.formats.io.decode_png` (``kind="depth"``),
    the same array, decoded by Pillow where it reads the file as 16-bit grey (about twice as fast
    as OpenCV's libpng on a 640x480 depth image); anything else, and every error, the usual way."""
    h, w = png_header(path, "depth", data)  # checks the signature, header and size first
    try:
        import io

        from PIL import Image

        with Image.open(io.BytesIO(data), formats=["PNG"]) as im:
            if im.mode == "I;16" and im.size == (w, h):
                arr = np.asarray(im)
                if arr.dtype == np.uint16 and arr.shape == (h, w):
                    return arr
    except Exception:  # Pillow refuses it: the usual decoder words the error
        pass
    return decode_png(data, path, "depth")


class DatasetView:
    """A dataset folder (tdof20's layout or BOP's standard one, read through
    :func:`tdof20.dataset.reader.open_dataset`) as scoring sees it: models_info read at once,
    models and scenes on demand. ``split``: a BOP dataset's split folder (default: the one
    test_targets_bop19.json belongs to); a tdof20 dataset's protocol is only used for messages."""

    def __init__(self, root: str | Path, split: str | None = None):
        self.dataset = open_dataset(root)  # the one "not a dataset" check
        self.root = self.dataset.root
        self.info = self.dataset.info
        # where the scenes of the split (default: the targets' split) are looked up
        self.folder = self.dataset.scene_folder(split if split is not None else self.dataset.targets_split())
        self.scene_ids = set(self.dataset.scene_ids(self.folder))
        self._scenes: dict[int, SceneData] = {}
        self._extra: dict[Any, Any] = {}
        eval_dir = self.dataset.models_eval_dir
        self.models_dir = eval_dir if eval_dir is not None else self.dataset.models_dir
        self.models_info = read_models_info(self.models_dir)
        self.models: dict[int, M.ModelPoints] = {}

    def scene_dir(self, scene_id: int) -> Path:
        return self.dataset.scene_dir(scene_id, self.folder)

    def model(self, obj_id: int) -> M.ModelPoints:
        if obj_id not in self.models:
            e = self.models_info[obj_id]
            sym = bool(e.get("symmetries_continuous")) or bool(e.get("symmetries_discrete"))
            pts = read_model_mesh(model_path(self.models_dir, obj_id), need_faces=False)[0]
            try:
                sR, st = M.symmetry_transformations(e)
            except (KeyError, TypeError, ValueError):
                raise TdofError(f"object {obj_id}: malformed symmetries (BOP form: symmetries_discrete as 4x4 "
                                "matrices of 16 numbers, symmetries_continuous as {\"axis\", \"offset\"})",
                                self.models_dir / MODELS_INFO) from None
            self.models[obj_id] = M.ModelPoints(pts, float(e["diameter"]), sym, sym_R=sR, sym_t=st)
        return self.models[obj_id]

    def mesh_path(self, obj_id: int) -> Path | None:
        """The triangle mesh VSD renders: models_eval/ when its model has faces (BOP renders the
        evaluation models), else models/; None when neither has one."""
        key = ("mesh", obj_id)
        if key not in self._extra:
            found = None
            for d in dict.fromkeys([self.models_dir, self.dataset.models_dir]):
                p = model_path(d, obj_id)
                if p.exists() and len(read_model_mesh(p, need_faces=False)[1]):
                    found = p
                    break
            self._extra[key] = found
        return self._extra[key]

    def renderer(self, obj_id: int) -> M.DepthRenderer:
        key = ("renderer", obj_id)
        if key not in self._extra:
            p = self.mesh_path(obj_id)
            if p is None:
                raise TdofError(f"object {obj_id} has no triangle mesh to render for VSD", self.models_dir)
            self._extra[key] = M.DepthRenderer(*read_model_mesh(p))
        return self._extra[key]

    def depth_path(self, scene_id: int, im_id: int) -> Path:
        return self.scene_dir(scene_id) / "depth" / f"{im_id:06d}.png"

    def depth_mm(self, scene_id: int, im_id: int) -> np.ndarray:
        """(H,W) float32 depth in mm of a test image (depth/ PNG x depth_scale; 0 = no depth)."""
        d, sc = self.depth_raw(scene_id, im_id)
        return d.astype(np.float32) * np.float32(sc)

    def depth_raw(self, scene_id: int, im_id: int) -> tuple[np.ndarray, float]:
        """(the depth/ PNG's (H,W) uint16 values, depth_scale in mm per unit, checked): depth in mm
        is their float32 product, which callers sampling a few pixels form only for those."""
        sc = self.depth_scale(scene_id, im_id)
        path = self.depth_path(scene_id, im_id)
        return decode_depth(read_bytes(path, "image file"), path), sc

    def depth_scale(self, scene_id: int, im_id: int) -> float:
        """A test image's depth_scale (mm per depth unit; 1.0 if absent), checked."""
        sc = self.scene(scene_id).depth_scale.get(im_id, 1.0)
        if isinstance(sc, bool) or not isinstance(sc, (int, float)) or not sc > 0:
            raise TdofError(f"image {im_id}: depth_scale must be a number > 0, got {sc!r}",
                            self.scene_dir(scene_id) / "scene_camera.json")
        return float(sc)

    def depth_bytes(self, scene_id: int, im_id: int) -> bytes:
        """The depth/ PNG's bytes (decode them with :func:`decode_depth`)."""
        return read_bytes(self.depth_path(scene_id, im_id), "image file")

    def mesh_digest(self, obj_id: int) -> str:
        """A digest of the triangle mesh VSD renders (what kept ground-truth renders depend on)."""
        key = ("mesh_digest", obj_id)
        if key not in self._extra:
            import hashlib

            p = self.mesh_path(obj_id)
            self._extra[key] = hashlib.sha256(read_bytes(p, "model file")).hexdigest() if p is not None else ""
        return self._extra[key]

    def image_width(self, scene_id: int) -> int:
        """Image width in pixels (MSPD scales by 640 / width): ROOT/camera.json's ``width``, else
        the header of the scene's first rgb/ or depth/ PNG."""
        key = ("width", scene_id)
        if key not in self._extra:
            w = None
            cam = self.root / "camera.json"
            if cam.exists():
                c = read_json(cam)
                if isinstance(c, dict) and isinstance(c.get("width"), int) and c["width"] > 0:
                    w = int(c["width"])
            if w is None:
                sd = self.scene_dir(scene_id)
                for sub in ("rgb", "depth"):
                    pngs = sorted((sd / sub).glob("*.png")) if (sd / sub).is_dir() else []
                    if pngs:
                        w = png_header(pngs[0])[1]
                        break
            if w is None:
                raise TdofError(f"MSPD and the 2D projection threshold need the image width: camera.json has no 'width' and scene {scene_id} has no "
                                "rgb/ or depth/ images", self.root)
            self._extra[key] = w
        return self._extra[key]

    def bop_instances(self, scene_id: int, im_id: int, obj_id: int,
                      count: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """[(gt_id, R, t)] the ground-truth instances BOP19 matches a target of ``count`` instances
        against: the ``count`` instances of the object with the largest visib_fract
        (scene_gt_info.json; ties and a missing file: in scene_gt.json order)."""
        gts = self.scene(scene_id).gt[im_id]
        vis = self.visib(scene_id)
        fr = vis.get(im_id) if vis is not None else None
        if fr is None or len(fr) != len(gts):
            fr = [1.0] * len(gts)
        ids = sorted((g for g in range(len(gts)) if gts[g][0] == obj_id), key=lambda g: -fr[g])
        return [(g, gts[g][1], gts[g][2]) for g in ids[:count]]

    @property
    def obj_ids(self) -> set[int]:
        return set(self.models_info)

    def scene(self, scene_id: int) -> SceneData:
        if scene_id not in self._scenes:
            self._scenes[scene_id] = _scene_data(self.scene_dir(scene_id))
        return self._scenes[scene_id]

    def visib(self, scene_id: int) -> dict[int, list[float]] | None:
        """visib_fract per image and instance from scene_gt_info.json (None when absent)."""
        key = ("visib", scene_id)
        if key not in self._extra:
            path = self.scene_dir(scene_id) / "scene_gt_info.json"
            out = None
            if path.exists():
                data = read_json(path)
                try:
                    out = {int(k): [float(e.get("visib_fract", 1.0)) for e in v] for k, v in data.items()}
                except (AttributeError, TypeError, ValueError):
                    raise TdofError("malformed scene_gt_info.json (visib_fract per instance)", path) from None
            self._extra[key] = out
        return self._extra[key]

    def valid_instances(self, scene_id: int, im_id: int, obj_id: int, count: int) -> list[tuple]:
        """The ground-truth instances a target of ``count`` instances refers to: those at least
        VISIB_MIN visible when scene_gt_info.json says exactly ``count`` are (BOP's rule, the
        dataset builder's too), else every instance of the object in the image."""
        gts = [(R, t) for o, R, t in self.scene(scene_id).gt[im_id] if o == obj_id]
        vis = self.visib(scene_id)
        if vis is not None and im_id in vis and len(vis[im_id]) == len(self.scene(scene_id).gt[im_id]):
            fr = [v for (o, _, _), v in zip(self.scene(scene_id).gt[im_id], vis[im_id]) if o == obj_id]
            keep = [g for g, v in zip(gts, fr) if v >= VISIB_MIN]
            if len(keep) == count:
                return keep
        return gts

    def scene_label(self, scene_id: int) -> str:
        return self.dataset.scene_name(scene_id, self.folder)

    def object_name(self, obj_id: int) -> str:
        return self.dataset.object_name(obj_id)


@dataclass
class Targets:
    path: Path
    scene_id: np.ndarray
    im_id: np.ndarray
    obj_id: np.ndarray
    inst_count: np.ndarray

    def __len__(self) -> int:
        return len(self.scene_id)


def targets_path(dataset_root: str | Path, split: str | None, targets: str | Path | None,
                 ds: "DatasetView | None" = None) -> Path:
    """The targets file to score against: ``targets``, or those of ``split`` as the dataset's layout
    has them (tdof20: ROOT/test_targets_{split}.json; BOP: ROOT/test_targets_bop19.json of its
    test folder). ``ds``: the dataset's view (default: the dataset at ``dataset_root`` is opened)."""
    reader = ds.dataset if ds is not None else open_dataset(dataset_root)
    if (split is None) == (targets is None):
        raise TdofError(f"give exactly one of --split ({reader.split_hint}) and --targets FILE")
    if targets is not None:
        return Path(targets)
    return reader.scoring_targets_path(split)


def load_targets(path: Path, ds: DatasetView) -> Targets:
    """Read BOP test targets [{"scene_id", "im_id", "obj_id", "inst_count"}] and check them
    against the dataset (scene, image, object and enough ground-truth instances)."""
    data = read_json(path)
    if not isinstance(data, list):
        raise TdofError(f"must hold a JSON list of targets, got {type(data).__name__}", path)
    rows = []
    seen: dict[tuple, int] = {}
    for i, e in enumerate(data):
        if not isinstance(e, dict):
            raise TdofError(f"target {i}: must be an object, got {type(e).__name__}", path)
        vals = []
        for k in ("scene_id", "im_id", "obj_id", "inst_count"):
            v = e.get(k)
            if isinstance(v, bool) or not isinstance(v, int) or v < (1 if k in ("obj_id", "inst_count") else 0):
                raise TdofError(f"target {i}: {k} must be an integer >= {1 if k in ('obj_id', 'inst_count') else 0},"
                                f" got {v!r}", path)
            if v > ID_MAX:
                raise TdofError(f"target {i}: {k} {v} is too large (at most {ID_MAX})", path)
            vals.append(v)
        key = tuple(vals[:3])
        if key in seen:
            raise TdofError(f"target {i}: scene {key[0]} image {key[1]} object {key[2]} is also target "
                            f"{seen[key]}", path)
        seen[key] = i
        rows.append(vals)
    arr = np.asarray(rows, dtype=np.int64).reshape(-1, 4)
    for s in np.unique(arr[:, 0]):
        if int(s) not in ds.scene_ids:
            raise TdofError(f"scene {s} is not in the dataset {ds.root}", path)
        sc = ds.scene(int(s))
        have_of: dict[tuple[int, int], int] = {}
        for im, lst in sc.gt.items():
            for o, _, _ in lst:
                have_of[(im, o)] = have_of.get((im, o), 0) + 1
        objs = ds.obj_ids
        for sid, im, ob, cnt in arr[arr[:, 0] == s].tolist():
            if im not in sc.K:
                raise TdofError(f"scene {sid} has no image {im}", path)
            if ob not in objs:
                raise TdofError(f"object {ob} is not in the dataset's models_info.json", path)
            have = have_of.get((im, ob), 0)
            if have < cnt:
                raise TdofError(f"scene {sid} image {im}: {cnt} instances of object {ob} to find but the ground "
                                f"truth has {have}", path)
    return Targets(path, arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])


def require_targets(tg: Targets, ds: DatasetView, split: str | None) -> None:
    """Refuse to score against no targets (every score would be a meaningless 0 %), saying why."""
    if len(tg):
        return
    if split is None:
        raise TdofError("no test targets in this file: nothing to score", tg.path)
    why = ds.dataset.no_targets_reason(split)
    raise TdofError(f"no test targets in this file: the {split} split of the dataset has none to score{why}", tg.path)


__all__ = ["DatasetView", "SceneData", "Targets", "load_targets", "require_targets", "targets_path"]
