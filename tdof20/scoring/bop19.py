"""BOP19's pose-error metrics on a results file: the VSD, MSSD and MSPD errors of every (estimate,
ground-truth instance) pair of a target, and BOP19's matching — per target the top ``inst_count``
estimates, greedily by score, each take the unmatched one of the ``inst_count`` most visible
ground-truth instances with the smallest error below the threshold. The average recalls are
summarised by :class:`tdof20.scoring.evaluation.ObjectEval`.
"""

from __future__ import annotations

import time as _time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from tdof20.dataset.results import Results
from tdof20.scoring import metrics as M
from tdof20.scoring.dataset_view import DatasetView
from tdof20.scoring.evaluation import THREADS


def greedy_count(E: np.ndarray, th: float) -> int:
    """BOP19 matching of one (image, object): the estimates (rows of E, by decreasing score) each
    take the unmatched ground-truth instance (column) with the smallest error below ``th``
    (strict; ties: the first). Returns the number matched."""
    return int(greedy_counts(np.asarray(E, np.float64)[:, :, None], np.array([th]))[0, 0])


def greedy_counts(E: np.ndarray, th: np.ndarray) -> np.ndarray:
    """:func:`greedy_count` for every error kind (E (n_est, n_gt, T): e.g. VSD's taus) and every
    threshold (J,) at once: (T, J) counts. The estimates are taken in turn (rows); the T x J
    matchings run side by side."""
    _, n_gt, T = E.shape
    J = len(th)
    taken = np.zeros((T, J, n_gt), bool)
    count = np.zeros((T, J), np.int64)
    for row in E:  # (n_gt, T)
        err = np.broadcast_to(row.T[:, None, :], (T, J, n_gt))
        cand = ~taken & (err < th[None, :, None])
        got = cand.any(axis=2)
        pick = np.argmin(np.where(cand, err, np.inf), axis=2)  # ties: the first
        ti, ji = np.nonzero(got)
        taken[ti, ji, pick[ti, ji]] = True
        count += got
    return count


def bop_matches(recs: list, res: Results, ds: DatasetView, keys: tuple, sizes: dict, timings: dict) -> dict:
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
        errs["vsd"] = vsd_errors(ds, res, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings)
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
            blk = E[p0:p0 + ne * ng].reshape(ne, ng, -1)  # (estimates, instances, taus or 1)
            cnt = greedy_counts(blk, th)
            # the first cnt of the target's slots are matched
            hit = np.arange(cnt.max(initial=0))[:, None, None] < cnt[None]
            dst = out[ob][m]
            if m == "vsd":
                dst[slot:slot + len(hit)] |= hit
            else:
                dst[slot:slot + len(hit)] |= hit[:, 0]
    return out


def _depth_for_vsd(raw: np.ndarray, scale: float) -> np.ndarray:
    """The test depth VSD samples: the PNG's uint16 values as they are where depth_scale is 1 (VSD
    turns the sampled values into float64 exactly as it would the float32 mm image, so no
    full-image conversion is needed), else the float32 mm image (:meth:`DatasetView.depth_mm`)."""
    return raw if scale == 1.0 else raw.astype(np.float32) * np.float32(scale)


def vsd_errors(ds: DatasetView, res: Results, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings,
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
        imgs = [_depth_for_vsd(*ds.depth_raw(int(ims[i] >> 32), int(ims[i] & 0xFFFFFFFF))) for i in ch]
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
                stack = [imgs[k] for k in local]  # sampled where the footprints are: no copy
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


__all__ = ["bop_matches", "greedy_count", "greedy_counts", "vsd_errors"]
