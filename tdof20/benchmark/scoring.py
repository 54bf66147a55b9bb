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

Conventions (BOP): per (scene, image, object) the top-scored ``inst_count`` estimates count
(ties: the earlier row); a target without an estimate is a failure (error inf); estimates that
match no target are ignored; thresholds are strict (<). When an object has several ground-truth
instances in an image, the estimates, in decreasing score, each take the still unmatched
instance with the smallest error (per metric); instances left over are failures. The instances
matched against are those at least 10% visible (scene_gt_info.json) when exactly ``inst_count``
are, else all instances of the object in the image.

Exactness. ADD and proj2d are computed exactly for every target (float32, redone in float64 near
the thresholds). ADD-S decisions are exact: the fast bounds of :mod:`~tdof20.benchmark.metrics`
decide every target whose interval lies on one side of the threshold, finer bounds and then
KD-tree queries the rest. ADD-S *values* (for the AUCs and plots) are the cluster estimate plus
the mean of exact-minus-control residuals at random model points (a control variate, so the
corrected value is unbiased); the number of samples is chosen per object so that the standard
error of its AUC is <= 1.25e-4 (4 standard errors < 0.0005 < the 0.001 tolerance). Targets whose
interval straddles 100 mm, or whose ADD-S was computed exactly anyway, use the exact value.
"""

from __future__ import annotations

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
from tdof20.benchmark import metrics as M
from tdof20.benchmark.results import ID_MAX, Results, check_against_dataset, read_results

ADD_THRESHOLD = 0.1  # fraction of the diameter
PROJ_THRESHOLD = 5.0  # pixels
PROJ_PLOT_MAX = 20.0  # pixels: the plots' range of 2D projection errors
AUC_MAX = 100.0  # mm
AUC_SE_TARGET = 1.25e-4  # standard error of each object's ADD-S AUC
VISIB_MIN = 0.1  # BOP: ground-truth instances less visible are no targets
KEYS = ("n", "add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s")
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
    gtd: dict[int, list] = {int(k): [] for k in gt}
    for j, (i, _) in enumerate(where):
        if i not in Kd:
            raise TdofError(f"image {i} has ground truth but no camera entry", gpath)
        gtd[i].append((objs[j], R[j], t[j]))
    return SceneData(Kd, gtd, t)


class DatasetView:
    """A tdof20 dataset folder as scoring sees it (models_info read at once; models and scenes
    on demand)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise TdofError("no such dataset folder", self.root)
        info_path = self.root / "dataset_info.json"
        self.info = read_json(info_path) if info_path.exists() else {}
        if not isinstance(self.info, dict):
            raise TdofError("must hold a JSON object", info_path)
        self.scene_names: dict[int, str] = {}
        for k, v in (self.info.get("scenes") or {}).items():
            try:
                self.scene_names[int(k)] = str(v)
            except ValueError:
                raise TdofError(f"scene key {k!r} is not an integer id", info_path) from None
        scenes_dir = self.root / "scenes"
        on_disk = {int(p.name) for p in scenes_dir.iterdir() if p.is_dir() and p.name.isdigit()} \
            if scenes_dir.is_dir() else set()
        self.scene_ids = set(self.scene_names) | on_disk
        self._scenes: dict[int, SceneData] = {}
        self._extra: dict[Any, Any] = {}
        self.models_dir = self.root / "models_eval" if (self.root / "models_eval").is_dir() else self.root / "models"
        info_file = self.models_dir / MODELS_INFO
        if not info_file.exists():
            info_file = self.root / "models" / MODELS_INFO
        self.models_info = read_models_info(info_file)
        self.models: dict[int, M.ModelPoints] = {}

    def model(self, obj_id: int) -> M.ModelPoints:
        if obj_id not in self.models:
            e = self.models_info[obj_id]
            sym = bool(e.get("symmetries_continuous")) or bool(e.get("symmetries_discrete"))
            pts = read_model_mesh(model_path(self.models_dir, obj_id), need_faces=False)[0]
            self.models[obj_id] = M.ModelPoints(pts, float(e["diameter"]), sym)
        return self.models[obj_id]

    @property
    def obj_ids(self) -> set[int]:
        return set(self.models_info)

    def scene(self, scene_id: int) -> SceneData:
        if scene_id not in self._scenes:
            self._scenes[scene_id] = _scene_data(self.root / "scenes" / f"{scene_id:06d}")
        return self._scenes[scene_id]

    def visib(self, scene_id: int) -> dict[int, list[float]] | None:
        """visib_fract per image and instance from scene_gt_info.json (None when absent)."""
        key = ("visib", scene_id)
        if key not in self._extra:
            path = self.root / "scenes" / f"{scene_id:06d}" / "scene_gt_info.json"
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
        return self.scene_names.get(scene_id, str(scene_id))


