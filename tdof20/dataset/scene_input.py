"""The annotated scenes a build takes, checked before anything is written, and copied in whole.

An annotated scene is a BOP scene folder with ``scene_info.json`` ({"scene_id": "multi/08",
"n_arms", "steps", ...}) and ``models/`` — what ``tdof20 annotate`` writes (and ``tdof20 sim
label`` from the simulator's truth). Both writers (:mod:`tdof20.dataset.build` for tdof20's
layout, :mod:`tdof20.dataset.build_bop` for BOP's) read their inputs here: every scene's files,
every image's PNG header, its labels against its own models, one model per object across scenes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import numpy as np

from tdof20.dataset.models import load_models
from tdof20.dataset.splits import scene_name, scene_number
from tdof20.errors import TdofError
from tdof20.formats import check_output_dir, check_scene_images, read_bytes, read_json, read_models_info, read_scene
from tdof20.formats.bop import SCENE_CAMERA, SCENE_GT, median_distance_if_metres
from tdof20.formats.bop_uncertainty import read_uncertainty
from tdof20.formats.session import MAX_STEPS

MAX_ARMS = 64  # arm positions of a scene (TDoF20: 4); bounds a typo before the split rules loop over them
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")
BUILD_MARKER = ".build.json"  # the scene list of a build under way; removed when it is done


def scene_info(scene_dir: Path) -> dict:
    info = read_json(scene_dir / "scene_info.json")
    if not isinstance(info, dict):
        raise TdofError(f"must hold a JSON object, got {type(info).__name__}", scene_dir / "scene_info.json")
    for k in ("scene_id", "steps", "n_arms"):
        if k not in info:
            raise TdofError(f"missing field '{k}'", scene_dir / "scene_info.json")
    for k, hi in (("steps", MAX_STEPS), ("n_arms", MAX_ARMS)):
        if isinstance(info[k], bool) or not isinstance(info[k], int) or not 1 <= info[k] <= hi:
            raise TdofError(f"{k} must be an integer in 1..{hi}, got {info[k]!r}", scene_dir / "scene_info.json")
    try:
        scene_number(info["scene_id"])  # checks the name
    except TdofError as e:
        raise TdofError(str(e), scene_dir / "scene_info.json") from None
    return info


#: the median valid depth x depth_scale of the first labelled image, over its objects' median
#: distance, must lie in this range (the table and room are near the objects; a depth_scale giving
#: metres or micrometres is 1000 times off)
DEPTH_RATIO = (0.2, 5.0)


def check_labels(d: Path, scene, models: dict[int, dict]) -> None:
    """What a label must be before it joins a dataset: an object of the scene's models/, a
    translation in millimetres, a depth_scale that gives millimetres. A TdofError names the file."""
    ts = []
    for im_id, insts in sorted(scene.gt.items()):
        for gt_id, e in enumerate(insts):
            if int(e["obj_id"]) not in models:
                raise TdofError(f"image {im_id} instance {gt_id} is object {e['obj_id']}, which the scene's "
                                f"models/models_info.json does not list (objects {sorted(models)})", d / SCENE_GT)
            ts.append(e["cam_t_m2c"])
    if not ts:
        return
    med = median_distance_if_metres(np.asarray(ts))
    if med is not None:
        raise TdofError(f"the objects lie {med:.4g} from the camera in the median: cam_t_m2c looks like metres "
                        "(it must be in millimetres)", d / SCENE_GT)
    # the depth's scale, on the first labelled image: depth at the objects against their distance
    im_id = next(i for i in sorted(scene.gt) if scene.gt[i])
    z = [float(e["cam_t_m2c"][2]) for e in scene.gt[im_id]]
    raw = scene.depth(im_id)
    valid = raw[raw > 0]
    if valid.size and np.median(z) > 0:
        got = float(np.median(valid)) * scene.depth_scale(im_id)
        ratio = got / float(np.median(z))
        if not DEPTH_RATIO[0] <= ratio <= DEPTH_RATIO[1]:
            raise TdofError(f"image {im_id}: depth x depth_scale is {got:.4g} mm in the median where its objects "
                            f"are {float(np.median(z)):.4g} mm away: depth_scale ({scene.depth_scale(im_id):g}) "
                            "must turn the depth PNG into millimetres", d / SCENE_CAMERA)


def read_scenes(dirs: list[Path]) -> tuple[dict[int, tuple[dict, Path]], dict[int, tuple[int, int]], dict]:
    """Read and check the annotated scene folders: ({scene id: (scene_info, folder)}, {id: (height,
    width)}, {id: BopScene}). Each scene's JSON files agree, every image is a PNG of its kind, and
    its labels pass check_labels against its own models (a scene without models/ is refused
    later, by the models' plan (plan_models)), and its scene_gt_uncertainty.json, when it has one,
    matches its scene_gt.json (:func:`tdof20.formats.bop_uncertainty.read_uncertainty`). A scene
    given twice is refused."""
    new: dict[int, tuple[dict, Path]] = {}
    sizes: dict[int, tuple[int, int]] = {}
    scenes = {}
    for d in dirs:
        info = scene_info(d)
        sid = scene_number(info["scene_id"])
        if sid in new:
            raise TdofError(f"scene {info['scene_id']} is given twice ({new[sid][1]} and {d})")
        scenes[sid] = read_scene(d)
        sizes[sid] = check_scene_images(scenes[sid])
        read_uncertainty(d, scenes[sid].gt)
        if (d / "models" / "models_info.json").exists():
            check_labels(d, scenes[sid], read_models_info(d / "models"))
        new[sid] = (info, d)
    return new, sizes, scenes


def _file_hash(p: Path) -> str:
    return hashlib.sha256(read_bytes(p, "model file")).hexdigest()


def scene_list(ids) -> str:
    return ", ".join(scene_name(i) for i in sorted(ids)) or "none"


def plan_models(sources: list[Path], sub: str, out: Path, keep: bool) -> tuple[dict[int, dict], list[tuple[Path, Path]]]:
    """The models of ``out/sub`` after the build: (models_info entries, [(model file to copy, destination)]).
    One object must keep one model across scenes (and, with ``keep``, the dataset's own); a model
    taken is checked as annotate --models checks a user's (tdof20.dataset.models.load_models)."""
    seen: dict[int, tuple[str, str]] = {}
    infos: dict[int, dict] = {}
    copies: list[tuple[Path, Path]] = []
    if keep and (out / sub / "models_info.json").exists():
        for obj_id, entry in read_models_info(out / sub).items():
            ply = out / sub / f"obj_{obj_id:06d}.ply"
            seen[obj_id] = (_file_hash(ply), f"the dataset's {sub}/")
            infos[obj_id] = entry
    for d in sources:
        if not (d / sub / "models_info.json").exists():
            if sub == "models":
                raise TdofError("has no models/ (a BOP models folder with models_info.json)", d)
            continue
        entries = read_models_info(d / sub)
        fresh = [o for o in entries if o not in seen]
        for obj_id, entry in entries.items():
            ply = d / sub / f"obj_{obj_id:06d}.ply"
            if not ply.exists():
                raise TdofError(f"models_info.json lists object {obj_id} but {ply.name} is missing", d / sub)
            h = _file_hash(ply)
            if obj_id in seen and seen[obj_id][0] != h:
                raise TdofError(f"object {obj_id} has a different model in {seen[obj_id][1]} and {d}: one object "
                                "must keep one model across scenes (annotate with --models)", d / sub)
            if obj_id not in seen:
                seen[obj_id] = (h, str(d))
                infos[obj_id] = entry
                copies.append((ply, out / sub / ply.name))
        # the models this build takes from d: each decodes, in mm, of its models_info diameter
        load_models(d / sub, fresh, need_faces=sub == "models")
    return infos, copies


def copy_file(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def copy_scene(src: Path, dst: Path) -> None:
    """Copy a scene folder into place whole: a copy beside it, then two renames."""
    tmp, old = dst.with_name(f".{dst.name}.tmp"), dst.with_name(f".{dst.name}.old")
    for p in (tmp, old):
        if p.exists():
            shutil.rmtree(p)
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copytree(src, tmp, ignore=shutil.ignore_patterns("models", "models_eval", ".*.tmp"))
    except shutil.Error as e:  # a list of (src, dst, why) per failed file (a full disk: every one of them)
        shutil.rmtree(tmp, ignore_errors=True)
        errors = [x for x in (e.args[0] if e.args and isinstance(e.args[0], list) else []) if len(x) == 3]
        if not errors:
            raise
        first_src, first_dst, why = errors[0]
        more = f" ({len(errors) - 1} more files failed too)" if len(errors) > 1 else ""
        why = str(why).split(": '", 1)[0]  # "[Errno 28] No space left on device: '<path>'" -> without the path
        try:  # name the file where it was to go, not the temporary copy
            first_dst = dst / Path(first_dst).relative_to(tmp)
        except ValueError:
            pass
        raise TdofError(f"cannot copy the scene file {first_src} here: {why}{more}", first_dst) from None
    if dst.exists():
        os.replace(dst, old)
    os.replace(tmp, dst)
    if old.exists():
        shutil.rmtree(old)


def scene_folders(scene_dirs, out: Path) -> list[Path]:
    """The scene folders given to a build, checked before anything is written: at least one, each
    a folder, --out a folder that can hold the dataset, neither inside the other."""
    dirs = [Path(d) for d in scene_dirs]
    if not dirs:
        raise TdofError("give at least one annotated scene folder")
    check_output_dir(out, "--out", "folder for the dataset")
    for d in dirs:
        if not d.is_dir():
            raise TdofError("no such scene folder", d)
    _check_not_nested(dirs, out)
    return dirs


def _check_not_nested(dirs: list[Path], out: Path) -> None:
    """Refuse an --out inside a scene folder (the copy would copy itself) and a scene inside --out."""
    o = out.resolve()
    for d in dirs:
        r = d.resolve()
        if o == r or r in o.parents:
            raise TdofError(f"--out is inside the scene folder {d}: the scene would be copied into itself; "
                            "choose an --out outside every scene folder", out)
        if o in r.parents:
            raise TdofError(f"the scene folder lies inside --out {out}: give scene folders from outside the "
                            "dataset (it keeps its own copies in scenes/)", d)


__all__ = ["BUILD_MARKER", "DEPTH_RATIO", "MAX_ARMS", "SCENE_FILES", "check_labels", "copy_file", "copy_scene",
           "plan_models", "read_scenes", "scene_folders", "scene_info", "scene_list"]
