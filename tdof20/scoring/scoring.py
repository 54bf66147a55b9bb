"""Score pose-estimation results against a tdof20 (BOP) dataset: exact accuracies, fast.

``score(results, dataset_root, split=None, targets=None) -> dict`` gives, per object, averaged
over objects ("mean") and pooled over targets ("all")::

    n          number of targets (in "mean": the number of objects averaged)
    add        ADD accuracy       mean distance of corresponding model points < 10% of the diameter
    adds       ADD-S accuracy     mean closest-point distance < 10% of the diameter
    add_s      ADD(S) accuracy    ADD-S for symmetric objects, ADD otherwise (the paper's ADD)
    proj2d     2D projection accuracy, mean reprojection distance < 5 px
    auc_adds   AUC of ADD-S over 0-100 mm: mean over targets of max(0, 1 - e / 100 mm)
    auc_add_s  the same for ADD(S)
    ar_vsd     BOP19 average recall of VSD (10 taus 0.05-0.5 x 10 thresholds 0.05-0.5, delta 15 mm)
    ar_mssd    BOP19 average recall of MSSD (thresholds 0.05-0.5 of the diameter)
    ar_mspd    BOP19 average recall of MSPD (thresholds 5-50 px, errors scaled by 640 / image width)
    ar         (ar_vsd + ar_mssd + ar_mspd) / 3

and "scenes": the same pooled per scene. Which keys appear follows ``metrics``
(:func:`resolve_metrics`): by default all but VSD and AR, and those two when every test image has
a depth image. The BOP metrics are matched as BOP19 does (:func:`_bop_matches`): per target the
top ``inst_count`` estimates, greedily by score, each take the unmatched one of the
``inst_count`` most visible ground-truth instances with the smallest error below the threshold.

Conventions (BOP): per (scene, image, object) the top-scored ``inst_count`` estimates count
(ties: the earlier row); a target without an estimate is a failure (error inf); estimates that
match no target are ignored; thresholds are strict (<). When an object has several ground-truth
instances in an image, the estimates, in decreasing score, each take the still unmatched
instance with the smallest error (per metric); instances left over are failures. The instances
matched against are those at least 10% visible (scene_gt_info.json) when exactly ``inst_count``
are, else all instances of the object in the image.

Exactness. ADD and proj2d are computed exactly for every target (float32, redone in float64 near
the thresholds). ADD-S decisions are exact: the fast bounds of :mod:`~tdof20.scoring.metrics`
decide every target whose interval lies on one side of the threshold, finer bounds and then
KD-tree queries the rest. ADD-S *values* (for the AUCs and plots) are the cluster estimate plus
the mean of exact-minus-control residuals at random model points (a control variate, so the
corrected value is unbiased); the number of samples is chosen per object so that the standard
error of its AUC is <= 1.25e-4 (4 standard errors < 0.0005 < the 0.001 tolerance). Targets whose
interval straddles 100 mm, or whose ADD-S was computed exactly anyway, use the exact value.
"""

from __future__ import annotations

import json
import math
import os
import time as _time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop import MODELS_INFO, model_path, read_model_mesh, read_models_info
from tdof20.formats.io import read_json
from tdof20.scoring import metrics as M
from tdof20.dataset.results import ID_MAX, Results, check_against_dataset, read_results

ADD_THRESHOLD = 0.1  # fraction of the diameter
PROJ_THRESHOLD = 5.0  # pixels
PROJ_PLOT_MAX = 20.0  # pixels: the plots' range of 2D projection errors
AUC_MAX = 100.0  # mm
AUC_SE_TARGET = 1.25e-4  # standard error of each object's ADD-S AUC
VISIB_MIN = 0.1  # BOP: ground-truth instances less visible are no targets
KEYS = ("n", "add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s")
BOP_KEYS = ("ar_vsd", "ar_mssd", "ar_mspd", "ar")
METRICS = ("add", "proj", "vsd", "mssd", "mspd", "ar")  # what --metrics selects
METRIC_KEYS = {"add": ("add", "adds", "add_s", "auc_adds", "auc_add_s"), "proj": ("proj2d",), "vsd": ("ar_vsd",),
               "mssd": ("ar_mssd",), "mspd": ("ar_mspd",), "ar": ("ar",)}
ALL_KEYS = KEYS + BOP_KEYS
SPLITS = ("simple", "hard")
THREADS = min(2, os.cpu_count() or 1)  # objects scored in parallel


# =============================================================================================
# the dataset
# =============================================================================================
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


