"""Import the released TDoF20 (MightyCrane/HFF6DoF's layout) as a tdof20 dataset.

    summary = import_tdof20(SRC, ROOT)               # writes ROOT; resumes an interrupted import
    summary = import_tdof20(SRC, ROOT, check=True)   # reads and checks everything, writes nothing

What ROOT holds (the layout of :mod:`tdof20.dataset.build`, docs/tdof20_release.md)::

    ROOT/dataset_info.json     "source": "tdof20-release", scenes, objects, units, depth modes, im_id rule
    ROOT/camera.json           the release's intrinsics (depth_scale in mm per unit)
    ROOT/models/               obj_{class id:06d}.ply in mm, models_info.json, keypoints.json (centre + 8 released)
    ROOT/scenes/{scene_id:06d}/  rgb/{im:06d}.jpg (the release's bytes), depth/ (broken_depth: the sensor),
                               depth_stabilized/ (the release's depth/), depth_restored/ (rendered models
                               composited into the stabilized depth), mask/ (rendered), mask_visib/ (class-id
                               mask), scene_camera/gt/gt_info.json, scene_info.json (stems of the images)
    ROOT/splits/{simple,hard}_{train,test}.json, splits/visual.json   exactly the release's lists
    ROOT/test_targets_{simple,hard}.json

Scene ids: single/<class> -> its class id (line of classes.txt), multi/NN -> n_classes + 1 + NN.
Every input is read and checked (units detected, one frame per scene rendered against its mask)
before anything is written (``check=True`` also decodes every mask and depth, as the import does).
The import writes into ``.ROOT.importing/`` beside ROOT and moves it into place at the end, so a
refusal half-way leaves ROOT as it was; ``.import.json`` in it marks an import under way; each
scene is finished when its scene_info.json is written; a rerun continues.
"""

from __future__ import annotations

import os
import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from tdof20.dataset.layouts.base import TARGET_MIN_VISIB
from tdof20.errors import TdofError
from tdof20.formats import (BopSceneWriter, atomic_write_bytes, check_output_dir, model_path, png_header, read_bytes,
                            read_json, read_png, write_json, write_model_mesh, write_models_info)
from tdof20.formats.tdof20_release import (ClassGeometry, Release, image_size, pose_units, read_class_mask,
                                           read_geometry, read_pose, read_release)
from tdof20.geometry import PinholeCamera
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.geometry.transforms import rotation_about_axis
from tdof20.objects import object_by_name
from tdof20.progress import progress

SOURCE = "tdof20-release"
MARKER = ".import.json"
MIN_MASK_IOU = 0.5      # the released mask and the models rendered at the poses must overlap this much
SPLIT_LISTS = {"simple_train": "train", "simple_test": "test", "hard_train": "hard_train", "hard_test": "hard_test"}
DEPTH_MODES = {"raw": "depth/: the release's broken_depth/ (the sensor's depth, holes = 0)",
               "stabilized": "depth_stabilized/: the release's depth/ (stabilized, hole-filled)",
               "restored": "depth_restored/: the models rendered at the poses, composited into the stabilized depth"}
FLUSH_EVERY = 100
IOU_FILE = ".mask_iou.json"  # a scene's per-frame mask IoUs while it is imported


# ---------------------------------------------------------------------------------------------
# checks of --out
# ---------------------------------------------------------------------------------------------
def _out_state(out: Path, src: Path, scenes: list[str]) -> str:
    """'new' | 'resume' (an import of the same source and scenes is here); anything else is refused."""
    check_output_dir(out, "--out", "folder for the dataset")
    o, s = out.resolve(), src.resolve()
    if o == s or s in o.parents:
        raise TdofError(f"--out lies inside the release folder {src}: choose a folder outside it", out)
    if not out.exists() or not any(out.iterdir()):
        return "new"
    want = {"source_path": str(s), "scenes": sorted(scenes)}
    for name, what in ((MARKER, "an unfinished import"), ("dataset_info.json", "a dataset")):
        p = out / name
        if p.exists():
            info = read_json(p)
            got = {"source_path": info.get("source_path"), "scenes": sorted((info.get("scenes") or {}).values())
                   if name == "dataset_info.json" else sorted(info.get("scenes") or [])} if isinstance(info, dict) else {}
            if isinstance(info, dict) and (name == MARKER or info.get("source") == SOURCE) and got == want:
                return "resume"
            raise TdofError(f"holds {what} of other data ({name}): import into a new or empty folder, or rerun the "
                            "same import (same SRC and --scenes) to finish it", out)
    raise TdofError("folder is not empty and holds no import of this release; choose another --out", out)


