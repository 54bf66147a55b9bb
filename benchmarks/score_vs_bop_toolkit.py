"""tdof20's BOP19 scorer against bop_toolkit's official scripts, on the same standard BOP dataset:
wall time of each, the ratio, the largest difference of the average recalls and the number of
decisions (per target, metric, threshold and VSD tau: how many instances are matched) that differ.

    python benchmarks/score_vs_bop_toolkit.py [--images 1500] [--workers 2] [--keep DIR] [--tdof20-only]

The dataset is written here from bop_toolkit's documented format (docs/bop_datasets_format.md) with
the documentation-only helpers of tests/fixtures (no tdof20 code writes it): it poses as IC-MI
("icmi": 640x480, objects 1-6, VSD delta 15 mm) so that the unmodified toolkit reads it. Objects 1-4
appear: 1 a box with discrete 2-fold symmetries, 2 a cylinder (continuous about Z plus a flip),
3 a mug (none), 4 a cylinder whose axis is offset from the model origin (continuous, offset
[15, 0, 0]); 5 and 6 are small boxes in models/ only (the toolkit loads every object of the dataset).
Each image shows 3-4 objects on a table plane seen from 20-40 deg elevation, 15% of images a second
instance of one object (inst_count 2 when both are >= 10% visible); its depth PNG is the rendered
depth with 3% holes and, per object, a random share of see-through pixels (the table's depth), as a
transparent object's sensor depth. Results: per target instance an estimate (45% close, 25% near
the thresholds, 27% far, 3% missing; symmetric objects turned by a symmetry), 5% a lower-scored
second estimate.

VSD's decisions can differ where an error lies within a pixel of a threshold: the toolkit's
rasteriser snaps projected vertices to 1/256 pixel, tdof20 ray casts the exact mesh (its depths
are quantised as the toolkit's 16-bit depth buffer stores them); docs/benchmark.md has the
investigation.

Both sides run in fresh processes, reading every file: tdof20 ``evaluate(..., split="test", metrics="ar")`` (VSD,
MSSD, MSPD, AR); the toolkit ``scripts/eval_bop19_pose.py --renderer_type vispy --num_workers N``
(its eval_calc_errors.py per error type, then eval_calc_scores.py per threshold), whose matches
files give the toolkit's decisions.

The toolkit's environment (once; it is not a tdof20 dependency). The script skips, saying so, when
it is missing:

    git clone https://github.com/thodan/bop_toolkit /work/ext/bop_toolkit
    python3.11 -m venv /work/ext/bopvenv
    /work/ext/bopvenv/bin/pip install "numpy<2" pillow pypng imageio scipy opencv-python-headless \\
        vispy pyopengl scikit-image matplotlib tqdm pytz
    apt-get install -y libegl1 libgl1 libegl-mesa0   # headless EGL (Mesa llvmpipe, EGL_PLATFORM=surfaceless)

(or ``--bop-toolkit DIR --bop-venv DIR``, or the environment variables BOP_TOOLKIT and BOP_VENV).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DATASET = "icmi"  # a BOP dataset the toolkit knows: 640x480, objects 1-6, test scenes 1-6
W, H = 640, 480
K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
USED = (1, 2, 3, 4)
RESULT = f"bench_{DATASET}-test.csv"
TAUS = np.arange(0.05, 0.51, 0.05)


def _meshes():
    """obj_id -> (trimesh, symmetries in models_info form)."""
    import trimesh

    from tests.fixtures import _geometry as g

    out = {o: g.obj_mesh_bop(o) for o in (1, 2, 3)}  # box (discrete), cylinder (continuous + flip), mug
    cyl = trimesh.creation.cylinder(radius=20.0, height=60.0, sections=32)
    cyl.apply_translation([15.0, 0.0, 0.0])  # the axis (0,0,1) through (15, 0, 0): an offset symmetry
    out[4] = (cyl, {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [15.0, 0.0, 0.0]}]})
    for o in (5, 6):
        out[o] = (trimesh.creation.box(extents=[20.0, 15.0, 10.0]), {})
    return out


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, float)
    return Rotation.from_rotvec(np.deg2rad(deg) * a / np.linalg.norm(a)).as_matrix()


def _render(meshes_cam: list, plane: tuple, rays: np.ndarray) -> dict:
    """Ray cast the posed meshes (camera frame) and the table plane z = 0 of the frame ``plane`` (R,
    t): depth (mm, 0 = none), the index of the nearest instance (-1: plane or nothing), the plane's
    depth, each instance's silhouette alone (cast only inside its projected bounding box)."""
    from tdof20.o3d import o3d

    def cast(items, r):
        scene = o3d.t.geometry.RaycastingScene()
        for v, f in items:
            scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
        ans = scene.cast_rays(o3d.core.Tensor(r))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy().astype(np.int64)  # ids are 0, 1, ... in the order added
        hit = np.isfinite(t)
        return np.where(hit, t, 0.0), np.where(hit, gid, -1)

    Rp, tp = plane
    nrm = Rp[:, 2]
    with np.errstate(divide="ignore"):
        zp = (nrm @ tp) / (rays[:, 3:] @ nrm)  # the plane's depth (direction z = 1)
    zp = np.where(np.isfinite(zp) & (zp > 0), zp, 0.0)
    depth, idx = cast(meshes_cam, rays)
    front = (zp > 0) & ((depth == 0) | (zp < depth))
    depth = np.where(front, zp, depth)
    idx = np.where(front, -1, idx)
    full = []
    d = rays[:, 3:]
    for v, f in meshes_cam:  # pixels whose ray direction lies inside the vertices' (x/z, y/z) box
        q = v[:, :2] / v[:, 2:3]
        inside = np.flatnonzero((d[:, 0] >= q[:, 0].min() - 1e-3) & (d[:, 0] <= q[:, 0].max() + 1e-3)
                                & (d[:, 1] >= q[:, 1].min() - 1e-3) & (d[:, 1] <= q[:, 1].max() + 1e-3))
        m = np.zeros(len(rays), bool)
        m[inside] = cast([(v, f)], rays[inside])[0] > 0
        full.append(m)
    return {"depth": depth, "inst": idx, "depth_plane": zp, "full": full}