class DatasetView:
    """A dataset folder (tdof20's layout or BOP's standard one, read through
    :func:`tdof20.dataset.reader.open_dataset`) as scoring sees it: models_info read at once,
    models and scenes on demand. ``split``: a BOP dataset's split folder (default: the one
    test_targets_bop19.json belongs to); a tdof20 dataset's protocol is only used for messages."""

    def __init__(self, root: str | Path, split: str | None = None):
        from tdof20.dataset.reader import open_dataset

        self.dataset = open_dataset(root)  # the one "not a dataset" check
        self.root = self.dataset.root
        self.info = self.dataset.info
        self.folder: str | None = None
        if self.dataset.layout == "bop":
            self.folder = self.dataset.check_split(split if split is not None else self.dataset.targets_split())
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
        from tdof20.formats.io import read_png

        sc = self.scene(scene_id).depth_scale.get(im_id, 1.0)
        if isinstance(sc, bool) or not isinstance(sc, (int, float)) or not sc > 0:
            raise TdofError(f"image {im_id}: depth_scale must be a number > 0, got {sc!r}",
                            self.scene_dir(scene_id) / "scene_camera.json")
        d = read_png(self.depth_path(scene_id, im_id), kind="depth")
        return d.astype(np.float32) * np.float32(sc)

    def image_width(self, scene_id: int) -> int:
        """Image width in pixels (MSPD scales by 640 / width): ROOT/camera.json's ``width``, else
        the header of the scene's first rgb/ or depth/ PNG."""
        key = ("width", scene_id)
        if key not in self._extra:
            from tdof20.formats.io import png_header

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
                raise TdofError(f"MSPD needs the image width: camera.json has no 'width' and scene {scene_id} has no "
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
    """The targets file to score against: ``targets``, or those of ``split`` (tdof20:
    ROOT/test_targets_{split}.json; BOP, ``ds`` given: ROOT/test_targets_bop19.json of its test folder)."""
    bop = ds is not None and ds.dataset.layout == "bop"
    if (split is None) == (targets is None):
        raise TdofError("give exactly one of --split (" + ("a split folder such as test" if bop else "simple or hard")
                        + ") and --targets FILE")
    if targets is not None:
        return Path(targets)
    if bop:
        if split != ds.dataset.targets_split():
            raise TdofError(f"{ds.dataset.targets_path().name} holds the targets of the split folder "
                            f"{ds.dataset.targets_split()}/, not {split}/: score with --split "
                            f"{ds.dataset.targets_split()} or give --targets FILE", ds.root)
        return ds.dataset.targets_path()
    if split not in SPLITS:
        raise TdofError(f"unknown split {split!r} (use one of: {', '.join(SPLITS)})")
    return Path(dataset_root) / f"test_targets_{split}.json"


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
    from tdof20.dataset.build import empty_part_reason, split_images

    why = ""
    if ds.dataset.layout == "tdof20":
        try:
            has_test = bool(split_images(ds.root, split, "test"))
        except TdofError:
            has_test = False
        why = (f": its test images hold no object instance at least {VISIB_MIN:.0%} visible" if has_test
               else f": {empty_part_reason(ds.root, split, 'test')}")
    raise TdofError(f"no test targets in this file: the {split} split of the dataset has none to score{why}", tg.path)


# =============================================================================================
# evaluation
# =============================================================================================
@dataclass
class ObjectEval:
    """Per object: one entry per target instance (a target with inst_count k gives k entries).
    Errors are inf where there was no estimate. ``adds`` values are exact where ``adds_exact``
    and control-variate estimates elsewhere; the *_ok decisions are always exact. ``bop`` holds,
    per BOP metric computed, whether each instance is matched (BOP19 matching) at each threshold:
    'mssd' and 'mspd' (n,10), 'vsd' (n,10,10) (tau, threshold); ``scene`` each instance's scene."""

    obj_id: int
    diameter: float
    symmetric: bool
    add: np.ndarray
    adds: np.ndarray
    proj: np.ndarray
    add_ok: np.ndarray
    adds_ok: np.ndarray
    proj_ok: np.ndarray
    adds_exact: np.ndarray
    auc_se: float = 0.0
    stages: dict = field(default_factory=dict)
    scene: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    bop: dict = field(default_factory=dict)
    keys: tuple = KEYS

    @property
    def n(self) -> int:
        return len(self.add)

    @property
    def add_s(self) -> np.ndarray:
        return self.adds if self.symmetric else self.add

    @property
    def add_s_ok(self) -> np.ndarray:
        return self.adds_ok if self.symmetric else self.add_ok

    def values(self, mask: np.ndarray | None = None) -> dict[str, float]:
        """The summary values of the instances in ``mask`` (all by default)."""
        sel = slice(None) if mask is None else mask

        def auc(e):
            e = e[sel]
            return float(np.mean(np.maximum(0.0, 1.0 - e / AUC_MAX))) if len(e) else 0.0

        def acc(ok):
            ok = ok[sel]
            return float(np.mean(ok)) if len(ok) else 0.0

        def ar(name):
            ok = self.bop[name][sel]
            return float(ok.mean()) if ok.size else 0.0

        get = {"add": lambda: acc(self.add_ok), "adds": lambda: acc(self.adds_ok), "add_s": lambda: acc(self.add_s_ok),
               "proj2d": lambda: acc(self.proj_ok), "auc_adds": lambda: auc(self.adds),
               "auc_add_s": lambda: auc(self.add_s), "ar_vsd": lambda: ar("vsd"), "ar_mssd": lambda: ar("mssd"),
               "ar_mspd": lambda: ar("mspd")}
        out: dict[str, float] = {"n": int(np.count_nonzero(np.ones(self.n, bool)[sel]))}
        for k in self.keys[1:]:
            if k == "ar":
                out[k] = (ar("vsd") + ar("mssd") + ar("mspd")) / 3.0
            else:
                out[k] = get[k]()
        return out

    def summary(self) -> dict[str, float]:
        return self.values()


@dataclass
class Evaluation:
    method: str
    objects: dict[int, ObjectEval]
    warnings: list[str]
    timings: dict[str, float]
    n_rows: int = 0
    keys: tuple = KEYS  # "n" and the metric keys computed, in report order
    scene_labels: dict = field(default_factory=dict)  # scene id -> its name ("multi/08")
    object_labels: dict = field(default_factory=dict)  # obj_id -> the dataset's name for it

    def summary(self) -> dict[str, Any]:
        """{"objects": {"<obj_id>": {...}}, "mean": {...} (over objects), "all": {...} (pooled over
        target instances), "scenes": {"<scene_id>": {...}} (pooled over each scene's instances)}."""
        keys = self.keys
        objs = {str(k): v.summary() for k, v in sorted(self.objects.items())}
        per = [v for v in objs.values() if v["n"] > 0]
        mean = {k: (float(np.mean([o[k] for o in per])) if per else 0.0) for k in keys[1:]}
        mean = {"n": len(per), **mean}
        allv: dict[str, Any] = {"n": int(sum(o["n"] for o in per))}
        for k in keys[1:]:
            allv[k] = float(sum(o[k] * o["n"] for o in per) / allv["n"]) if allv["n"] else 0.0
        scenes = {}
        ids = sorted({int(x) for o in self.objects.values() for x in np.unique(o.scene)})
        for sid in ids:
            parts = [o.values(o.scene == sid) for o in self.objects.values()]
            parts = [p for p in parts if p["n"] > 0]
            n = sum(p["n"] for p in parts)
            scenes[str(sid)] = {"n": n, **{k: float(sum(p[k] * p["n"] for p in parts) / n) for k in keys[1:]}}
        out = {"objects": objs, "mean": mean, "all": allv, "scenes": scenes}
        return _rounded(out)


def _rounded(d: Any) -> Any:
    """Floats to 10 decimals (float32 kernels leave ~1e-12 noise: 0.99999999999 -> 1.0)."""
    if isinstance(d, dict):
        return {k: _rounded(v) for k, v in d.items()}
    return round(d, 10) if isinstance(d, float) else d


def _as_results(results: Any) -> Results:
    if isinstance(results, Results):
        return results
    if isinstance(results, (str, Path)):
        return read_results(results)
    return Results.from_rows(results)


def _group_rows(res: Results) -> dict[tuple[int, int, int], np.ndarray]:
    """(scene, image, object) -> row indices sorted by decreasing score (ties: file order)."""
    if len(res) == 0:
        return {}
    order = np.lexsort((res.line, -res.score, res.obj_id, res.im_id, res.scene_id))
    keys = np.stack([res.scene_id[order], res.im_id[order], res.obj_id[order]], axis=1)
    cut = np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [len(order)]])
    return {(int(keys[s, 0]), int(keys[s, 1]), int(keys[s, 2])): order[s:e] for s, e in zip(starts, ends)}