@dataclass
class Targets:
    path: Path
    scene_id: np.ndarray
    im_id: np.ndarray
    obj_id: np.ndarray
    inst_count: np.ndarray

    def __len__(self) -> int:
        return len(self.scene_id)


def targets_path(dataset_root: str | Path, split: str | None, targets: str | Path | None) -> Path:
    if (split is None) == (targets is None):
        raise TdofError("give exactly one of --split (simple or hard) and --targets FILE")
    if targets is not None:
        return Path(targets)
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
    from tdof20.benchmark.dataset import empty_part_reason, split_images

    why = ""
    if (ds.root / "dataset_info.json").exists():
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
    and control-variate estimates elsewhere; the *_ok decisions are always exact."""

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

    @property
    def n(self) -> int:
        return len(self.add)

    @property
    def add_s(self) -> np.ndarray:
        return self.adds if self.symmetric else self.add

    @property
    def add_s_ok(self) -> np.ndarray:
        return self.adds_ok if self.symmetric else self.add_ok

    def summary(self) -> dict[str, float]:
        def auc(e):
            return float(np.mean(np.maximum(0.0, 1.0 - e / AUC_MAX))) if len(e) else 0.0

        def acc(ok):
            return float(np.mean(ok)) if len(ok) else 0.0

        return {"n": self.n, "add": acc(self.add_ok), "adds": acc(self.adds_ok), "add_s": acc(self.add_s_ok),
                "proj2d": acc(self.proj_ok), "auc_adds": auc(self.adds), "auc_add_s": auc(self.add_s)}


@dataclass
class Evaluation:
    method: str
    objects: dict[int, ObjectEval]
    warnings: list[str]
    timings: dict[str, float]
    n_rows: int = 0

    def summary(self) -> dict[str, Any]:
        objs = {str(k): v.summary() for k, v in sorted(self.objects.items())}
        per = [v for v in objs.values() if v["n"] > 0]
        mean = {k: (float(np.mean([o[k] for o in per])) if per else 0.0) for k in KEYS[1:]}
        mean = {"n": len(per), **mean}
        allv: dict[str, Any] = {"n": int(sum(o["n"] for o in per))}
        for k in KEYS[1:]:
            allv[k] = float(sum(o[k] * o["n"] for o in per) / allv["n"]) if allv["n"] else 0.0
        out = {"objects": objs, "mean": mean, "all": allv}
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
                     ) -> ObjectEval:
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


def evaluate(results: Any, dataset_root: str | Path, split: str | None = None,
             targets: str | Path | None = None, dataset: DatasetView | None = None) -> Evaluation:
    """Everything :func:`score` computes, with the per-target errors (for reports and plots)."""
    timings: dict[str, float] = {}
    t0 = _time.perf_counter()
    ds = dataset if dataset is not None else DatasetView(dataset_root)
    tpath = targets_path(ds.root, split, targets)
    tg = load_targets(tpath, ds)
    require_targets(tg, ds, split)
    res = _as_results(results)
    timings["read"] = _time.perf_counter() - t0

    # checks against the dataset: ids, units
    dists = np.concatenate([np.linalg.norm(ds.scene(int(s)).t_all, axis=1) for s in np.unique(tg.scene_id)]) \
        if len(tg) else np.zeros(0)
    check_against_dataset(res, ds.scene_ids, lambda s: set(ds.scene(s).K), ds.obj_ids,
                          float(np.median(dists)) if len(dists) else None)
    warnings = list(res.warnings)

    # matching
    groups = _group_rows(res)
    per_obj: dict[int, dict] = {}
    used = 0
    for s, im, ob, cnt in zip(tg.scene_id.tolist(), tg.im_id.tolist(), tg.obj_id.tolist(), tg.inst_count.tolist()):
        po = per_obj.setdefault(ob, {"single": [], "multi": [], "missing": 0})
        scene = ds.scene(s)
        gts = [(R, t) for o, R, t in scene.gt[im] if o == ob]
        rows = groups.get((s, im, ob))
        if rows is None:
            po["missing"] += cnt
            continue
        used += len(rows)
        if cnt == 1 and len(gts) == 1:
            po["single"].append((int(rows[0]), gts[0][0], gts[0][1], scene.K[im]))
        else:
            gts = ds.valid_instances(s, im, ob, cnt)
            top = rows[:cnt]
            po["multi"].append({"ests": [(res.R[r], res.t[r]) for r in top], "gts": gts, "K": scene.K[im],
                                "count": cnt})
    n_ignored = len(res) - used
    n_missing = sum(p["missing"] for p in per_obj.values())
    if n_missing:
        warnings.append(f"{n_missing} of {int(tg.inst_count.sum())} targets have no estimate (counted as failures)")
    if n_ignored:
        warnings.append(f"{n_ignored} row(s) match no target of {tpath.name} (ignored)")
    timings["match"] = _time.perf_counter() - t0 - timings["read"]

    def job(ob: int) -> ObjectEval:
        po = per_obj[ob]
        model = ds.model(ob)
        sg = po["single"]
        idx = np.array([x[0] for x in sg], dtype=np.int64)
        single = {"Re": res.R[idx], "te": res.t[idx],
                  "Rg": np.array([x[1] for x in sg]).reshape(-1, 3, 3),
                  "tg": np.array([x[2] for x in sg]).reshape(-1, 3),
                  "K": np.array([x[3] for x in sg]).reshape(-1, 3, 3)}
        return _evaluate_object(model, ob, single, po["multi"], po["missing"])

    # objects in parallel threads (numpy and the KD-tree release the GIL); largest first
    order = sorted(per_obj, key=lambda o: -len(per_obj[o]["single"]))
    with ThreadPoolExecutor(max_workers=max(1, min(THREADS, len(order)))) as pool:
        done = dict(zip(order, pool.map(job, order)))
    objects = {ob: done[ob] for ob in sorted(done)}
    timings["metrics"] = _time.perf_counter() - t0 - timings["read"] - timings["match"]
    timings["total"] = _time.perf_counter() - t0
    return Evaluation(res.name, objects, warnings, timings, len(res))


def score(results: Any, dataset_root: str | Path, split: str | None = None,
          targets: str | Path | None = None) -> dict[str, Any]:
    """Score ``results`` (a BOP results CSV path, a :class:`Results`, or a list of
    (scene_id, im_id, obj_id, score, R, t, time) rows) on the dataset at ``dataset_root`` with the
    targets of ``split`` ('simple' | 'hard': ROOT/test_targets_{split}.json) or the ``targets``
    file. Returns {"objects": {"<obj_id>": {...}}, "mean": {...}, "all": {...}} (see the module
    docstring); accuracies and AUCs are fractions in [0, 1]."""
    return evaluate(results, dataset_root, split, targets).summary()


__all__ = ["ADD_THRESHOLD", "PROJ_THRESHOLD", "AUC_MAX", "KEYS", "DatasetView", "Targets", "ObjectEval",
           "Evaluation", "load_targets", "require_targets", "targets_path", "evaluate", "score"]


def score_command(results: list[Path], dataset: Path, split: str | None, targets: Path | None,
                  json_out: Path | None, plots: Path | None) -> str:
    """``tdof20 benchmark score RESULTS.csv... --dataset ROOT (--split S | --targets F) [--json OUT]
    [--plots DIR]``: score each results file, write the JSON (one file: its summary; several:
    {"<method>": summary, ...}) and the plots plus ``report.md`` (Markdown tables) in DIR, and
    return the text to print: Tables 1-2, every metric per method, warnings and timings."""
    from tdof20.benchmark import report
    from tdof20.formats.io import atomic_write_bytes, check_output_dir, check_output_file, write_json

    if not results:
        raise TdofError("give at least one results file")
    if json_out is not None:
        check_output_file(json_out, "--json", "JSON file")
    if plots is not None:
        check_output_dir(plots, "--plots", "folder for the plots and report.md")
    ds = DatasetView(dataset)
    tpath = targets_path(ds.root, split, targets)
    evals = [evaluate(r, ds.root, split, targets, dataset=ds) for r in results]
    names = report.method_names(evals)
    n_targets = max((e.summary()["all"]["n"] for e in evals), default=0)
    head = f"dataset {ds.root}  targets {tpath.name} ({n_targets} target instances)"
    parts = [head, "", report.report_text(evals)]
    notes = []
    for name, ev in zip(names, evals):
        for w in ev.warnings:
            notes.append(f"warning: {name}: {w}")
        t = ev.timings
        notes.append(f"{name}: {ev.n_rows} rows scored in {t['total']:.2f} s (read {t['read']:.2f} s, "
                     f"metrics {t['metrics']:.2f} s)")
    if json_out is not None:
        content = evals[0].summary() if len(evals) == 1 else {n: e.summary() for n, e in zip(names, evals)}
        write_json(json_out, content)
        notes.append(f"wrote {json_out}")
    if plots is not None:
        paths = report.write_plots(evals, plots)
        md = Path(plots) / "report.md"
        atomic_write_bytes(md, (f"{head}\n\n" + report.report_markdown(evals)).encode())
        notes.append("wrote " + ", ".join(str(p) for p in paths + [md]))
    return "\n".join(parts + [""] + notes)


__all__.append("score_command")