def make_dataset(out: Path, n_images: int, seed: int = 0) -> dict:
    """Write ``out/bop/icmi`` (models, models_eval, test scenes, targets) and ``out/results/RESULT``."""
    import cv2

    from tests.fixtures import _geometry as g
    from tests.fixtures.bop_standard import save_json

    rng = np.random.default_rng(seed)
    base = out / "bop" / DATASET
    meshes = _meshes()
    for folder in ("models", "models_eval"):
        (base / folder).mkdir(parents=True, exist_ok=True)
        info = {}
        for oid, (m, syms) in meshes.items():
            if folder == "models_eval" and oid in USED:
                m = m.subdivide()  # denser evaluation models, as BOP's remeshed models_eval
            lo, hi = m.bounds
            info[str(oid)] = {"diameter": g.diameter(m.vertices), "min_x": float(lo[0]), "min_y": float(lo[1]),
                              "min_z": float(lo[2]), "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]),
                              "size_z": float(hi[2] - lo[2]), **syms}
            g.write_ply_ascii(base / folder / f"obj_{oid:06d}.ply", m.vertices, m.faces, m.vertex_normals)
        save_json(base / folder / "models_info.json", info)
    diam = {o: info[str(o)]["diameter"] for o in USED}
    save_json(base / "camera.json", {"cx": K[0, 2], "cy": K[1, 2], "depth_scale": 1.0, "fx": K[0, 0],
                                     "fy": K[1, 1], "height": H, "width": W})
    rays = g._rays(K, W, H).reshape(-1, 6)
    targets, rows = [], []
    scenes = np.array_split(np.arange(n_images), 6)
    for sc, ims in zip(range(1, 7), scenes):
        sdir = base / "test" / f"{sc:06d}"
        (sdir / "depth").mkdir(parents=True, exist_ok=True)
        cams, gts, ginfo = {}, {}, {}
        for im in range(len(ims)):
            objs = [int(o) for o in rng.permutation(USED)[: rng.integers(3, 5)]]
            if rng.random() < 0.15:
                objs.append(int(rng.choice(objs)))
            Rt, tt = g.table_frame(rng.uniform(20, 40), rng.uniform(0, 360),
                                   [rng.uniform(-40, 40), rng.uniform(-20, 30), rng.uniform(550, 850)])
            ang0 = rng.uniform(0, 2 * np.pi)
            poses = []
            for k, oid in enumerate(objs):
                a = ang0 + 2 * np.pi * k / len(objs)
                m = meshes[oid][0]
                p = np.array([85.0 * np.cos(a), 85.0 * np.sin(a), -m.bounds[0, 2]])
                poses.append((Rt @ g.rot_z(rng.uniform(0, 2 * np.pi)), Rt @ p + tt))
            r = _render([(meshes[o][0].vertices @ R.T + t, meshes[o][0].faces) for o, (R, t) in zip(objs, poses)],
                        (Rt, tt), rays)
            depth, inst = r["depth"].reshape(H, W), r["inst"].reshape(H, W)
            r["depth_plane"] = r["depth_plane"].reshape(H, W)
            r["full"] = [f.reshape(H, W) for f in r["full"]]
            for k in range(len(objs)):  # see-through pixels: the table's depth
                sel = (inst == k) & (rng.random(depth.shape) < rng.uniform(0.0, 0.4))
                depth[sel] = r["depth_plane"][sel]
            depth[rng.random(depth.shape) < 0.03] = 0
            cv2.imwrite(str(sdir / "depth" / f"{im:06d}.png"), np.round(depth).astype(np.uint16),
                        [cv2.IMWRITE_PNG_COMPRESSION, 1])
            cams[str(im)] = {"cam_K": K.flatten().tolist(), "depth_scale": 1.0}
            gts[str(im)] = [{"cam_R_m2c": R.flatten().tolist(), "cam_t_m2c": t.tolist(), "obj_id": o}
                            for (R, t), o in zip(poses, objs)]
            info_im, vis = [], []
            for k in range(len(objs)):
                full, v = r["full"][k], inst == k
                n_all, n_vis = int(full.sum()), int(v.sum())
                vis.append(n_vis / n_all if n_all else 0.0)
                info_im.append({"bbox_obj": g.bbox_xywh(full), "bbox_visib": g.bbox_xywh(v), "px_count_all": n_all,
                                "px_count_valid": int((depth[full] > 0).sum()), "px_count_visib": n_vis,
                                "visib_fract": vis[-1]})
            ginfo[str(im)] = info_im
            for oid in sorted(set(objs)):
                ks = [k for k, o in enumerate(objs) if o == oid and vis[k] >= 0.1]
                if not ks:
                    continue
                targets.append({"im_id": im, "inst_count": len(ks), "obj_id": oid, "scene_id": sc})
                for k in ks:
                    R, t = poses[k]
                    cat = rng.choice(4, p=[0.45, 0.25, 0.27, 0.03])
                    if cat == 3:
                        continue
                    deg, tau = {0: (rng.uniform(0, 5), rng.uniform(0, 0.05)), 1: (rng.uniform(0, 12),
                                rng.uniform(0.04, 0.14)), 2: (rng.uniform(0, 180), rng.uniform(0.1, 1.0))}[cat]
                    Re = _rot(rng.normal(size=3), deg) @ R
                    if oid in (2, 4):  # turned about the symmetry axis
                        Re = Re @ _rot([0, 0, 1], rng.uniform(0, 360))
                    elif oid == 1 and rng.random() < 0.5:
                        Re = Re @ np.diag([1.0, -1.0, -1.0])
                    v = rng.normal(size=3)
                    te = t + tau * diam[oid] * v / np.linalg.norm(v)
                    rows.append((sc, im, oid, rng.uniform(0.5, 1.0), Re, te))
                    if rng.random() < 0.05:
                        rows.append((sc, im, oid, rng.uniform(0.0, 0.45), _rot(rng.normal(size=3), 90) @ R,
                                     t + rng.normal(size=3) * 0.3 * diam[oid]))
        save_json(sdir / "scene_camera.json", cams)
        save_json(sdir / "scene_gt.json", gts)
        save_json(sdir / "scene_gt_info.json", ginfo)
    save_json(base / "test_targets_bop19.json", targets)
    (out / "results").mkdir(exist_ok=True)
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    lines += [f"{s},{i},{o},{sc:.6f}," + " ".join(f"{x:.9f}" for x in R.reshape(-1)) + ","
              + " ".join(f"{x:.6f}" for x in t) + ",-1" for s, i, o, sc, R, t in rows]
    (out / "results" / RESULT).write_text("\n".join(lines) + "\n")
    meta = {"images": n_images, "targets": len(targets), "instances": int(sum(t["inst_count"] for t in targets)),
            "rows": len(rows), "multi": sum(t["inst_count"] > 1 for t in targets)}
    (out / "meta.json").write_text(json.dumps(meta))
    return meta