def _adds_values(model: M.ModelPoints, A: np.ndarray, b: np.ndarray, thr: float, add_ub: np.ndarray,
                 n_targets: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, dict]:
    """ADD-S of matched poses: (values, ok, exact mask, AUC standard error, stage counts)."""
    B = len(A)
    st = {"poses": B}
    if B == 0:
        return np.zeros(0), np.zeros(0, bool), np.zeros(0, bool), 0.0, st
    tic = _time.perf_counter()
    model.grid, model.coarse, model.fine  # noqa: B018  (precompute, timed apart)
    st["t_pre"] = _time.perf_counter() - tic
    tic = _time.perf_counter()
    bd = M.adds_cluster_bounds(model, A, b, "coarse")
    st["t_coarse"] = _time.perf_counter() - tic
    lo, hi = bd.lo, np.minimum(bd.hi, add_ub)  # ADD-S <= ADD
    est = np.full(B, np.nan)
    val = np.full(B, np.nan)
    exact = np.zeros(B, bool)

    def undecided():
        return (lo < thr) & (hi >= thr)

    # fine clusters: every pose that can contribute to the AUC (for its control variate) or is undecided
    need = (lo < AUC_MAX) | undecided()
    st["fine"] = int(need.sum())
    if need.any():
        tic = _time.perf_counter()
        f = M.adds_cluster_bounds(model, A[need], b[need], "fine")
        st["t_fine"] = _time.perf_counter() - tic
        lo[need] = np.maximum(lo[need], f.lo)
        hi[need] = np.minimum(hi[need], f.hi)
        est[need] = f.est
    u = undecided()
    st["points"] = int(u.sum())
    if u.any():
        tic = _time.perf_counter()
        p = M.adds_point_bounds(model, A[u], b[u])
        st["t_points"] = _time.perf_counter() - tic
        lo[u] = np.maximum(lo[u], p.lo)
        hi[u] = np.minimum(hi[u], p.hi)
    u = undecided()
    st["exact"] = int(u.sum())
    if u.any():
        tic = _time.perf_counter()
        d = M.adds_decide(model, A[u], b[u], thr)
        st["t_exact"] = _time.perf_counter() - tic
        lo[u] = np.maximum(lo[u], d.lo)
        hi[u] = np.minimum(hi[u], d.hi)
        full = np.flatnonzero(u)[d.lo == d.hi]
        val[full] = d.lo[d.lo == d.hi]
        exact[full] = True
        st["exact_full"] = int(len(full))
    ok = hi < thr  # exact: every pose is now decided
    # values: exact where known, 0-contribution beyond 100 mm, control-variate estimates elsewhere
    far = ~exact & (lo >= AUC_MAX)
    val[far] = np.maximum(lo[far], AUC_MAX)
    cv = np.flatnonzero(~exact & ~far)
    se = 0.0
    tic = _time.perf_counter()
    if len(cv):
        rng = np.random.default_rng(seed)
        m0 = 8
        R = M.adds_cv_residuals(model, A[cv], b[cv], "fine", m0, rng)
        sd = float(R.std())
        need_m = math.ceil((sd / (AUC_MAX * AUC_SE_TARGET)) ** 2 * len(cv) / max(1, n_targets) ** 2)
        if need_m * 4 >= model.n:  # sampling would cost about as much as the exact values
            val[cv] = M.adds_exact(model, A[cv], b[cv])
            exact[cv] = True
            st["cv_exact"] = int(len(cv))
        else:
            m = max(m0, need_m)
            if m > m0:
                R = np.concatenate([R, M.adds_cv_residuals(model, A[cv], b[cv], "fine", m - m0, rng)], axis=1)
                sd = float(R.std())
            val[cv] = np.clip(est[cv] + R.mean(axis=1), lo[cv], hi[cv])
            se = sd / math.sqrt(m) * math.sqrt(len(cv)) / max(1, n_targets) / AUC_MAX
            st["cv_samples"] = m
    st["t_cv"] = _time.perf_counter() - tic
    return val, ok, exact, se, st