# ---------------------------------------------------------------------------------------------
# reading and checking everything
# ---------------------------------------------------------------------------------------------
def _poses(rel: Release, frames: dict[str, list[int]], show_progress: bool) -> tuple[dict, dict]:
    poses, paths = {}, {}
    n = sum(len(v) for v in frames.values())
    with progress(show_progress and n > 200) as bar:
        task = bar.add_task("reading poses", total=n)
        for scene, ims in frames.items():
            single = rel.class_id(scene.split("/", 1)[1]) if scene.startswith("single/") else None
            for im in ims:
                p = rel.frame_path(scene, im, "pose")
                fp = read_pose(p, len(rel.classes))
                if single is not None and set(fp.cls_ids.tolist()) != {single}:
                    raise TdofError(f"a frame of the single-object scene {scene} lists classes {fp.cls_ids.tolist()}: "
                                    f"expected only {single} ({rel.classes[single - 1]})", p)
                poses[(scene, im)] = fp
                paths[(scene, im)] = p
                bar.advance(task)
    return poses, paths


def _check_images(rel: Release, frames: dict[str, list[int]], size: tuple[int, int] | None,
                  show_progress: bool) -> tuple[int, int]:
    """Every listed frame's files from their headers: JPEG colour, 16-bit depths, grey/palette masks, one size."""
    n = sum(len(v) for v in frames.values())
    ref, first = size, None
    with progress(show_progress and n > 200) as bar:
        task = bar.add_task("checking images", total=n)
        for scene, ims in frames.items():
            for im in ims:
                p = rel.frame_path(scene, im, "rgb")
                hw = image_size(p, "colour image")
                checks = [(p, hw)]
                for sub in ("broken_depth", "depth"):
                    q = rel.frame_path(scene, im, sub)
                    checks.append((q, png_header(q, "depth")))
                q = rel.frame_path(scene, im, "mask")
                data = read_bytes(q, "mask file", limit=33)
                hdr = png_header(q, "any", data)
                bits, colour = data[24], data[25]
                if colour not in (0, 2, 3, 6) or bits > 16:  # grey, RGB(A) of equal channels, palette
                    raise TdofError(f"the mask must be a grey, palette or RGB PNG of class ids, found colour type "
                                    f"{colour} with {bits} bits", q)
                checks.append((q, hdr))
                for path, hw in checks:
                    if ref is None:
                        ref, first = hw, path
                    if hw != ref:
                        where = f"{first}" if first else "intrinsics.json"
                        raise TdofError(f"the image is {hw[1]}x{hw[0]} (width x height), {where} gives {ref[1]}x{ref[0]}: "
                                        "one image size for the release", path)
                bar.advance(task)
    return ref


def _camera(rel: Release, hw: tuple[int, int]):
    K = rel.intrinsics.K
    h, w = hw
    if not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
        raise TdofError(f"the principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {w}x{h} images: these "
                        "intrinsics do not belong to them", rel.root / "dataset_config" / "intrinsics.json")
    return PinholeCamera(K, w, h, rel.intrinsics.depth_scale_mm)


def _transforms(fp, f_pose: float) -> list[np.ndarray]:
    out = []
    for R, t in zip(fp.R, fp.t):
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = t * f_pose
        out.append(T)
    return out


