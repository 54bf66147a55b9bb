"""Speed of ``tdof20 benchmark score`` on a synthetic workload the size of TDoF20-hard's test split.

    python benchmarks/score_speed.py [--images 9139] [--subset 300] [--bop-subset 120] [--keep DIR]

Writes a synthetic dataset to a temporary folder: 20 objects (catalog shapes with the catalog's
symmetries: 11 continuous, 2 discrete; 2,000-10,000 model points sampled on their surfaces as
models_eval/ point clouds; the catalog meshes as models/ for VSD's renders), 6 multi-object scenes
holding 9,139 images of 640x480 with 3-5 objects each (about 36,500 targets), a depth image per
image (a background surface and the objects, ray cast, with the holes and see-through pixels of
transparent objects), the test targets and a results CSV: per target a perturbed estimate (45%
close, 25% around the 10% threshold, 27% far off, 3% missing; symmetric objects also turned about
their axis), and for 5% of the targets extra lower-scored estimates.

Then, each in a fresh process, it times ``evaluate()`` with the ADD family (``--metrics
add,proj``) and with the BOP metrics (``--metrics ar``: VSD, MSSD, MSPD and AR), reading every file
included, and their peak memory (ru_maxrss). It times the straightforward way on random subsets of
the targets and extrapolates to all of them (saying so): for ADD(-S) and 2D projection the BOP
toolkit's (a KD-tree per pose, plain numpy), for VSD, MSSD and MSPD the BOP toolkit's too (per
pose two full-frame depth renders, by the same open3d ray casting, and a loop over every symmetry
transformation over every model point). On the subsets it checks that every decision (each
threshold, and each tau for VSD) agrees, and prints the ratios.

The imports are inside the functions that need them, so that the fresh ``--score-only`` process
holds, and times, only what ``evaluate()`` imports (its wall time includes that import).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENES = [22, 28, 29, 30, 31, 35]  # multi/02, 08, 09, 10, 11, 15
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 640, 480


def _rot(axis_angle: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis_angle).as_matrix()


def _depth_image(renderers: dict, poses: list, rng: np.random.Generator) -> np.ndarray:
    """(480,640) uint16 mm: a background surface 1,050 mm away (nearer at the bottom), the objects
    ray cast in their footprints; per object a random share of pixels sees through it (the
    background's depth) or has no depth, as a transparent object's raw depth does; 2% holes."""
    v = np.arange(HEIGHT, dtype=np.float32)[:, None]
    z = np.broadcast_to(1050.0 - 0.3 * (v - HEIGHT / 2), (HEIGHT, WIDTH)).astype(np.float32).copy()
    bg = z.copy()
    for ob, R, t in poses:
        ren = renderers[ob]
        (box,), _ = ren.footprints(R[None], t[None], K[None], WIDTH, HEIGHT)
        v0, v1, u0, u1 = (int(x) for x in box)
        if v0 >= v1 or u0 >= u1:
            continue
        vv, uu = np.mgrid[v0:v1, u0:u1].reshape(2, -1).astype(np.float64)
        y = (vv - K[1, 2]) / K[1, 1]
        x = (uu - K[0, 2]) / K[0, 0]
        d = np.stack([x, y, np.ones_like(x)], axis=1) @ R
        o = np.broadcast_to(-R.T @ t, d.shape)
        hit = ren.cast(o.astype(np.float32), d.astype(np.float32)).reshape(v1 - v0, u1 - u0)
        sub = z[v0:v1, u0:u1]
        near = (hit > 0) & (hit < sub)
        r = rng.random(near.shape)
        p_see, p_hole = rng.uniform(0.2, 0.6), rng.uniform(0.05, 0.3)
        val = np.where(r < p_see, bg[v0:v1, u0:u1], np.where(r < p_see + p_hole, 0.0, hit))
        sub[near] = val[near]
    z[rng.random(z.shape) < 0.02] = 0.0
    return np.round(z).astype(np.uint16)


def make_workload(out: Path, n_images: int, seed: int = 0) -> dict:
    import cv2
    import trimesh
    from concurrent.futures import ThreadPoolExecutor
    from scipy.spatial.transform import Rotation

    from tdof20.dataset.results import write_results_csv
    from tdof20.formats.bop import dumps_bop_json, write_models_info
    from tdof20.formats.io import atomic_write_bytes, write_json
    from tdof20.objects import export_models, get_object
    from tdof20.scoring import metrics as M

    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    me = out / "models_eval"
    me.mkdir(exist_ok=True)
    export_models(out / "models")  # the meshes VSD renders (models_eval/ holds point clouds)
    sizes = rng.permutation(np.linspace(2000, 10000, 20).round().astype(int))
    infos, diam, symmetric, renderers = {}, {}, set(), {}
    for obj_id, n in zip(range(1, 21), sizes):
        m = get_object(obj_id)
        pts = m.sample_surface(int(n), seed=obj_id)
        atomic_write_bytes(me / f"obj_{obj_id:06d}.ply", trimesh.PointCloud(pts).export(file_type="ply"))
        infos[obj_id] = m.models_info()  # the catalog's diameter and symmetries (BOP form)
        diam[obj_id] = m.diameter
        if m.symmetric:
            symmetric.add(obj_id)
        renderers[obj_id] = M.DepthRenderer(m.vertices, m.faces)
    write_models_info(me, infos)
    write_json(out / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                     "height": 480, "depth_scale": 1.0})
    write_json(out / "dataset_info.json", {"name": "tdof20-synthetic",
                                           "scenes": {str(s): f"multi/{s - 20:02d}" for s in SCENES}})
    targets, rows = [], []
    per_scene = np.array_split(np.arange(n_images), len(SCENES))
    cat_p = [0.45, 0.25, 0.27, 0.03]
    writer = ThreadPoolExecutor(max_workers=2)  # PNG encoding (cv2 releases the GIL)

    def write_depth(path: Path, depth: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", depth, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        path.write_bytes(buf.tobytes())

    pending = []
    for sid, ims in zip(SCENES, per_scene):
        cam, gt = {}, {}
        ddir = out / "scenes" / f"{sid:06d}" / "depth"
        ddir.mkdir(parents=True, exist_ok=True)
        for im in range(len(ims)):
            objs = rng.choice(np.arange(1, 21), size=rng.integers(3, 6), replace=False)
            cam[str(im)] = {"cam_K": K.reshape(-1).tolist(), "depth_scale": 1.0}
            lst = []
            posed = []
            for ob in objs:
                ob = int(ob)
                Rg = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
                tg = np.array([rng.uniform(-120, 120), rng.uniform(-90, 90), rng.uniform(550, 950)])
                lst.append({"obj_id": ob, "cam_R_m2c": Rg.reshape(-1).tolist(), "cam_t_m2c": tg.tolist()})
                posed.append((ob, Rg, tg))
                targets.append({"scene_id": sid, "im_id": im, "obj_id": ob, "inst_count": 1})
                d = diam[ob]
                cat = rng.choice(4, p=cat_p)
                if cat == 3:
                    continue  # missing
                th, tau = {0: (rng.uniform(0, 5), rng.uniform(0, 0.05)),
                           1: (rng.uniform(0, 12), rng.uniform(0.04, 0.14)),
                           2: (rng.uniform(0, 180), np.exp(rng.uniform(np.log(0.1), np.log(4))))}[cat]
                ax = rng.normal(size=3)
                Re = _rot(np.deg2rad(th) * ax / np.linalg.norm(ax)) @ Rg
                if ob in symmetric:
                    Re = Re @ _rot(np.array([0.0, 0.0, rng.uniform(0, 2 * np.pi)]))
                v = rng.normal(size=3)
                te = tg + tau * d * v / np.linalg.norm(v)
                rows.append((sid, im, ob, float(rng.uniform(0.5, 1.0)), Re, te, 0.05))
                if rng.random() < 0.05:  # a lower-scored second guess
                    Rx = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
                    tx = tg + rng.normal(size=3) * 0.3 * d
                    rows.append((sid, im, ob, float(rng.uniform(0.0, 0.45)), Rx, tx, 0.05))
            gt[str(im)] = lst
            pending.append(writer.submit(write_depth, ddir / f"{im:06d}.png", _depth_image(renderers, posed, rng)))
            if len(pending) > 16:
                pending.pop(0).result()
        d = out / "scenes" / f"{sid:06d}"
        atomic_write_bytes(d / "scene_camera.json", dumps_bop_json(cam).encode())
        atomic_write_bytes(d / "scene_gt.json", dumps_bop_json(gt).encode())
    for f in pending:
        f.result()
    writer.shutdown()
    write_json(out / "test_targets_hard.json", targets, indent=None)
    write_results_csv(out / "synthetic_tdof20-hard.csv", rows)
    return {"targets": len(targets), "rows": len(rows), "images": n_images, "points": sizes.tolist(),
            "symmetric": len(symmetric)}


def run_score(root: Path, metrics: str) -> dict:
    """In this (fresh) process: time evaluate() with ``metrics`` and report its peak memory."""
    t0, c0 = time.perf_counter(), time.process_time()
    from tdof20.scoring.scoring import evaluate

    ev = evaluate(root / "synthetic_tdof20-hard.csv", root, split="hard", metrics=metrics)
    summ = ev.summary()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    stages = {}
    for o in ev.objects.values():
        for k, v in o.stages.items():
            stages[k] = stages.get(k, 0) + v
    if "add" in ev.keys:
        per = {str(k): {"add_s": o.add_s.tolist(), "adds": o.adds.tolist(), "add_ok": o.add_ok.tolist(),
                        "adds_ok": o.adds_ok.tolist(), "proj_ok": o.proj_ok.tolist()} for k, o in ev.objects.items()}
        (root / "fast_errors.json").write_text(json.dumps(per))
    if "ar" in ev.keys:
        np.savez(root / "fast_bop.npz", **{f"{m}_{k}": o.bop[m] for k, o in ev.objects.items() for m in o.bop})
    return {"wall_s": wall, "cpu_s": cpu, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "timings": ev.timings, "summary_all": summ["all"], "summary_mean": summ["mean"], "stages": stages,
            "auc_se_max": max((o.auc_se for o in ev.objects.values()), default=0.0), "keys": list(ev.keys)}


def straightforward(root: Path, subset: int, seed: int = 1) -> dict:
    """The BOP toolkit's way on ``subset`` random targets: per pose a KD-tree on the estimate-posed
    points (ADD-S), plain numpy for ADD and 2D projection. Compares with the fast run."""
    from scipy.spatial import cKDTree

    # the fast run's per-object order: single-instance matched targets in file order, then missing
    res, ds, matched = _matched_singles(root)
    fast = json.loads((root / "fast_errors.json").read_text())
    rng = np.random.default_rng(seed)
    pick = [matched[i] for i in rng.choice(len(matched), size=min(subset, len(matched)), replace=False)]
    t0 = time.perf_counter()
    rows = []
    for t, r, k in pick:
        ob = t["obj_id"]
        model = ds.model(ob)
        P = model.pts
        sc = ds.scene(t["scene_id"])
        (_, Rg, tg), = [g for g in sc.gt[t["im_id"]] if g[0] == ob]
        Re, te = res.R[r], res.t[r]
        pe, pg = P @ Re.T + te, P @ Rg.T + tg
        add = np.linalg.norm(pe - pg, axis=1).mean()
        adds = cKDTree(pe).query(pg, k=1)[0].mean()
        Kk = sc.K[t["im_id"]]
        ue, ug = pe @ Kk.T, pg @ Kk.T
        proj = np.linalg.norm(ue[:, :2] / ue[:, 2:] - ug[:, :2] / ug[:, 2:], axis=1).mean()
        rows.append((ob, k, add, adds, proj, model.diameter, model.symmetric))
    dt = time.perf_counter() - t0
    mism = 0
    ex_auc, fa_auc = [], []
    for ob, k, add, adds, proj, d, sym in rows:
        f = fast[str(ob)]
        thr = 0.1 * d
        mism += (add < thr) != f["add_ok"][k]
        mism += (adds < thr) != f["adds_ok"][k]
        mism += (proj < 5.0) != f["proj_ok"][k]
        ex_auc.append(max(0.0, 1 - adds / 100))
        fa_auc.append(max(0.0, 1 - f["adds"][k] / 100))
    return {"subset": len(rows), "seconds": dt, "per_target_ms": 1e3 * dt / len(rows), "matched": len(matched),
            "decision_mismatches": int(mism), "auc_adds_exact": float(np.mean(ex_auc)),
            "auc_adds_fast": float(np.mean(fa_auc))}


def _matched_singles(root: Path):
    """(results, dataset view, [(target, row, position within its object)]) for every target with
    an estimate, in the scorer's order (single-instance targets: their object's instance order)."""
    from tdof20.dataset.results import read_results
    from tdof20.scoring.dataset_view import DatasetView
    from tdof20.scoring.scorer import group_rows

    ds = DatasetView(root)
    res = read_results(root / "synthetic_tdof20-hard.csv")
    groups = group_rows(res)
    targets = json.loads((root / "test_targets_hard.json").read_text())
    pos: dict[int, int] = {}
    matched = []
    for t in targets:
        key = (t["scene_id"], t["im_id"], t["obj_id"])
        if key in groups:
            k = pos.get(t["obj_id"], 0)
            pos[t["obj_id"]] = k + 1
            matched.append((t, int(groups[key][0]), k))
    return res, ds, matched


def straightforward_bop(root: Path, subset: int, seed: int = 2) -> dict:
    """BOP toolkit's way on ``subset`` random targets: the test depth read per image, per pose the
    estimated and the ground-truth depth rendered over the full frame (the same open3d ray
    casting), VSD from them; MSSD and MSPD as a loop over every symmetry transformation over every
    model point. Compares every decision with the fast run's."""
    from tdof20.scoring import metrics as M

    res, ds, matched = _matched_singles(root)
    fast = np.load(root / "fast_bop.npz")
    rng = np.random.default_rng(seed)
    pick = [matched[i] for i in rng.choice(len(matched), size=min(subset, len(matched)), replace=False)]
    renderers = {}
    t_depth = t_vsd = t_mssd = t_mspd = 0.0
    mism = {"vsd": 0, "mssd": 0, "mspd": 0}
    for t, r, k in pick:
        ob, sid, im = t["obj_id"], t["scene_id"], t["im_id"]
        model = ds.model(ob)
        if ob not in renderers:
            from tdof20.formats.bop import read_model_mesh

            renderers[ob] = M.DepthRenderer(*read_model_mesh(ds.mesh_path(ob)))
        (_, Rg, tg), = [g for g in ds.scene(sid).gt[im] if g[0] == ob]
        Re, te = res.R[r], res.t[r]
        Kk = ds.scene(sid).K[im]
        tic = time.perf_counter()
        depth = ds.depth_mm(sid, im)
        t_depth += time.perf_counter() - tic
        tic = time.perf_counter()
        de = renderers[ob].render(Re, te, Kk, depth.shape[1], depth.shape[0])
        dg = renderers[ob].render(Rg, tg, Kk, depth.shape[1], depth.shape[0])
        vsd = M.vsd_from_depths(de, dg, depth, Kk, model.diameter)
        t_vsd += time.perf_counter() - tic
        tic = time.perf_counter()
        mssd = M.mssd(Re, te, Rg, tg, model.pts, model.syms) / model.diameter
        t_mssd += time.perf_counter() - tic
        tic = time.perf_counter()
        mspd = M.mspd(Re, te, Rg, tg, Kk, model.pts, model.syms) * M.MSPD_WIDTH / ds.image_width(sid)
        t_mspd += time.perf_counter() - tic
        mism["vsd"] += int((fast[f"vsd_{ob}"][k] != (vsd[:, None] < M.VSD_THRESHOLDS[None, :])).sum())
        mism["mssd"] += int((fast[f"mssd_{ob}"][k] != (mssd < M.MSSD_THRESHOLDS)).sum())
        mism["mspd"] += int((fast[f"mspd_{ob}"][k] != (mspd < M.MSPD_THRESHOLDS)).sum())
    n = len(pick)
    n_images = len({(t["scene_id"], t["im_id"]) for t, _, _ in matched})
    per_pair = (t_vsd + t_mssd + t_mspd) / n
    total = per_pair * len(matched) + t_depth / n * n_images  # each depth image read once
    return {"subset": n, "matched": len(matched), "images": n_images, "ms_depth_read": 1e3 * t_depth / n,
            "ms_vsd": 1e3 * t_vsd / n, "ms_mssd": 1e3 * t_mssd / n, "ms_mspd": 1e3 * t_mspd / n,
            "total_s": total, "mismatches": mism}