def _evaluate_object(model: M.ModelPoints, obj_id: int, single: dict, multi: list, n_missing: int,
                     do_add: bool = True, do_proj: bool = True) -> ObjectEval:
    if not (do_add and do_proj):  # what is not asked for is not computed (nan; not reported)
        full = _evaluate_object(model, obj_id, single, multi, n_missing) if (do_add or do_proj) else None
        n = len(single["Re"]) + sum(g["count"] for g in multi) + n_missing
        nan, no = np.full(n, np.nan), np.zeros(n, bool)
        if full is None:
            return ObjectEval(obj_id, model.diameter, model.symmetric, nan, nan, nan, no, no, no, no)
        if not do_add:
            full.add, full.adds, full.add_ok, full.adds_ok = nan, nan, no, no
        if not do_proj:
            full.proj, full.proj_ok = nan, no
        return full
    thr = ADD_THRESHOLD * model.diameter
    Re, te, Rg, tg, K = (single[k] for k in ("Re", "te", "Rg", "tg", "K"))
    tic = _time.perf_counter()
    add_v, add_err = M.add_fast_with_error(model, Re, te, Rg, tg, thr)
    t_add = _time.perf_counter() - tic
    # 2D projection: rigorous bounds for all, the exact error where they straddle the threshold;
    # elsewhere an estimate for the plots (the mean over 512 fixed model points, kept inside the bounds)
    pb = M.proj2d_bounds(model, Re, te, Rg, tg, K)
    proj_v = np.maximum(pb.est, pb.lo)
    near = pb.lo < PROJ_PLOT_MAX
    if near.any():
        proj_v[near] = np.clip(M.proj2d_fast(model, Re[near], te[near], Rg[near], tg[near], K[near], sample=True),
                               pb.lo[near], pb.hi[near])
    amb = (pb.lo < PROJ_THRESHOLD) & (pb.hi >= PROJ_THRESHOLD)
    if amb.any():
        proj_v[amb] = M.proj2d_fast(model, Re[amb], te[amb], Rg[amb], tg[amb], K[amb], PROJ_THRESHOLD)
    proj_ok = proj_v < PROJ_THRESHOLD  # exact: decided by the bounds or by the exact error
    t_proj = _time.perf_counter() - tic - t_add
    A, b = M.relative_transform(Re, te, Rg, tg) if len(Re) else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    n_targets = len(Re) + n_missing + sum(g["count"] for g in multi)
    adds_v, adds_ok, adds_ex, se, stages = _adds_values(model, A, b, thr, add_v + add_err, n_targets, seed=obj_id)
    add_l, adds_l, proj_l = [add_v], [adds_v], [proj_v]
    add_okl, adds_okl, proj_okl, exl = [add_v < thr], [adds_ok], [proj_ok], [adds_ex]
    for g in multi:  # several instances: exact errors of every (estimate, instance) pair, greedy by score
        ests, gts, K1, count = g["ests"], g["gts"], g["K"], g["count"]
        errs = {k: np.full((len(ests), len(gts)), np.inf) for k in ("add", "adds", "proj")}
        for j, (R1, t1) in enumerate(gts):
            if ests:
                Rs = np.stack([e[0] for e in ests])
                ts = np.stack([e[1] for e in ests])
                Rj, tj = np.broadcast_to(R1, Rs.shape), np.broadcast_to(t1, ts.shape)
                errs["add"][:, j] = M.add_batch(Rs, ts, Rj, tj, model.pts)
                errs["adds"][:, j] = M.adds_batch(Rs, ts, Rj, tj, model.pts, model.tree)
                errs["proj"][:, j] = M.proj2d_batch(Rs, ts, Rj, tj, model.pts, K1)
        for k, out_v, out_ok, lim in (("add", add_l, add_okl, thr), ("adds", adds_l, adds_okl, thr),
                                      ("proj", proj_l, proj_okl, PROJ_THRESHOLD)):
            taken: set[int] = set()
            vals = []
            for i in range(len(ests)):
                free = [j for j in range(len(gts)) if j not in taken]
                if not free or len(vals) >= count:
                    break
                j = min(free, key=lambda jj: errs[k][i, jj])
                taken.add(j)
                vals.append(errs[k][i, j])
            vals += [np.inf] * (count - len(vals))
            v = np.asarray(vals, dtype=np.float64)
            out_v.append(v)
            out_ok.append(v < lim)
        exl.append(np.ones(count, bool))
    miss = np.full(n_missing, np.inf)
    add_l.append(miss)
    adds_l.append(miss)
    proj_l.append(miss)
    for lst in (add_okl, adds_okl, proj_okl):
        lst.append(np.zeros(n_missing, bool))
    exl.append(np.ones(n_missing, bool))
    stages["multi"] = len(multi)
    stages["t_add"], stages["t_proj"] = t_add, t_proj
    return ObjectEval(obj_id, model.diameter, model.symmetric, np.concatenate(add_l), np.concatenate(adds_l),
                      np.concatenate(proj_l), np.concatenate(add_okl), np.concatenate(adds_okl),
                      np.concatenate(proj_okl), np.concatenate(exl), se, stages)


def parse_metrics(spec: str | Any | None) -> tuple[str, ...] | None:
    """``"add,proj,vsd"`` (or a list of names) -> the names, checked; None stays None (the default)."""
    if spec is None:
        return None
    names = [x.strip().lower() for x in (spec.split(",") if isinstance(spec, str) else spec)]
    names = [x for x in names if x]
    bad = [x for x in names if x not in METRICS]
    if bad or not names:
        what = f"unknown metric {bad[0]!r}" if bad else "no metric given"
        raise TdofError(f"--metrics: {what} (choose from {', '.join(METRICS)}, comma-separated)")
    return tuple(dict.fromkeys(names))