def _split_class(pix: np.ndarray, members: list[int], lab) -> list[np.ndarray]:
    """The pixels of one class id seen twice in a frame, split between its instances: each pixel
    goes to the instance whose rendered visible (else full) region is nearest."""
    lbl = np.zeros(pix.shape, np.int32)
    for j, i in enumerate(members):
        lbl[lab.visible == i] = j + 1
    if not lbl.any():
        for j, i in enumerate(members):
            lbl[lab.full[i] & (lbl == 0)] = j + 1
    if not lbl.any():
        return [pix.copy()] + [np.zeros_like(pix) for _ in members[1:]]
    from scipy.ndimage import distance_transform_edt  # on first use: importing the importer stays light

    _, (iy, ix) = distance_transform_edt(lbl == 0, return_indices=True)
    nearest = lbl[iy, ix]
    return [pix & (nearest == j + 1) for j in range(len(members))]


def _check_class_ids(cmask: np.ndarray, n_classes: int, path: Path) -> None:
    vals = np.unique(cmask)
    bad = [int(v) for v in vals if v != 0 and not 1 <= v <= n_classes]
    if bad:
        raise TdofError(f"holds class id {bad[0]}, which is not in classes.txt (ids 1..{n_classes})", path)


def _read_frames(rel: Release, frames: dict[str, list[int]], camera, show_progress: bool) -> None:
    """What the import decodes, for ``--check``: every frame's class-id mask (its size and class
    ids) and both depth PNGs, so that a check that passes is an import that passes."""
    n = sum(len(v) for v in frames.values())
    with progress(show_progress and n > 200) as bar:
        task = bar.add_task("reading masks and depths", total=n)
        for scene, ims in frames.items():
            for im in ims:
                mpath = rel.frame_path(scene, im, "mask")
                cmask = read_class_mask(mpath)
                if cmask.shape != (camera.height, camera.width):
                    raise TdofError(f"the mask is {cmask.shape[1]}x{cmask.shape[0]}, the images "
                                    f"{camera.width}x{camera.height}", mpath)
                _check_class_ids(cmask, len(rel.classes), mpath)
                for sub in ("broken_depth", "depth"):
                    read_png(rel.frame_path(scene, im, sub), "depth")
                bar.advance(task)


def _labels(fp, cmask: np.ndarray, lab, n_classes: int, path: Path) -> tuple[list[np.ndarray], dict]:
    """Visible masks per instance from the class-id mask; what was odd about the frame."""
    _check_class_ids(cmask, n_classes, path)
    odd = {"split": 0, "unposed_px": int(np.count_nonzero((cmask > 0) & ~np.isin(cmask, fp.cls_ids)))}
    visib: list[np.ndarray] = [None] * len(fp.cls_ids)
    for c, n in Counter(fp.cls_ids.tolist()).items():
        members = [i for i, x in enumerate(fp.cls_ids.tolist()) if x == c]
        pix = cmask == c
        if n == 1:
            visib[members[0]] = pix
        else:
            odd["split"] += 1
            for i, m in zip(members, _split_class(pix, members, lab)):
                visib[i] = m
    return visib, odd


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.count_nonzero(a | b)
    return 1.0 if u == 0 else float(np.count_nonzero(a & b) / u)