def _fresh(root: Path, metrics: str) -> dict:
    out = subprocess.run([sys.executable, __file__, "--score-only", str(root), "--metrics", metrics],
                         capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=9139)
    ap.add_argument("--subset", type=int, default=300, help="targets timed the straightforward way (ADD family)")
    ap.add_argument("--bop-subset", type=int, default=120, help="targets timed the straightforward way (BOP metrics)")
    ap.add_argument("--keep", type=Path, default=None, help="write the workload here and keep it (reused if there)")
    ap.add_argument("--score-only", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--metrics", default="add,proj", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.score_only:
        print(json.dumps(run_score(a.score_only, a.metrics)))
        return
    tmp = None
    if a.keep is None:
        tmp = tempfile.TemporaryDirectory(prefix="tdof20-score-speed-")
        root = Path(tmp.name)
    else:
        root = a.keep
    t0 = time.perf_counter()
    if (root / "synthetic_tdof20-hard.csv").exists():
        print(f"workload: reusing {root}")
    else:
        info = make_workload(root, a.images)
        print(f"workload: {info['images']} images of {WIDTH}x{HEIGHT} with depth, {info['targets']} targets, "
              f"{info['rows']} result rows, 20 objects of {min(info['points'])}-{max(info['points'])} points, "
              f"{info['symmetric']} symmetric (written in {time.perf_counter() - t0:.1f} s to {root})")
    load = os.getloadavg()[0]

    # ADD(-S), 2D projection
    r = _fresh(root, "add,proj")
    t = r["timings"]
    print(f"\n[ADD family] evaluate(metrics='add,proj'): {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU (read "
          f"{t['read']:.2f}, match {t['match']:.2f}, metrics {t['metrics']:.2f}); peak memory {r['maxrss_mb']:.0f} MB "
          f"(ru_maxrss, whole process); {os.cpu_count()} cores, load average before {load:.1f}")
    st = r["stages"]
    print(f"ADD-S: {st.get('poses', 0)} poses; coarse bounds for all, fine bounds {st.get('fine', 0)}, per-point "
          f"bounds {st.get('points', 0)}, exact KD-tree decisions {st.get('exact', 0)} "
          f"({st.get('exact_full', 0)} needed every point); largest AUC standard error {r['auc_se_max']:.2e}")
    a_ = r["summary_all"]
    print("all: " + ", ".join(f"{k} {a_[k]:.4f}" for k in ("add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s")))
    s = straightforward(root, a.subset)
    full = s["per_target_ms"] * s["matched"] / 1e3
    print(f"straightforward (KD-tree per pose): {s['per_target_ms']:.2f} ms per target on {s['subset']} targets "
          f"-> {full:.0f} s for all {s['matched']} matched targets (extrapolated); ratio {full / r['wall_s']:.0f}x")
    print(f"check on the subset: {s['decision_mismatches']} decision mismatches (ADD, ADD-S, 2D proj); "
          f"AUC ADD-S exact {s['auc_adds_exact']:.5f} vs fast {s['auc_adds_fast']:.5f} "
          f"(difference {abs(s['auc_adds_exact'] - s['auc_adds_fast']):.5f})")

    # BOP19: VSD, MSSD, MSPD, AR
    load = os.getloadavg()[0]
    r = _fresh(root, "ar")
    t = r["timings"]
    print(f"\n[BOP] evaluate(metrics='ar'): {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU (read {t['read']:.2f}, "
          f"match {t['match']:.2f}, MSSD+MSPD {t.get('mssd_mspd', 0):.2f} with 2 threads, VSD {t.get('vsd', 0):.2f} "
          f"of which waiting for depth images {t.get('depth_wait', 0):.2f}, read ahead in a thread: "
          f"{t.get('depth_read', 0):.2f}); peak memory {r['maxrss_mb']:.0f} MB "
          f"(ru_maxrss, whole process); load average before {load:.1f}")
    a_ = r["summary_all"]
    print("all: " + ", ".join(f"{k} {a_[k]:.4f}" for k in ("ar_vsd", "ar_mssd", "ar_mspd", "ar")))
    b = straightforward_bop(root, a.bop_subset)
    print(f"straightforward (BOP toolkit's way: full-frame renders, every symmetry x every point), timed on "
          f"{b['subset']} random targets and extrapolated to all {b['matched']} matched targets and "
          f"{b['images']} depth images: per target VSD {b['ms_vsd']:.1f} ms, MSSD {b['ms_mssd']:.1f} ms, MSPD "
          f"{b['ms_mspd']:.1f} ms, depth read {b['ms_depth_read']:.1f} ms per image -> {b['total_s']:.0f} s; "
          f"ratio {b['total_s'] / r['wall_s']:.1f}x")
    print(f"check on the subset: decision mismatches VSD {b['mismatches']['vsd']} (of {b['subset'] * 100}), "
          f"MSSD {b['mismatches']['mssd']} (of {b['subset'] * 10}), MSPD {b['mismatches']['mspd']} "
          f"(of {b['subset'] * 10})")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