def vsd_unavailable(ds: DatasetView, tg: Targets) -> str | None:
    """Why VSD cannot be computed on these targets (None when it can): every target image needs
    its depth/ PNG and every target object a triangle mesh."""
    for s, im in sorted(set(zip(tg.scene_id.tolist(), tg.im_id.tolist()))):
        p = ds.depth_path(s, im)
        if not p.exists():
            return f"{p} is missing (VSD needs the depth image of every test image)"
    for ob in sorted(set(tg.obj_id.tolist())):
        if ds.mesh_path(ob) is None:
            return f"object {ob} has no triangle mesh in models_eval/ or models/ to render"
    return None


def resolve_metrics(metrics: Any, ds: DatasetView, tg: Targets) -> tuple[tuple[str, ...], list[str]]:
    """(the summary keys to compute, notes). Default: ADD(-S), 2D projection, MSSD, MSPD, and VSD
    and AR when the dataset has depth for every test image (else a one-line note says why not).
    Asking for ``vsd`` or ``ar`` on a dataset without depth is an error naming what is missing."""
    names = parse_metrics(metrics)
    notes: list[str] = []
    if names is None:
        want = {"add", "proj", "mssd", "mspd"}
        why = vsd_unavailable(ds, tg) if len(tg) else None
        if why is None:
            want |= {"vsd", "ar"}
        else:
            notes.append(f"VSD not computed: {why}; AR (the mean of VSD, MSSD and MSPD) not reported either")
    else:
        want = set(names)
        if "ar" in want:
            want |= {"vsd", "mssd", "mspd"}
        if "vsd" in want and len(tg):
            why = vsd_unavailable(ds, tg)
            if why is not None:
                raise TdofError(f"--metrics {','.join(names)}: VSD cannot be computed: {why}")
    keys = ("n",) + tuple(k for k in ALL_KEYS[1:] if any(k in METRIC_KEYS[m] for m in want))
    return keys, notes


def evaluate(results: Any, dataset_root: str | Path, split: str | None = None,
             targets: str | Path | None = None, dataset: DatasetView | None = None,
             metrics: Any = None) -> Evaluation:
    """Everything :func:`score` computes, with the per-target errors (for reports and plots).
    ``metrics``: None (the default set, see :func:`resolve_metrics`) or names from
    :data:`METRICS` ("add,proj,vsd,mssd,mspd,ar" or a list)."""
    timings: dict[str, float] = {}
    t0 = _time.perf_counter()
    ds = dataset if dataset is not None else DatasetView(dataset_root, split)
    tpath = targets_path(ds.root, split, targets, ds)
    tg = load_targets(tpath, ds)
    require_targets(tg, ds, split)
    keys, notes = resolve_metrics(metrics, ds, tg)
    res = _as_results(results)
    timings["read"] = _time.perf_counter() - t0

    # checks against the dataset: ids, units
    dists = np.concatenate([np.linalg.norm(ds.scene(int(s)).t_all, axis=1) for s in np.unique(tg.scene_id)]) \
        if len(tg) else np.zeros(0)
    check_against_dataset(res, ds.scene_ids, lambda s: set(ds.scene(s).K), ds.obj_ids,
                          float(np.median(dists)) if len(dists) else None)
    warnings = list(res.warnings) + notes
    do_bop = any(k in keys for k in BOP_KEYS)

    # matching (ADD, ADD-S, 2D projection); per object the instances are ordered singles, multis, missing
    groups = _group_rows(res)
    per_obj: dict[int, dict] = {}
    where: list[tuple] = []  # per target: (obj, kind, index within kind, scene, im, count, rows)
    used = 0
    for s, im, ob, cnt in zip(tg.scene_id.tolist(), tg.im_id.tolist(), tg.obj_id.tolist(), tg.inst_count.tolist()):
        po = per_obj.setdefault(ob, {"single": [], "multi": [], "missing": 0, "missing_scenes": []})
        scene = ds.scene(s)
        gts = [(R, t) for o, R, t in scene.gt[im] if o == ob]
        rows = groups.get((s, im, ob))
        if rows is None:
            po["missing"] += cnt
            po["missing_scenes"] += [s] * cnt
            continue
        used += len(rows)
        if cnt == 1 and len(gts) == 1:
            where.append((ob, 0, len(po["single"]), s, im, cnt, rows[:cnt]))
            po["single"].append((int(rows[0]), gts[0][0], gts[0][1], scene.K[im], s))
        else:
            where.append((ob, 1, len(po["multi"]), s, im, cnt, rows[:cnt]))
            gts = ds.valid_instances(s, im, ob, cnt)
            top = rows[:cnt]
            po["multi"].append({"ests": [(res.R[r], res.t[r]) for r in top], "gts": gts, "K": scene.K[im],
                                "count": cnt, "scene": s})
    n_ignored = len(res) - used
    n_missing = sum(p["missing"] for p in per_obj.values())
    if n_missing:
        warnings.append(f"{n_missing} of {int(tg.inst_count.sum())} targets have no estimate (counted as failures)")
    if n_ignored:
        warnings.append(f"{n_ignored} row(s) match no target of {tpath.name} (ignored)")
    timings["match"] = _time.perf_counter() - t0 - timings["read"]
    do_add = any(k in keys for k in METRIC_KEYS["add"])
    do_proj = "proj2d" in keys

    def job(ob: int) -> ObjectEval:
        po = per_obj[ob]
        model = ds.model(ob)
        sg = po["single"]
        idx = np.array([x[0] for x in sg], dtype=np.int64)
        single = {"Re": res.R[idx], "te": res.t[idx],
                  "Rg": np.array([x[1] for x in sg]).reshape(-1, 3, 3),
                  "tg": np.array([x[2] for x in sg]).reshape(-1, 3),
                  "K": np.array([x[3] for x in sg]).reshape(-1, 3, 3)}
        ev = _evaluate_object(model, ob, single, po["multi"], po["missing"], do_add, do_proj)
        ev.scene = np.array([x[4] for x in sg] + [g["scene"] for g in po["multi"] for _ in range(g["count"])]
                            + po["missing_scenes"], dtype=np.int64)
        ev.keys = keys
        return ev

    # objects in parallel threads (numpy and the KD-tree release the GIL); largest first
    order = sorted(per_obj, key=lambda o: -len(per_obj[o]["single"]))
    with ThreadPoolExecutor(max_workers=max(1, min(THREADS, len(order)))) as pool:
        done = dict(zip(order, pool.map(job, order)))
    objects = {ob: done[ob] for ob in sorted(done)}
    timings["metrics"] = _time.perf_counter() - t0 - timings["read"] - timings["match"]
    if do_bop:
        tic = _time.perf_counter()
        slots = {}
        for ob, po in per_obj.items():
            n1 = len(po["single"])
            starts = np.cumsum([0] + [g["count"] for g in po["multi"]])
            slots[ob] = (n1, starts)
        recs = []
        for ob, kind, k, s, im, cnt, rows in where:
            n1, starts = slots[ob]
            recs.append((ob, s, im, cnt, rows, k if kind == 0 else n1 + int(starts[k])))
        bop = _bop_matches(recs, res, ds, keys, {ob: o.n for ob, o in objects.items()}, timings)
        for ob, o in objects.items():
            o.bop = bop[ob]
        timings["bop"] = _time.perf_counter() - tic
    timings["total"] = _time.perf_counter() - t0
    labels = {int(sid): ds.scene_label(int(sid)) for sid in np.unique(tg.scene_id)}
    names = {int(ob): ds.object_name(int(ob)) for ob in objects}
    return Evaluation(res.name, objects, warnings, timings, len(res), keys, labels, names)