def run_tdof20(out: Path) -> dict:
    """In this (fresh) process: evaluate() with the BOP metrics; per object its decisions."""
    t0 = time.perf_counter()
    from tdof20.scoring.scoring import evaluate

    ev = evaluate(out / "results" / RESULT, out / "bop" / DATASET, split="test", metrics="ar")
    summ = ev.summary()["all"]
    wall = time.perf_counter() - t0
    np.savez(out / "tdof20_bop.npz", **{f"{m}_{k}": o.bop[m] for k, o in ev.objects.items() for m in o.bop})
    return {"wall_s": wall, "ar": {k: float(summ[k]) for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd")},
            "timings": ev.timings}


def _tdof20_slots(out: Path) -> dict:
    """(scene, im, obj) -> (obj, first slot, inst_count): where tdof20's per-object decision arrays
    hold each target (its scorer's order: per object, single-instance targets with an estimate,
    then several-instance ones, then those without an estimate, each in the targets' order)."""
    from tdof20.dataset.results import read_results
    from tdof20.scoring.scorer import group_rows

    base = out / "bop" / DATASET
    targets = json.loads((base / "test_targets_bop19.json").read_text())
    groups = group_rows(read_results(out / "results" / RESULT))
    gt = {}
    for sc in {t["scene_id"] for t in targets}:
        gt[sc] = json.loads((base / "test" / f"{sc:06d}" / "scene_gt.json").read_text())
    kinds: dict[int, list] = {}
    for t in targets:
        key = (t["scene_id"], t["im_id"], t["obj_id"])
        n_gt = sum(e["obj_id"] == t["obj_id"] for e in gt[t["scene_id"]][str(t["im_id"])])
        kind = 2 if key not in groups else (0 if t["inst_count"] == 1 and n_gt == 1 else 1)
        kinds.setdefault(t["obj_id"], []).append((kind, key, t["inst_count"]))
    slots = {}
    for ob, lst in kinds.items():
        pos = 0
        for kind in (0, 1, 2):
            for k, key, cnt in lst:
                if k == kind:
                    slots[key] = (ob, pos, cnt)
                    pos += cnt
    return slots


def run_toolkit(out: Path, toolkit: Path, venv: Path, workers: int) -> dict:
    """eval_bop19_pose.py as documented, in the toolkit's venv; its AR figures and decisions."""
    ev_dir = out / "eval"
    shutil.rmtree(ev_dir, ignore_errors=True)
    env = dict(os.environ, PATH=f"{venv / 'bin'}:{os.environ['PATH']}", PYTHONPATH=str(toolkit),
               BOP_PATH=str(out / "bop"), BOP_RESULTS_PATH=str(out / "results"), BOP_EVAL_PATH=str(ev_dir),
               PYOPENGL_PLATFORM="egl", EGL_PLATFORM="surfaceless")  # Mesa EGL without a display
    env.pop("VIRTUAL_ENV", None)
    cmd = [str(venv / "bin" / "python"), str(toolkit / "scripts" / "eval_bop19_pose.py"), "--renderer_type=vispy",
           f"--result_filenames={RESULT}", f"--results_path={out / 'results'}", f"--eval_path={ev_dir}",
           "--targets_filename=test_targets_bop19.json", f"--num_workers={workers}"]
    t0, c0 = time.perf_counter(), _children_cpu()
    log = out / "toolkit.log"
    with open(log, "w") as f:
        rc = subprocess.call(cmd, cwd=toolkit, env=env, stdout=f, stderr=subprocess.STDOUT)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    if rc != 0:
        raise SystemExit(f"bop_toolkit's eval_bop19_pose.py failed (exit {rc}); its log: {log}")
    name = RESULT[:-4]
    rec: dict[str, list] = {"vsd": [], "mssd": [], "mspd": []}
    dec: dict = {}  # (metric, tau index, threshold index) -> {(scene, im, obj): matched count}
    for d in sorted((ev_dir / name).iterdir()):
        if not d.name.startswith("error="):
            continue
        m = d.name.split("=")[1].split("_")[0]  # error=vsd_ntop=-1_delta=15.000_tau=0.050
        ti = round(float(d.name.split("tau=")[1]) / 0.05) - 1 if "tau=" in d.name else 0
        for sf in sorted(d.glob("scores_*.json")):
            th = float(sf.name.split("th=")[1].split("_")[0])
            rec[m].append(json.loads(sf.read_text())["recall"])
            j = round(th / (5.0 if m == "mspd" else 0.05)) - 1
            cnt: dict = {}
            for e in json.loads((d / sf.name.replace("scores_", "matches_")).read_text()):
                if e["est_id"] != -1:
                    key = (e["scene_id"], e["im_id"], e["obj_id"])
                    cnt[key] = cnt.get(key, 0) + 1
            dec[(m, ti, j)] = cnt
    ar = {f"ar_{m}": float(np.mean(v)) for m, v in rec.items()}
    ar["ar"] = float(np.mean([ar["ar_vsd"], ar["ar_mssd"], ar["ar_mspd"]]))
    assert len(rec["vsd"]) == 100 and len(rec["mssd"]) == 10 and len(rec["mspd"]) == 10, {k: len(v) for k, v in rec.items()}
    return {"wall_s": wall, "cpu_s": cpu, "ar": ar, "decisions": dec}


def _children_cpu() -> float:
    """CPU seconds (user + system, every thread) of the finished child processes and theirs: a
    figure the machine's load changes far less than wall time."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def compare(out: Path, tk: dict) -> dict:
    """Count (target, metric, tau, threshold) whose number of matched instances differs."""
    fast = np.load(out / "tdof20_bop.npz")
    slots = _tdof20_slots(out)
    n = diff = 0
    per_metric = {"vsd": 0, "mssd": 0, "mspd": 0}
    where: dict = {}  # (scene, im, obj) -> differing decisions
    for key, (ob, s0, cnt) in slots.items():
        for m in ("vsd", "mssd", "mspd"):
            arr = fast[f"{m}_{ob}"][s0:s0 + cnt]
            if m != "vsd":
                arr = arr[:, None, :]
            got = arr.sum(axis=0)  # (taus or 1, thresholds)
            for ti in range(got.shape[0]):
                for j in range(got.shape[1]):
                    n += 1
                    if int(got[ti, j]) != tk["decisions"][(m, ti, j)].get(key, 0):
                        diff += 1
                        per_metric[m] += 1
                        where[key] = where.get(key, 0) + 1
    return {"decisions": n, "differ": diff, "per_metric": per_metric, "targets": where}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=1500)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="the toolkit's --num_workers")
    ap.add_argument("--keep", type=Path, help="dataset folder, reused when it holds one of --images images")
    ap.add_argument("--bop-toolkit", type=Path, default=Path(os.environ.get("BOP_TOOLKIT", "/work/ext/bop_toolkit")))
    ap.add_argument("--bop-venv", type=Path, default=Path(os.environ.get("BOP_VENV", "/work/ext/bopvenv")))
    ap.add_argument("--tdof20-only", action="store_true", help="time tdof20 alone (e.g. while profiling)")
    ap.add_argument("--reuse-toolkit", action="store_true",
                    help="reuse the toolkit's figures of an earlier run on the --keep dataset (they are saved there)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of tdof20 (the best is reported)")
    ap.add_argument("--_tdof20", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._tdof20 is not None:
        print(json.dumps(run_tdof20(a._tdof20)))
        return
    if not a.tdof20_only and not ((a.bop_toolkit / "scripts" / "eval_bop19_pose.py").exists()
                                  and (a.bop_venv / "bin" / "python").exists()):
        print(f"skipped: bop_toolkit ({a.bop_toolkit}) or its venv ({a.bop_venv}) is missing; see this script's "
              "docstring for how to make them, or run with --tdof20-only")
        return
    tmp = None
    if a.keep is None:
        tmp = tempfile.TemporaryDirectory(prefix="score_vs_bop_")
        out = Path(tmp.name)
    else:
        out = a.keep
    meta_p = out / "meta.json"
    if not (meta_p.exists() and json.loads(meta_p.read_text())["images"] == a.images):
        shutil.rmtree(out / "bop", ignore_errors=True)
        t0 = time.perf_counter()
        meta = make_dataset(out, a.images)
        print(f"wrote the dataset in {time.perf_counter() - t0:.0f} s")
    meta = json.loads(meta_p.read_text())
    print(f"dataset ({out}): {meta['images']} images of {W}x{H}, {meta['targets']} targets "
          f"({meta['instances']} instances, {meta['multi']} with several), {meta['rows']} estimates")
    tk = None
    if not a.tdof20_only:  # the toolkit first: its (long) run is saved and can be reused with --reuse-toolkit
        saved = out / "toolkit_result.json"
        if a.reuse_toolkit and saved.exists():
            tk = json.loads(saved.read_text())
            tk["decisions"] = {tuple(json.loads(k)): {tuple(json.loads(kk)): v for kk, v in d.items()}
                               for k, d in tk["decisions"].items()}
            print(f"bop_toolkit: the figures of its run at {tk['when']} (saved in {saved})")
        else:
            tk = run_toolkit(out, a.bop_toolkit, a.bop_venv, a.workers)
            tk["when"] = time.strftime("%Y-%m-%d %H:%M")
            tk["load"] = os.getloadavg()[0]
            tk["workers"] = a.workers
            saved.write_text(json.dumps({**tk, "decisions": {json.dumps(k): {json.dumps(kk): v for kk, v in d.items()}
                                                            for k, d in tk["decisions"].items()}}))
    runs = []
    for _ in range(a.repeat):
        c0 = _children_cpu()
        p = subprocess.run([sys.executable, __file__, "--_tdof20", str(out)], capture_output=True, text=True, check=False)
        if p.returncode != 0:
            raise SystemExit(p.stderr)
        runs.append(dict(json.loads(p.stdout.strip().splitlines()[-1]), cpu_s=_children_cpu() - c0))
    td = min(runs, key=lambda r: r["wall_s"])
    load = os.getloadavg()[0]
    t = td["timings"]
    print(f"tdof20 evaluate(metrics='ar'), fresh process, best of {len(runs)}: "
          + ", ".join(f"{r['wall_s']:.2f}" for r in runs) + f" s wall (vsd {t.get('vsd', 0):.2f}, mssd+mspd "
          f"{t.get('mssd_mspd', 0):.2f}, read {t.get('read', 0):.2f}), {td['cpu_s']:.1f} s CPU; load average {load:.1f}")
    print("tdof20: " + ", ".join(f"{k} {v:.12f}" for k, v in td["ar"].items()))
    if a.tdof20_only:
        return
    print(f"bop_toolkit eval_bop19_pose.py --renderer_type=vispy --num_workers={tk['workers']}: {tk['wall_s']:.1f} s "
          f"wall, {tk['cpu_s']:.1f} s CPU; load average after it {tk['load']:.1f}")
    print("toolkit: " + ", ".join(f"{k} {v:.12f}" for k, v in tk["ar"].items()))
    c = compare(out, tk)
    dmax = max(abs(td["ar"][k] - tk["ar"][k]) for k in tk["ar"])
    print(f"ratio {tk['wall_s'] / td['wall_s']:.1f}x wall, {tk['cpu_s'] / td['cpu_s']:.1f}x CPU; "
          f"max |AR difference| {dmax:.2e}; decisions differing: "
          f"{c['differ']} of {c['decisions']} ({', '.join(f'{k} {v}' for k, v in c['per_metric'].items())})")
    if c["targets"]:  # where to look: the toolkit's errors_*.json under --keep's eval/ hold its values
        print(f"in {len(c['targets'])} targets (scene, image, object): "
              + ", ".join(f"{k} {v}" for k, v in sorted(c["targets"].items())[:8])
              + (" ..." if len(c["targets"]) > 8 else ""))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