def _precheck_scene(rel: Release, scene: str, im: int, fp, f_pose: float, raycaster, camera) -> float:
    """Render the scene's first frame: the mask must agree with the models at the poses, and the
    depth (read with depth_scale) must lie where the objects are."""
    lab = raycaster.render(list(zip(fp.cls_ids.tolist(), _transforms(fp, f_pose))))
    mpath = rel.frame_path(scene, im, "mask")
    cmask = read_class_mask(mpath)
    if cmask.shape != (camera.height, camera.width):
        raise TdofError(f"the mask is {cmask.shape[1]}x{cmask.shape[0]}, the images {camera.width}x{camera.height}", mpath)
    visib, _ = _labels(fp, cmask, lab, len(rel.classes), mpath)
    ious = [_iou(v, lab.visible == i) for i, v in enumerate(visib)]
    iou = float(np.median(ious))
    if iou < MIN_MASK_IOU:
        raise TdofError(f"the class-id mask and the models rendered at the poses of {rel.frame_path(scene, im, 'pose').name} "
                        f"overlap only {iou:.2f} (IoU, median over {len(ious)} instances; at least {MIN_MASK_IOU} "
                        "expected): the poses (model to camera?), their units or the intrinsics do not fit the "
                        "images", mpath)
    dpath = rel.frame_path(scene, im, "depth")
    d = read_png(dpath, "depth").astype(np.float64) * camera.depth_scale
    z = np.median(fp.t[:, 2] * f_pose)
    valid = d[d > 0]
    if valid.size and not (1 / 3 <= np.median(valid) / z <= 3):
        raise TdofError(f"with depth_scale read as {camera.depth_scale:g} mm per unit this depth lies at "
                        f"{np.median(valid):.0f} mm, the objects at {z:.0f} mm: depth_scale of intrinsics.json does not "
                        "fit the depth images", dpath)
    return iou