# ---------------------------------------------------------------------------------------------
# BOP19: VSD, MSSD, MSPD errors and their matching
# ---------------------------------------------------------------------------------------------
def _greedy_count(E: np.ndarray, th: float) -> int:
    """BOP19 matching of one (image, object): the estimates (rows of E, by decreasing score) each
    take the unmatched ground-truth instance (column) with the smallest error below ``th``
    (strict; ties: the first). Returns the number matched."""
    taken = np.zeros(E.shape[1], bool)
    m = 0
    for row in E:
        cand = ~taken & (row < th)
        if cand.any():
            taken[int(np.argmin(np.where(cand, row, np.inf)))] = True
            m += 1
    return m


def _bop_matches(recs: list, res: Results, ds: DatasetView, keys: tuple, sizes: dict, timings: dict) -> dict:
    """Per object {"vsd": (n,10,10), "mssd": (n,10), "mspd": (n,10)} bool: instance matched at
    each (tau and) threshold. ``recs``: per target with estimates (obj, scene, im, count, its top
    ``count`` rows, first instance slot)."""
    want = {m for m in ("vsd", "mssd", "mspd") if ("ar_" + m) in keys or "ar" in keys}
    nT = len(M.MSSD_THRESHOLDS)
    out = {ob: {"vsd": np.zeros((n, len(M.VSD_TAUS), len(M.VSD_THRESHOLDS)), bool) if "vsd" in want else None,
                "mssd": np.zeros((n, nT), bool) if "mssd" in want else None,
                "mspd": np.zeros((n, len(M.MSPD_THRESHOLDS)), bool) if "mspd" in want else None}
           for ob, n in sizes.items()}
    for ob in out:
        out[ob] = {k: v for k, v in out[ob].items() if v is not None}
    # every (estimate, valid ground truth) pair of every target
    p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, p_exact = [], [], [], [], [], [], [], []
    blocks = []  # per target: (obj, first pair, n_est, n_gt, slot)
    for ob, s, im, cnt, rows, slot in recs:
        gts = ds.bop_instances(s, im, ob, cnt)
        K = ds.scene(s).K[im]
        blocks.append((ob, len(p_obj), len(rows), len(gts), slot, cnt))
        for r in rows:
            for _, R, t in gts:
                p_obj.append(ob)
                p_scene.append(s)
                p_im.append(im)
                p_row.append(int(r))
                p_R.append(R)
                p_t.append(t)
                p_K.append(K)
                p_exact.append(cnt > 1 or len(gts) > 1)
    n = len(p_obj)
    if n == 0:
        return out
    p_obj, p_scene, p_im, p_row = (np.asarray(x, np.int64) for x in (p_obj, p_scene, p_im, p_row))
    p_R, p_t, p_K = np.asarray(p_R).reshape(-1, 3, 3), np.asarray(p_t).reshape(-1, 3), np.asarray(p_K).reshape(-1, 3, 3)
    p_exact = np.asarray(p_exact, bool)
    errs: dict[str, np.ndarray] = {}
    # MSSD and MSPD per object: exact values where several instances are matched, elsewhere
    # intervals narrowed until they lie in one threshold bin (the decisions are then exact)
    mssd_e = np.full(n, np.inf)
    mspd_e = np.full(n, np.inf)

    def job(ob: int) -> None:
        idx = np.flatnonzero(p_obj == ob)
        model = ds.model(ob)
        Re, te = res.R[p_row[idx]], res.t[p_row[idx]]
        Rg, tgt, K = p_R[idx], p_t[idx], p_K[idx]
        ex = p_exact[idx]
        d = model.diameter
        if "mssd" in want:
            th = M.MSSD_THRESHOLDS
            cut = th[-1] * d * (1 + 1e-9) + 1e-9
            binof = lambda x, b: np.searchsorted(th, x / d, side="right")  # noqa: E731
            v = np.empty(len(idx))
            for sel, bf in ((~ex, binof), (ex, None)):
                if sel.any():
                    v[sel] = M.mssd_fast(model, Re[sel], te[sel], Rg[sel], tgt[sel], cut, bf).lo
            mssd_e[idx] = v / d
        if "mspd" in want:
            th = M.MSPD_THRESHOLDS
            fac = np.array([M.MSPD_WIDTH / ds.image_width(int(sc)) for sc in p_scene[idx]])
            v = np.empty(len(idx))
            for sel, by_bin in ((~ex, True), (ex, False)):
                if sel.any():
                    f = fac[sel]
                    cut = float(th[-1] / f.min()) * (1 + 1e-9) + 1e-9
                    bf = (lambda x, b, f=f: np.searchsorted(th, x * f[b], side="right")) if by_bin else None
                    v[sel] = M.mspd_fast(model, Re[sel], te[sel], Rg[sel], tgt[sel], K[sel], cut, bf).lo * f
            mspd_e[idx] = v

    tic = _time.perf_counter()
    objs = sorted(set(p_obj.tolist()), key=lambda o: -int((p_obj == o).sum()))
    with ThreadPoolExecutor(max_workers=max(1, min(THREADS, len(objs)))) as pool:
        list(pool.map(job, objs))
    timings["mssd_mspd"] = _time.perf_counter() - tic
    errs["mssd"], errs["mspd"] = mssd_e, mspd_e
    if "vsd" in want:
        tic = _time.perf_counter()
        errs["vsd"] = _vsd_errors(ds, res, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings)
        timings["vsd"] = _time.perf_counter() - tic
    # matching: single targets at once, several instances greedily (BOP19)
    ths = {"mssd": M.MSSD_THRESHOLDS, "mspd": M.MSPD_THRESHOLDS, "vsd": M.VSD_THRESHOLDS}
    blocks_a = np.array([b[:5] for b in blocks], dtype=np.int64).reshape(-1, 5)
    one = (blocks_a[:, 2] == 1) & (blocks_a[:, 3] == 1) & (np.array([b[5] for b in blocks]) == 1)
    for m in want:
        th = ths[m]
        E = errs[m]
        for ob in np.unique(blocks_a[one, 0]):
            sel = one & (blocks_a[:, 0] == ob)
            pi, slot = blocks_a[sel, 1], blocks_a[sel, 4]
            out[int(ob)][m][slot] = E[pi][..., None] < th
        for k in np.flatnonzero(~one):
            ob, p0, ne, ng, slot = (int(x) for x in blocks_a[k])
            blk = E[p0:p0 + ne * ng]
            if m == "vsd":
                blk = blk.reshape(ne, ng, -1)
                for ti in range(blk.shape[2]):
                    for j, t in enumerate(th):
                        out[ob][m][slot:slot + _greedy_count(blk[:, :, ti], t), ti, j] = True
            else:
                blk = blk.reshape(ne, ng)
                for j, t in enumerate(th):
                    out[ob][m][slot:slot + _greedy_count(blk, t), j] = True
    return out


