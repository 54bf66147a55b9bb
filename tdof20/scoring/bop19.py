"""BOP19's pose-error metrics on a results file: the VSD, MSSD and MSPD errors of every (estimate,
ground-truth instance) pair of a target, and BOP19's matching — per target the top ``inst_count``
estimates, greedily by score, each take the unmatched one of the ``inst_count`` most visible
ground-truth instances with the smallest error below the threshold. The average recalls are
summarised by :class:`tdof20.scoring.evaluation.ObjectEval`.
"""

from __future__ import annotations

import hashlib
import time as _time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from tdof20.dataset.results import Results
from tdof20.formats.io import png_header
from tdof20.scoring import metrics as M
from tdof20.scoring.dataset_view import DatasetView, decode_depth
from tdof20.scoring.evaluation import THREADS
from tdof20.scoring.vsd_cache import BLOCK, FORMAT, GtCache, digest, encode, unpack


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


def bop_matches(recs: list, res: Results, ds: DatasetView, keys: tuple, sizes: dict, timings: dict,
                targets: list | None = None, cache: GtCache | None = None) -> dict:
    """Per object {"vsd": (n,10,10), "mssd": (n,10), "mspd": (n,10)} bool: instance matched at
    each (tau and) threshold. ``recs``: per target with estimates (obj, scene, im, count, its top
    ``count`` rows, first instance slot). ``targets`` (every target's (obj, scene, im, count)) and
    ``cache``: VSD's ground-truth half kept on disk (:func:`vsd_errors`)."""
    want = {m for m in ("vsd", "mssd", "mspd") if ("ar_" + m) in keys or "ar" in keys}
    nT = len(M.MSSD_THRESHOLDS)
    out = {ob: {"vsd": np.zeros((n, len(M.VSD_TAUS), len(M.VSD_THRESHOLDS)), bool) if "vsd" in want else None,
                "mssd": np.zeros((n, nT), bool) if "mssd" in want else None,
                "mspd": np.zeros((n, len(M.MSPD_THRESHOLDS)), bool) if "mspd" in want else None}
           for ob, n in sizes.items()}
    for ob in out:
        out[ob] = {k: v for k, v in out[ob].items() if v is not None}
    # every (estimate, valid ground truth) pair of every target
    p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, p_exact, p_gid = [], [], [], [], [], [], [], [], []
    blocks = []  # per target: (obj, first pair, n_est, n_gt, slot)
    for ob, s, im, cnt, rows, slot in recs:
        gts = ds.bop_instances(s, im, ob, cnt)
        K = ds.scene(s).K[im]
        blocks.append((ob, len(p_obj), len(rows), len(gts), slot, cnt))
        for r in rows:
            for gid, R, t in gts:
                p_gid.append(gid)
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
        errs["vsd"] = vsd_errors(ds, res, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings,
                                 np.asarray(p_gid, np.int64), targets, cache)
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


def _footprints(ds: DatasetView, obj: np.ndarray, R, t, K, size: np.ndarray):
    """:meth:`DepthRenderer.footprints` of poses of several objects and image sizes ((h, w) each):
    boxes (n,4) and polygons, in the poses' order."""
    n = len(obj)
    boxes = np.zeros((n, 4), np.int64)
    polys: list = [None] * n
    groups = np.unique(np.column_stack([obj, size]), axis=0) if n else np.zeros((0, 3), np.int64)
    for ob, h, w in groups.tolist():
        sel = np.flatnonzero((obj == ob) & (size[:, 0] == h) & (size[:, 1] == w))
        b, p = ds.renderer(int(ob)).footprints(R[sel], t[sel], K[sel], int(w), int(h))
        boxes[sel] = b
        for i, pp in zip(sel.tolist(), p):
            polys[i] = pp
    return boxes, polys