def _symmetries(geo: dict[int, ClassGeometry]) -> dict[int, tuple[dict, str]]:
    """BOP symmetries per class from the catalog when the class name is one of ours and its
    symmetries map the released mesh onto itself (95 % of surface samples within 1 % of the
    diameter); else none. -> {class id: (models_info keys, a note)}."""
    from tdof20.o3d import o3d

    out = {}
    for cid, g in geo.items():
        try:
            obj = object_by_name(g.name)
        except TdofError:
            out[cid] = ({}, f"{g.name}: not in our catalog, no symmetries")
            continue
        info = obj.models_info()
        keys = {k: info[k] for k in ("symmetries_continuous", "symmetries_discrete") if k in info}
        if not keys:
            out[cid] = ({}, f"{g.name}: no symmetries (the catalog's)")
            continue
        Ts = [np.asarray(T, float).reshape(4, 4) for T in keys.get("symmetries_discrete", [])]
        for s in keys.get("symmetries_continuous", []):
            Ts += [rotation_about_axis(np.asarray(s["axis"], float), a, np.asarray(s["offset"], float))
                   for a in np.radians([37.0, 90.0, 180.0])]
        sc = o3d.t.geometry.RaycastingScene()
        sc.add_triangles(o3d.core.Tensor(g.vertices.astype(np.float32)), o3d.core.Tensor(g.faces.astype(np.uint32)))
        P = sample_mesh_surface(g.vertices, g.faces, 3000, 0)
        worst = 0.0
        for T in Ts:
            Q = (P @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
            worst = max(worst, float(np.percentile(sc.compute_distance(o3d.core.Tensor(Q)).numpy(), 95)))
        if worst <= 0.01 * g.diameter:
            out[cid] = (keys, f"{g.name}: symmetries of our catalog ({', '.join(k.split('_')[1] for k in keys)}), "
                              "checked on the released mesh")
        else:
            out[cid] = ({}, f"{g.name}: our catalog's symmetries do not map the released mesh onto itself "
                            f"({worst:.1f} mm off): no symmetries")
    return out


# ---------------------------------------------------------------------------------------------
# the import
# ---------------------------------------------------------------------------------------------
def import_tdof20(src: str | Path, out: str | Path | None, *, check: bool = False, scenes=None,
                  show_progress: bool = True) -> dict:
    """Import the TDoF20 release in ``src`` into the tdof20 dataset ``out`` (see the module doc);
    ``check=True`` reads and checks everything and writes nothing; ``scenes``: only these
    (``single/<class>``, ``multi/NN``). Returns a summary of what was found (and written)."""
    src = Path(src)
    state = None
    if not check:
        if out is None:
            raise TdofError("give --out (or --check)")
        out = Path(out)
        if not src.is_dir():
            raise TdofError("no such folder (the TDoF20 release)", src)
    rel = read_release(src, scenes)
    frames = rel.frames()
    if not frames:
        raise TdofError("the lists name no frame of the scenes read: nothing to import", src / "dataset_config")
    if not check:
        state = _out_state(out, src, list(frames))
    geo = read_geometry(rel)
    poses, paths = _poses(rel, frames, show_progress)
    f_pose, pose_text = pose_units(poses, paths)
    intr = rel.intrinsics
    hw = _check_images(rel, frames, (intr.height, intr.width) if intr.width else None, show_progress)
    camera = _camera(rel, hw)
    from tdof20.geometry.raycast import ModelRaycaster  # imports open3d at top level

    raycaster = ModelRaycaster({cid: (g.vertices, g.faces) for cid, g in geo.items()}, camera)
    first_iou = {s: _precheck_scene(rel, s, ims[0], poses[(s, ims[0])], f_pose, raycaster, camera)
                 for s, ims in frames.items()}
    syms = _symmetries(geo)

    summary = {
        "source": str(src), "classes": list(rel.classes),
        "scenes": {s: len(v) for s, v in frames.items()},
        "scene_ids": {s: rel.scene_id(s) for s in frames},
        "lists": {k: sum(1 for s, _ in v if s in frames) for k, v in rel.lists.items()},
        "list_files": {k: v.name for k, v in rel.list_files.items()},
        "list_forms": rel.list_forms,
        "units": {"models": {g.name: g.units for g in geo.values()}, "poses": pose_text,
                  "depth": f"{camera.depth_scale:g} mm per unit"},
        "intrinsics": intr.found, "image_size": [camera.width, camera.height],
        "im_id_rule": sorted({rel.scenes[s].im_id_rule for s in frames}),
        "mask_iou_first_frame": {s: round(v, 3) for s, v in first_iou.items()},
        "symmetries": [n for _, n in syms.values()],
        "notes": list(rel.notes) + ([f"scenes not read (--scenes): {', '.join(rel.missing_scenes)}"]
                                    if rel.missing_scenes else []),
        "written": False,
    }
    if check:
        _read_frames(rel, frames, camera, show_progress)
        return summary

    # ------------------------------------------------------------------ write
    # into a work folder beside --out, moved into place at the end: a refusal half-way leaves --out as it was
    dest = out
    out, fresh = _work_folder(dest, src, list(frames), state)
    try:
        _write_all(rel, frames, geo, syms, poses, f_pose, raycaster, camera, summary, src, out, show_progress)
    except TdofError:
        if fresh:
            shutil.rmtree(out, ignore_errors=True)
        raise
    if out != dest:
        os.replace(out, dest)
    summary.update(written=True, out=str(dest), resumed=state == "resume" or not fresh)
    return summary


def _work_folder(out: Path, src: Path, scenes: list[str], state: str) -> tuple[Path, bool]:
    """Where the import writes: --out itself when it holds this import already (or its parent
    cannot be written), else ``.{name}.importing`` beside it (resumed when it holds this import).
    -> (folder, whether this run starts it)."""
    up = next(p for p in out.absolute().parents if p.exists())
    if state == "resume" or not os.access(up, os.W_OK | os.X_OK):
        return out, False
    work = out.parent / f".{out.name}.importing"
    return work, _out_state(work, src, scenes) == "new"


def _write_all(rel: Release, frames: dict, geo: dict, syms: dict, poses: dict, f_pose: float, raycaster, camera,
               summary: dict, src: Path, out: Path, show_progress: bool) -> None:
    intr = rel.intrinsics
    out.mkdir(parents=True, exist_ok=True)
    src_abs = str(src.resolve())
    write_json(out / MARKER, {"source_path": src_abs, "scenes": sorted(frames)})
    mdir = out / "models"
    infos, kps = {}, {}
    for cid, g in geo.items():
        write_model_mesh(model_path(mdir, cid), g.vertices, g.faces)
        lo, size = g.vertices.min(0), np.ptp(g.vertices, axis=0)
        infos[cid] = {"diameter": g.diameter, "min_x": lo[0], "min_y": lo[1], "min_z": lo[2], "size_x": size[0],
                      "size_y": size[1], "size_z": size[2], **syms[cid][0], "name": g.name,
                      "diameter_mesh": round(g.mesh_extent, 6)}
        kps[str(cid)] = np.round(g.keypoints, 6).tolist()
    write_models_info(mdir, infos)
    write_json(mdir / "keypoints.json", kps)
    write_json(out / "camera.json", {"cx": camera.cx, "cy": camera.cy, "fx": camera.fx, "fy": camera.fy,
                                     "width": camera.width, "height": camera.height,
                                     "depth_scale": camera.depth_scale})
    odd_total: Counter = Counter()
    with progress(show_progress) as bar:
        for scene, ims in frames.items():
            odd = _write_scene(rel, scene, ims, poses, f_pose, raycaster, camera, out, bar)
            odd_total.update(odd)
    _write_splits(rel, frames, out)
    info = {"name": "tdof20", "format": "bop", "source": SOURCE, "source_path": src_abs,
            "scenes": {str(rel.scene_id(s)): s for s in frames},
            "layout": {str(rel.scene_id(s)): {"frames": len(ims), "folder": str(rel.scenes[s].folder.relative_to(rel.root))}
                       for s, ims in frames.items()},
            "objects": {str(cid): g.name for cid, g in geo.items()},
            "splits": {"simple": f"the release's {rel.list_files['train'].name} / {rel.list_files['test'].name}",
                       "hard": f"the release's {rel.list_files['hard_train'].name} / {rel.list_files['hard_test'].name}",
                       "visual": rel.list_files["visual"].name if "visual" in rel.list_files else None},
            "rgb_ext": ".jpg", "depth_modes": DEPTH_MODES, "units": summary["units"], "intrinsics": intr.found,
            "im_id_rule": summary["im_id_rule"], "symmetries": summary["symmetries"],
            "target_min_visib_fract": TARGET_MIN_VISIB, "notes": summary["notes"]}
    if odd_total["split"]:
        info["notes"].append(f"{odd_total['split']} times a class appeared twice in a frame: its mask pixels were "
                             "split between the instances by their rendered silhouettes")
    if odd_total["unposed_px"]:
        info["notes"].append(f"{odd_total['unposed_px']} mask pixels carry a class with no pose in their frame: ignored")
    write_json(out / "dataset_info.json", info)
    (out / MARKER).unlink(missing_ok=True)
    summary["notes"] = info["notes"]


def _write_scene(rel: Release, scene: str, ims: list[int], poses: dict, f_pose: float, raycaster, camera,
                 out: Path, bar) -> Counter:
    sid = rel.scene_id(scene)
    d = out / "scenes" / f"{sid:06d}"
    sc = rel.scenes[scene]
    task = bar.add_task(f"importing {scene}", total=len(ims))
    odd: Counter = Counter()
    info_path = d / "scene_info.json"
    if info_path.exists():
        done_info = read_json(info_path)
        if isinstance(done_info, dict) and sorted(int(k) for k in done_info.get("stems", {})) == ims:
            bar.advance(task, len(ims))
            return Counter(done_info.get("odd", {}))
        info_path.unlink()
    done = set()
    if (d / "scene_gt.json").exists():
        done = {int(k) for k in read_json(d / "scene_gt.json")}
    bar.advance(task, len(done & set(ims)))
    # each frame's mask IoUs, kept beside the scene's files as they are flushed, so that a resumed
    # import's mask_iou_mean covers every frame, not only the last run's
    iou_path = d / IOU_FILE
    saved = read_json(iou_path) if iou_path.exists() and done else {}
    ious: dict[int, list[float]] = {int(k): v for k, v in saved.items() if int(k) in done} \
        if isinstance(saved, dict) else {}
    with BopSceneWriter(d) as writer:
        try:
            for n, im in enumerate(i for i in ims if i not in done):
                odd.update(_write_frame(rel, scene, im, poses[(scene, im)], f_pose, raycaster, camera, d, writer,
                                        ious))
                bar.advance(task)
                if (n + 1) % FLUSH_EVERY == 0:
                    write_json(iou_path, ious, indent=None)  # before the frames it covers are flushed
                    writer.flush()
        finally:
            if ious:
                write_json(iou_path, ious, indent=None)
    every = [v for im in ims for v in ious.get(im, [])]
    write_json(info_path, {"scene_id": scene, "source": str(sc.folder.relative_to(rel.root)), "frames": len(ims),
                           "im_id_rule": sc.im_id_rule, "stems": {str(i): sc.stems[i] for i in ims},
                           "mask_iou_mean": round(float(np.mean(every)), 4) if every else None,
                           "odd": dict(odd)})
    iou_path.unlink(missing_ok=True)
    return odd


def _write_frame(rel: Release, scene: str, im: int, fp, f_pose: float, raycaster, camera, d: Path, writer,
                 ious: dict) -> Counter:
    """One frame into the scene writer (its mask IoUs into ``ious``); what was odd about it."""
    Ts = _transforms(fp, f_pose)
    ids = fp.cls_ids.tolist()
    lab = raycaster.render(list(zip(ids, Ts)))
    mpath = rel.frame_path(scene, im, "mask")
    cmask = read_class_mask(mpath)
    if cmask.shape != (camera.height, camera.width):
        raise TdofError(f"the mask is {cmask.shape[1]}x{cmask.shape[0]}, the images "
                        f"{camera.width}x{camera.height}", mpath)
    visib, odd = _labels(fp, cmask, lab, len(rel.classes), mpath)
    ious[im] = [_iou(v, lab.visible == i) for i, v in enumerate(visib)]
    full = [f | v for f, v in zip(lab.full, visib)]
    broken = read_png(rel.frame_path(scene, im, "broken_depth"), "depth")
    stab = read_png(rel.frame_path(scene, im, "depth"), "depth")
    restored = stab.copy()
    hit = lab.visible >= 0
    restored[hit] = camera.mm_to_depth(lab.depth[hit])
    atomic_write_bytes(d / "rgb" / f"{im:06d}.jpg", read_bytes(rel.frame_path(scene, im, "rgb"), "colour image"))
    writer.add_frame(im, camera.K, camera.depth_scale, [(c, T[:3, :3], T[:3, 3]) for c, T in zip(ids, Ts)],
                     full, visib, depth=broken, extra={"depth_stabilized": stab, "depth_restored": restored})
    return Counter(odd)


def _write_splits(rel: Release, frames: dict[str, list[int]], out: Path) -> None:
    """splits/*.json exactly from the lists (the scenes imported), test targets from scene_gt_info."""
    def members(key: str) -> dict[str, list[int]]:
        m: dict[int, list[int]] = {}
        for s, im in rel.lists.get(key, []):
            if s in frames:
                m.setdefault(rel.scene_id(s), []).append(im)
        return {str(k): sorted(v) for k, v in sorted(m.items())}

    gts, infos = {}, {}
    for s in frames:
        d = out / "scenes" / f"{rel.scene_id(s):06d}"
        gts[rel.scene_id(s)] = read_json(d / "scene_gt.json")
        infos[rel.scene_id(s)] = read_json(d / "scene_gt_info.json")
    for name, key in SPLIT_LISTS.items():
        m = members(key)
        write_json(out / "splits" / f"{name}.json", m)
        if name.endswith("_test"):
            targets = []
            for sid_s, ims in m.items():
                sid = int(sid_s)
                for im in ims:
                    counts = Counter(g["obj_id"] for g, gi in zip(gts[sid][str(im)], infos[sid][str(im)])
                                     if gi["visib_fract"] >= TARGET_MIN_VISIB)
                    targets += [{"scene_id": sid, "im_id": im, "obj_id": int(o), "inst_count": int(c)}
                                for o, c in sorted(counts.items())]
            write_json(out / f"test_targets_{name.split('_')[0]}.json", targets, indent=None)
    write_json(out / "splits" / "visual.json", members("visual"))