def _vsd_errors(ds: DatasetView, res: Results, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings,
                chunk: int = 32) -> np.ndarray:
    """VSD (n, 10 taus) of every pair, image by image: chunks of ``chunk`` test depths, the next
    chunk read by a thread while this one is scored (open3d's ray casting uses every core)."""
    n = len(p_obj)
    out = np.ones((n, len(M.VSD_TAUS)))
    key = p_scene * (1 << 32) + p_im
    order = np.argsort(key, kind="stable")
    ims, first = np.unique(key[order], return_index=True)
    bounds = np.r_[first, n]
    chunks = [range(i, min(len(ims), i + chunk)) for i in range(0, len(ims), chunk)]
    t_read = [0.0]

    def load(ch):
        tic = _time.perf_counter()
        imgs = [ds.depth_mm(int(ims[i] >> 32), int(ims[i] & 0xFFFFFFFF)) for i in ch]
        t_read[0] += _time.perf_counter() - tic
        return imgs

    t_wait = 0.0
    with ThreadPoolExecutor(max_workers=1) as reader:
        nxt = reader.submit(load, chunks[0]) if chunks else None
        for ci, ch in enumerate(chunks):
            tic = _time.perf_counter()
            imgs = nxt.result()
            t_wait += _time.perf_counter() - tic
            nxt = reader.submit(load, chunks[ci + 1]) if ci + 1 < len(chunks) else None
            for shp in {im.shape for im in imgs}:  # one image size per stack
                local = [k for k, im in enumerate(imgs) if im.shape == shp]
                stack = np.stack([imgs[k] for k in local])
                sel = np.concatenate([order[bounds[ch[k]]:bounds[ch[k] + 1]] for k in local])
                img_of = np.concatenate([np.full(bounds[ch[k] + 1] - bounds[ch[k]], j) for j, k in enumerate(local)])
                for ob in np.unique(p_obj[sel]):
                    m = p_obj[sel] == ob
                    idx = sel[m]
                    r = p_row[idx]
                    out[idx] = M.vsd_batch(ds.renderer(int(ob)), res.R[r], res.t[r], p_R[idx], p_t[idx], p_K[idx],
                                           stack, img_of[m], ds.model(int(ob)).diameter)
    timings["depth_read"] = t_read[0]
    timings["depth_wait"] = t_wait
    return out