def vsd_errors(ds: DatasetView, res: Results, p_obj, p_scene, p_im, p_row, p_R, p_t, p_K, timings,
               p_gid=None, targets=None, cache: GtCache | None = None) -> np.ndarray:
    """VSD (n, 10 taus) of every pair, block by block of a scene's images (:data:`BLOCK` image ids):
    a thread reads the next block's depth PNGs while this one is scored, and keeps of each image
    only what the pairs' footprints cover. The ground-truth half (each instance's V_g,
    :class:`~tdof20.scoring.metrics.vsd.VisibleGt`) is computed once per instance and, with
    ``cache`` (:class:`~tdof20.scoring.vsd_cache.GtCache`) writable, kept on disk for every
    ``targets`` instance ((obj, scene, im, inst_count) each), so a later scoring only renders the
    estimates. ``p_gid``: each pair's ground-truth index in its image (default: told apart by pose)."""
    n = len(p_obj)
    T = len(M.VSD_TAUS)
    out = np.ones((n, T))
    # the ground-truth instances: the pairs', and (kept) every target's
    keep = cache is not None and cache.writable() and targets is not None
    inst: dict[tuple, int] = {}
    i_obj, i_scene, i_im, i_gid, i_R, i_t, i_K = [], [], [], [], [], [], []

    def add(ob, s, im, gid, R, t, K) -> int:
        k = (int(s), int(im), int(ob), int(gid))
        if k not in inst:
            inst[k] = len(i_obj)
            for lst, v in zip((i_obj, i_scene, i_im, i_gid, i_R, i_t, i_K), (ob, s, im, gid, R, t, K)):
                lst.append(v)
        return inst[k]

    if p_gid is None:  # instances told apart by their pose
        p_gid = np.unique(np.concatenate([p_R.reshape(n, 9), p_t], axis=1), axis=0, return_inverse=True)[1].reshape(-1)
    p_inst = np.array([add(*a) for a in zip(p_obj.tolist(), p_scene.tolist(), p_im.tolist(), np.asarray(p_gid).tolist(),
                                            p_R, p_t, p_K)], np.int64).reshape(n)
    if keep:
        for ob, s, im, cnt in targets:
            K = ds.scene(s).K[im]
            for gid, R, t in ds.bop_instances(s, im, ob, cnt):
                add(ob, s, im, gid, R, t, K)
    m = len(i_obj)
    i_obj, i_scene, i_im, i_gid = (np.asarray(x, np.int64).reshape(m) for x in (i_obj, i_scene, i_im, i_gid))
    i_R, i_t, i_K = (np.asarray(x, np.float64).reshape((m,) + sh) for x, sh in ((i_R, (3, 3)), (i_t, (3,)),
                                                                                 (i_K, (3, 3))))
    # blocks of images, in order; each: its instances and pairs
    bkey = i_scene * (1 << 32) + i_im // BLOCK
    blocks = np.unique(bkey)
    t_read = [0.0, 0.0, 0.0, 0.0]  # wall, CPU, footprints' CPU, decoding's CPU
    first_pair = np.full(m, -1, np.int64)
    first_pair[p_inst[::-1]] = np.arange(n)[::-1]

    def load(b):
        """Read block b: its images' PNGs (bytes digested), every pose's footprint, and the test depth
        on each pair's raster (its estimate's and ground truth's boxes) and on each instance without
        a pair's (its box): images are dropped once cropped."""
        tic, cpu = _time.perf_counter(), _time.thread_time()
        ii = np.flatnonzero(bkey == b)
        ii = ii[np.lexsort((i_gid[ii], i_obj[ii], i_im[ii]))]  # in an order of their own (the file's)
        pp = np.flatnonzero(np.isin(p_inst, ii))
        s = int(i_scene[ii[0]])
        ims = np.unique(i_im[ii])
        data = {int(im): ds.depth_bytes(s, int(im)) for im in ims}
        size = {im: png_header(ds.depth_path(s, im), "depth", d) for im, d in data.items()}
        bi = {im: k for k, im in enumerate(data)}
        szi = np.array([size[int(im)] for im in i_im[ii]], np.int64).reshape(-1, 2)
        szp = np.array([size[int(im)] for im in p_im[pp]], np.int64).reshape(-1, 2)
        c0 = _time.thread_time()
        bg, pg = _footprints(ds, i_obj[ii], i_R[ii], i_t[ii], i_K[ii], szi)
        rows = p_row[pp]
        be, pe = _footprints(ds, p_obj[pp], res.R[rows], res.t[rows], p_K[pp], szp)
        t_read[2] += _time.thread_time() - c0
        loc = {int(g): k for k, g in enumerate(ii)}  # instance -> its index in the block
        pl = np.array([loc[int(g)] for g in p_inst[pp]], np.int64)
        alone = np.flatnonzero(first_pair[ii] < 0)  # instances without a pair
        empty = np.zeros((len(alone), 4), np.int64)
        ras = M.Rasters(np.concatenate([be, empty]), np.concatenate([bg[pl], bg[alone]]),
                        dtype=np.uint16)
        # each instance's raster: its first pair's (in the block), else its own
        sel_i = np.empty(len(ii), np.int64)
        sel_i[alone] = len(pp) + np.arange(len(alone))
        seen = np.full(len(ii), -1, np.int64)
        seen[pl[::-1]] = np.arange(len(pp))[::-1]
        has = seen >= 0
        sel_i[has] = seen[has]
        owner = np.concatenate([np.array([bi[int(im)] for im in p_im[pp]], np.int64).reshape(-1),
                                np.array([bi[int(im)] for im in i_im[ii][alone]], np.int64).reshape(-1)])
        order = np.argsort(owner, kind="stable")
        digests = {}
        ras.depth = None
        pos = 0
        for im, d in data.items():
            path = ds.depth_path(s, im)
            digests[im] = hashlib.sha256(d).hexdigest()
            c0 = _time.thread_time()
            img = _depth_for_vsd(decode_depth(d, path), ds.depth_scale(s, im))
            t_read[3] += _time.thread_time() - c0
            if img.dtype != np.uint16 and ras.dtype == np.uint16:  # a depth_scale != 1 in the block
                ras.dtype = np.float32
                if ras.depth is not None:
                    ras.depth = ras.depth.astype(np.float32)
            k = bi[im]
            while pos < len(order) and owner[order[pos]] == k:
                ras.crop(int(order[pos]), img)
                pos += 1
        if ras.depth is None:
            ras.depth = np.zeros(ras.total, ras.dtype)
        t_read[0] += _time.perf_counter() - tic
        t_read[1] += _time.thread_time() - cpu
        return ii, pp, pl, bg, pg, be, pe, ras, sel_i, szi, szp, digests, s

    t_wait = 0.0
    with ThreadPoolExecutor(max_workers=1) as reader:
        nxt = reader.submit(load, blocks[0]) if len(blocks) else None
        for bk, b in enumerate(blocks):
            tic = _time.perf_counter()
            ii, pp, pl, bg, pg, be, pe, ras, sel_i, szi, szp, digests, s = nxt.result()
            t_wait += _time.perf_counter() - tic
            nxt = reader.submit(load, blocks[bk + 1]) if bk + 1 < len(blocks) else None
            # the ground truths' V_g: kept, or computed (and kept)
            objs = np.unique(i_obj[ii])
            path = key = None
            stored = None
            if keep:
                ident = np.column_stack([i_obj[ii], i_im[ii], i_gid[ii]])
                path = cache.path(s, int(b & 0xFFFFFFFF), digest(FORMAT, ident))
                key = digest(FORMAT, repr(M.VSD_DELTA), ident, i_R[ii], i_t[ii], i_K[ii], szi,
                             *[ds.mesh_digest(int(o)) for o in objs],
                             *[f"{im}:{dg}:{ds.depth_scale(s, im)!r}" for im, dg in sorted(digests.items())])
                stored = cache.load(path, key)
            groups = []  # (object, h, w, block indices) of the instances
            for ob in objs:
                sel = np.flatnonzero(i_obj[ii] == ob)
                for (h, w) in np.unique(szi[sel], axis=0).tolist():
                    groups.append((int(ob), int(h), int(w), sel[(szi[sel, 0] == h) & (szi[sel, 1] == w)]))
            parts = None
            if stored is not None:
                try:
                    packed = unpack(stored)
                    if len(packed) != len(ii):
                        raise ValueError("not the block's instances")
                    parts = []
                    for ob, h, w, g in groups:
                        sub = packed.take(g)
                        parts.append(M.VisibleGt.from_stored(ds.renderer(ob), i_R[ii][g], i_t[ii][g], sub.boxes,
                                                             sub.start, sub.idx, sub.qi))
                except Exception:  # a damaged file: computed again (and rewritten)
                    parts = None
            fresh = parts is None
            if fresh:
                parts = [M.visible_gt(ds.renderer(ob), i_R[ii][g], i_t[ii][g], i_K[ii][g], bg[g], [pg[j] for j in g],
                                      ras, sel_i[g], w, h) for ob, h, w, g in groups]
            order = np.concatenate([g for *_, g in groups])
            inv = np.empty(len(order), np.int64)
            inv[order] = np.arange(len(order))
            gt_block = M.VisibleGt.concatenate(parts).take(inv)  # in the block's order
            if fresh and keep:
                cache.save(path, key, encode(gt_block))
            # the estimates
            for ob in np.unique(p_obj[pp]):
                sel = np.flatnonzero(p_obj[pp] == ob)
                for (h, w) in np.unique(szp[sel], axis=0).tolist():
                    g = sel[(szp[sel, 0] == h) & (szp[sel, 1] == w)]
                    rows = p_row[pp[g]]
                    out[pp[g]] = M.vsd_estimates(ds.renderer(int(ob)), res.R[rows], res.t[rows], p_K[pp[g]], be[g],
                                                 [pe[j] for j in g], gt_block.take(pl[g]), ras, g, int(w), int(h),
                                                 ds.model(int(ob)).diameter)
    timings["depth_read"] = t_read[0]
    timings["depth_read_cpu"] = t_read[1]  # the reading thread's CPU seconds, of which
    timings["depth_read_footprints_cpu"] = t_read[2]  # the poses' footprints
    timings["depth_read_decode_cpu"] = t_read[3]  # the depth PNGs decoded
    timings["depth_wait"] = t_wait
    if cache is not None:
        timings["vsd_cache_hits"] = float(cache.hits)
    return out


__all__ = ["bop_matches", "greedy_count", "greedy_counts", "vsd_errors"]
