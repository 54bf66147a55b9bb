"""The scorer: a results file matched to the test targets and every metric computed, exactly and
fast (:func:`evaluate`; :func:`tdof20.scoring.scoring.score` summarises it).

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

import math
import time as _time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.dataset.results import Results, check_against_dataset, read_results, read_top_results
from tdof20.errors import TdofError
from tdof20.scoring import metrics as M
from tdof20.scoring.bop19 import bop_matches
from tdof20.scoring.vsd_cache import GtCache
from tdof20.scoring.dataset_view import DatasetView, Targets, load_targets, require_targets, targets_path
from tdof20.scoring.evaluation import (ADD_THRESHOLD, ALL_KEYS, AUC_MAX, AUC_SE_TARGET, BOP_KEYS, METRIC_KEYS, METRICS,
                                       PROJ_PLOT_MAX, PROJ_THRESHOLD, THREADS, Evaluation, ObjectEval, proj_threshold)


def _as_results(results: Any) -> Results:
    if isinstance(results, Results):
        return results
    if isinstance(results, (str, Path)):
        return read_results(results)
    return Results.from_rows(results)


def group_rows(res: Results) -> dict[tuple[int, int, int], np.ndarray]:
    """(scene, image, object) -> row indices sorted by decreasing score (ties: file order)."""
    if len(res) == 0:
        return {}
    order = np.lexsort((res.line, -res.score, res.obj_id, res.im_id, res.scene_id))
    keys = np.stack([res.scene_id[order], res.im_id[order], res.obj_id[order]], axis=1)
    cut = np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [len(order)]])
    return {(int(keys[s, 0]), int(keys[s, 1]), int(keys[s, 2])): order[s:e] for s, e in zip(starts, ends)}


def adds_values(model: M.ModelPoints, A: np.ndarray, b: np.ndarray, thr: float, add_ub: np.ndarray,
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


def evaluate_object(model: M.ModelPoints, obj_id: int, single: dict, multi: list, n_missing: int,
                     do_add: bool = True, do_proj: bool = True) -> ObjectEval:
    """One object's targets: ``single`` {"Re", "te", "Rg", "tg", "K", ["pthr"]} (one estimate, one
    instance each), ``multi`` [{"ests", "gts", "K", "count", ["pthr"]}], ``n_missing`` targets
    without an estimate. "pthr": the 2D projection threshold (px) per single target / of the group
    (default :data:`PROJ_THRESHOLD`)."""
    if not (do_add and do_proj):  # what is not asked for is not computed (nan; not reported)
        full = evaluate_object(model, obj_id, single, multi, n_missing) if (do_add or do_proj) else None
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
    pthr = np.broadcast_to(np.asarray(single.get("pthr", PROJ_THRESHOLD), np.float64), (len(Re),))
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
    amb = (pb.lo < pthr) & (pb.hi >= pthr)
    if amb.any():
        proj_v[amb] = M.proj2d_fast(model, Re[amb], te[amb], Rg[amb], tg[amb], K[amb], pthr[amb])
    proj_ok = proj_v < pthr  # exact: decided by the bounds or by the exact error
    t_proj = _time.perf_counter() - tic - t_add
    A, b = M.relative_transform(Re, te, Rg, tg) if len(Re) else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    n_targets = len(Re) + n_missing + sum(g["count"] for g in multi)
    adds_v, adds_ok, adds_ex, se, stages = adds_values(model, A, b, thr, add_v + add_err, n_targets, seed=obj_id)
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
                                      ("proj", proj_l, proj_okl, float(g.get("pthr", PROJ_THRESHOLD)))):
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
             metrics: Any = None, proj_px: float | None = None, vsd_cache: bool = True) -> Evaluation:
    """Everything :func:`score` computes, with the per-target errors (for reports and plots).
    ``metrics``: None (the default set, see :func:`resolve_metrics`) or names from
    :data:`METRICS` ("add,proj,vsd,mssd,mspd,ar" or a list). ``proj_px``: the 2D projection
    threshold in pixels (default: 5 px at 640 pixels wide, scaled with each scene's image width,
    :func:`~tdof20.scoring.evaluation.proj_threshold`). ``vsd_cache``: keep VSD's ground-truth half
    in ROOT/.cache/vsd/ for the next scoring (:mod:`tdof20.scoring.vsd_cache`; the same scores
    either way)."""
    proj_px = check_proj_px(proj_px)
    timings: dict[str, float] = {}
    t0 = _time.perf_counter()
    ds = dataset if dataset is not None else DatasetView(dataset_root, split)
    tpath = targets_path(ds.root, split, targets, ds)
    tg = load_targets(tpath, ds)
    require_targets(tg, ds, split)
    keys, notes = resolve_metrics(metrics, ds, tg)
    # checks against the dataset: ids, units
    dists = np.concatenate([np.linalg.norm(ds.scene(int(s)).t_all, axis=1) for s in np.unique(tg.scene_id)]) \
        if len(tg) else np.zeros(0)
    gt_dist = float(np.median(dists)) if len(dists) else None
    if isinstance(results, (str, Path)):
        # a file: read in parts, only each target's top inst_count rows kept (memory bounded by the targets)
        count = dict(zip(zip(tg.scene_id.tolist(), tg.im_id.tolist(), tg.obj_id.tolist()), tg.inst_count.tolist()))

        def keep(part: Results) -> np.ndarray:
            return np.array([count.get(k, 0) for k in zip(part.scene_id.tolist(), part.im_id.tolist(),
                                                              part.obj_id.tolist())], np.int64)

        res = read_top_results(results, keep, lambda part: check_against_dataset(
            part, ds.scene_ids, lambda s: set(ds.scene(s).K), ds.obj_ids, None), gt_dist)
    else:
        res = _as_results(results)
        check_against_dataset(res, ds.scene_ids, lambda s: set(ds.scene(s).K), ds.obj_ids, gt_dist)
    timings["read"] = _time.perf_counter() - t0
    warnings = list(res.warnings) + notes
    do_bop = any(k in keys for k in BOP_KEYS)

    # matching (ADD, ADD-S, 2D projection); per object the instances are ordered singles, multis, missing
    groups = group_rows(res)
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
    n_ignored = res.n_unmatched + len(res) - used  # (a file read in parts: its unmatched rows were not kept)
    n_missing = sum(p["missing"] for p in per_obj.values())
    if n_missing:
        warnings.append(f"{n_missing} of {int(tg.inst_count.sum())} targets have no estimate (counted as failures)")
    if n_ignored:
        warnings.append(f"{n_ignored} row(s) match no target of {tpath.name} (ignored)")
    timings["match"] = _time.perf_counter() - t0 - timings["read"]
    do_add = any(k in keys for k in METRIC_KEYS["add"])
    do_proj = "proj2d" in keys
    # the 2D projection threshold of each scene scored (its image width, unless proj_px is given)
    pthr = {int(s): proj_threshold(0 if proj_px is not None else ds.image_width(int(s)), proj_px)
            for s in np.unique(tg.scene_id)} if do_proj else {}
    for po in per_obj.values():
        for g in po["multi"]:
            g["pthr"] = pthr.get(g["scene"], PROJ_THRESHOLD)

    def job(ob: int) -> ObjectEval:
        po = per_obj[ob]
        model = ds.model(ob)
        sg = po["single"]
        idx = np.array([x[0] for x in sg], dtype=np.int64)
        single = {"Re": res.R[idx], "te": res.t[idx],
                  "Rg": np.array([x[1] for x in sg]).reshape(-1, 3, 3),
                  "tg": np.array([x[2] for x in sg]).reshape(-1, 3),
                  "K": np.array([x[3] for x in sg]).reshape(-1, 3, 3),
                  "pthr": np.array([pthr.get(x[4], PROJ_THRESHOLD) for x in sg], np.float64)}
        ev = evaluate_object(model, ob, single, po["multi"], po["missing"], do_add, do_proj)
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
        every = list(zip(tg.obj_id.tolist(), tg.scene_id.tolist(), tg.im_id.tolist(), tg.inst_count.tolist()))
        bop = bop_matches(recs, res, ds, keys, {ob: o.n for ob, o in objects.items()}, timings, every,
                          GtCache(ds.root) if vsd_cache else None)
        for ob, o in objects.items():
            o.bop = bop[ob]
        timings["bop"] = _time.perf_counter() - tic
    timings["total"] = _time.perf_counter() - t0
    labels = {int(sid): ds.scene_label(int(sid)) for sid in np.unique(tg.scene_id)}
    names = {int(ob): ds.object_name(int(ob)) for ob in objects}
    px_used = sorted(set(pthr.values()))
    proj_used = (px_used[0] if len(px_used) == 1 else {str(k): v for k, v in sorted(pthr.items())}) if px_used else None
    n_rows = len(res) if res.n_read is None else res.n_read
    return Evaluation(res.name, objects, warnings, timings, n_rows, keys, labels, names, proj_used)


def check_proj_px(proj_px: Any) -> float | None:
    """``proj_px`` (--proj-px) as a float > 0, or None (the default: scaled with the image width)."""
    if proj_px is None:
        return None
    try:
        v = float(proj_px)
    except (TypeError, ValueError):
        v = float("nan")
    if isinstance(proj_px, bool) or not (math.isfinite(v) and v > 0):
        raise TdofError(f"--proj-px: the 2D projection threshold must be a number of pixels > 0, got {proj_px!r}")
    return v


__all__ = ["adds_values", "check_proj_px", "evaluate", "evaluate_object", "group_rows", "parse_metrics", "resolve_metrics",
           "vsd_unavailable"]