def score(results: Any, dataset_root: str | Path, split: str | None = None,
          targets: str | Path | None = None, metrics: Any = None) -> dict[str, Any]:
    """Score ``results`` (a BOP results CSV path, a :class:`Results`, or a list of
    (scene_id, im_id, obj_id, score, R, t, time) rows) on the dataset at ``dataset_root`` with the
    targets of ``split`` ('simple' | 'hard': ROOT/test_targets_{split}.json) or the ``targets``
    file. ``metrics``: None (the default set) or names of :data:`METRICS`. Returns
    {"objects": {"<obj_id>": {...}}, "mean": {...}, "all": {...}, "scenes": {"<scene_id>": {...}}}
    (see the module docstring); accuracies, AUCs and average recalls are fractions in [0, 1]."""
    return evaluate(results, dataset_root, split, targets, metrics=metrics).summary()


__all__ = ["ADD_THRESHOLD", "PROJ_THRESHOLD", "AUC_MAX", "KEYS", "BOP_KEYS", "METRICS", "DatasetView", "Targets",
           "ObjectEval", "Evaluation", "load_targets", "require_targets", "targets_path", "parse_metrics",
           "resolve_metrics", "vsd_unavailable", "evaluate", "score"]


def run_info(results_csv: str | Path) -> dict | None:
    """What ``tdof20 predict`` wrote beside a results file (``<stem>_info.json``: method, its config,
    input, depth mode, masks, timings), or None for results from elsewhere. ``oracle_masks`` is
    added: True when the poses were recovered on ground-truth masks (``masks == "gt"``), which
    every score made from them must say."""
    from tdof20.formats import read_json

    p = Path(results_csv)
    side = p.with_name(p.stem + "_info.json")
    if not side.is_file():
        return None
    info = read_json(side)
    if not isinstance(info, dict):
        raise TdofError(f"must hold a JSON object, got {type(info).__name__}", side)
    keep = ("method", "input", "depth_mode", "masks", "method_config", "run", "split")
    out = {k: info[k] for k in keep if k in info}
    out["oracle_masks"] = info.get("masks") == "gt"
    return out


def run_line(name: str, info: dict) -> str:
    """One line naming how a results file was made (for the scorer's output)."""
    cfg = json.dumps(info.get("method_config", {}), sort_keys=True)
    oracle = "  ORACLE MASKS (ground-truth segmentation)" if info.get("oracle_masks") else ""
    return (f"{name}: method {info.get('method', '?')} ({info.get('input', '?')}), depth {info.get('depth_mode', '?')}, "
            f"masks {info.get('masks', '-')}{oracle}, config {cfg}")


def score_command(results: list[Path], dataset: Path, split: str | None, targets: Path | None,
                  json_out: Path | None, plots: Path | None, metrics: str | None = None) -> str:
    """``tdof20 benchmark score RESULTS.csv... --dataset ROOT (--split S | --targets F) [--json OUT]
    [--plots DIR] [--metrics add,proj,vsd,mssd,mspd,ar]``: score each results file, write the JSON
    (one file: its summary; several: {"<method>": summary, ...}) and the plots plus ``report.md``
    (Markdown tables) in DIR, and return the text to print: Tables 1-3 (those computed), every
    metric per method and per scene, warnings and timings."""
    from tdof20.scoring import report
    from tdof20.formats.io import atomic_write_bytes, check_output_dir, check_output_file, write_json

    if not results:
        raise TdofError("give at least one results file")
    parse_metrics(metrics)  # a bad --metrics is refused before anything is read
    if json_out is not None:
        check_output_file(json_out, "--json", "JSON file")
    if plots is not None:
        check_output_dir(plots, "--plots", "folder for the plots and report.md")
    ds = DatasetView(dataset, split)
    tpath = targets_path(ds.root, split, targets, ds)
    evals = [evaluate(r, ds.root, split, targets, dataset=ds, metrics=metrics) for r in results]
    names = report.method_names(evals)
    n_targets = max((e.summary()["all"]["n"] for e in evals), default=0)
    head = f"dataset {ds.root}  targets {tpath.name} ({n_targets} target instances)"
    parts = [head, "", report.report_text(evals)]
    notes = []
    infos = [run_info(r) for r in results]
    for name, info in zip(names, infos):
        if info is not None:
            notes.append(run_line(name, info))
    for name, ev in zip(names, evals):
        for w in ev.warnings:
            notes.append(f"{'note' if w.startswith('VSD not computed') else 'warning'}: {name}: {w}")
        t = ev.timings
        bop = f", BOP metrics {t['bop']:.2f} s" if "bop" in t else ""
        notes.append(f"{name}: {ev.n_rows} rows scored in {t['total']:.2f} s (read {t['read']:.2f} s, "
                     f"metrics {t['metrics']:.2f} s{bop})")
    if json_out is not None:
        summaries = [dict(e.summary(), **({"run": i} if i is not None else {})) for e, i in zip(evals, infos)]
        content = summaries[0] if len(evals) == 1 else dict(zip(names, summaries))
        write_json(json_out, content)
        notes.append(f"wrote {json_out}")
    if plots is not None:
        paths = report.write_plots(evals, plots)
        md = Path(plots) / "report.md"
        runs = "".join(f"- {run_line(n, i)}\n" for n, i in zip(names, infos) if i is not None)
        atomic_write_bytes(md, (f"{head}\n\n" + (runs + "\n" if runs else "") + report.report_markdown(evals)).encode())
        notes.append("wrote " + ", ".join(str(p) for p in paths + [md]))
    return "\n".join(parts + [""] + notes)


__all__ += ["score_command", "run_info", "run_line"]
