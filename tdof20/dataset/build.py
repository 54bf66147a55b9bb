"""Assemble annotated scenes into one BOP dataset with the paper's two protocols.

    ROOT/dataset_info.json        {"name", "scenes": {"<scene_id>": "single/cube_136", ...}, "splits": ...}
    ROOT/camera.json              BOP camera file (cx, cy, fx, fy, width, height, depth_scale)
    ROOT/models/                  obj_000001.ply ... + models_info.json (one model per object)
    ROOT/models_eval/             when the scenes bring one
    ROOT/scenes/{scene_id:06d}/   the BOP scene (rgb, depth, depth_opaque, depth_restored, masks, JSON)
    ROOT/splits/{simple,hard}_{train,test}.json    {"<scene_id>": [im_id, ...]}
    ROOT/test_targets_{simple,hard}.json           BOP targets [{"scene_id","im_id","obj_id","inst_count"}]

An annotated scene is a BOP scene folder with ``scene_info.json`` ({"scene_id": "multi/08",
"n_arms", "steps", ...}) and ``models/`` — what ``tdof20 annotate`` writes (and
``tdof20 sim label`` from the simulator's truth). See docs/dataset.md.

A build checks every input (scene files, every image's PNG header, models) before it writes, and
writes ``ROOT/.build.json`` (the scene list under way) first and ``dataset_info.json`` last, so an
interrupted build is finished by running it again. An existing dataset is only rebuilt from its own
scene list, or grown with ``add=True`` (``dataset build --add``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections import Counter, defaultdict
from pathlib import Path

from tdof20.dataset.splits import (PARTS, SPLITS, min_simple_steps, part_needs, part_of, scene_can_serve,
                                     scene_name, scene_number)
from tdof20.errors import TdofError
from tdof20.formats import (check_output_dir, check_output_file, check_scene_images, read_bytes, read_json,
                            read_models_info, read_scene, write_json)
from tdof20.dataset.reader import open_dataset
from tdof20.formats.session import MAX_STEPS
from tdof20.progress import progress

TARGET_MIN_VISIB = 0.1  # BOP: instances at least 10 % visible are targets
MAX_ARMS = 64  # arm positions of a scene (TDoF20: 4); bounds a typo before the split rules loop over them
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")
BUILD_MARKER = ".build.json"  # the scene list of a build under way; removed when it is done
SPLIT_RULES = {"simple": "single-object scenes, contiguous test arc per arm position (docs/dataset.md)",
               "hard": "train: single + multi 00,01,03-07,12-14,16-19; test: multi 02,08,09,10,11,15"}


def _scene_info(scene_dir: Path) -> dict:
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


def _check_labels(d: Path, scene, models: dict[int, dict]) -> None:
    """What a label must be before it joins a dataset: an object of the scene's models/, a
    translation in millimetres, a depth_scale that gives millimetres. A TdofError names the file."""
    import numpy as np

    from tdof20.formats.bop import SCENE_CAMERA, SCENE_GT, median_distance_if_metres

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


def _read_scenes(dirs: list[Path]) -> tuple[dict[int, tuple[dict, Path]], dict[int, tuple[int, int]], dict]:
    """Read and check the annotated scene folders: ({scene id: (scene_info, folder)}, {id: (height,
    width)}, {id: BopScene}). Each scene's JSON files agree, every image is a PNG of its kind, and
    its labels pass _check_labels against its own models (a scene without models/ is refused
    later, by the models' plan). A scene given twice is refused."""
    new: dict[int, tuple[dict, Path]] = {}
    sizes: dict[int, tuple[int, int]] = {}
    scenes = {}
    for d in dirs:
        info = _scene_info(d)
        sid = scene_number(info["scene_id"])
        if sid in new:
            raise TdofError(f"scene {info['scene_id']} is given twice ({new[sid][1]} and {d})")
        scenes[sid] = read_scene(d)
        sizes[sid] = check_scene_images(scenes[sid])
        if (d / "models" / "models_info.json").exists():
            _check_labels(d, scenes[sid], read_models_info(d / "models"))
        new[sid] = (info, d)
    return new, sizes, scenes


def _file_hash(p: Path) -> str:
    return hashlib.sha256(read_bytes(p, "model file")).hexdigest()


def _names(ids) -> str:
    return ", ".join(scene_name(i) for i in sorted(ids)) or "none"


def _plan_models(sources: list[Path], sub: str, out: Path, keep: bool) -> tuple[dict[int, dict], list[tuple[Path, Path]]]:
    """The models of ``out/sub`` after the build: (models_info entries, [(model file to copy, destination)]).
    One object must keep one model across scenes (and, with ``keep``, the dataset's own); a model
    taken is checked as annotate --models checks a user's (tdof20.dataset.models.load_models)."""
    from tdof20.dataset.models import load_models

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


def _copy_file(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _copy_scene(src: Path, dst: Path) -> None:
    """Copy a scene folder into place whole: a copy beside it, then two renames."""
    tmp, old = dst.with_name(f".{dst.name}.tmp"), dst.with_name(f".{dst.name}.old")
    for p in (tmp, old):
        if p.exists():
            shutil.rmtree(p)
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(src, tmp, ignore=shutil.ignore_patterns("models", "models_eval", ".*.tmp"))
    if dst.exists():
        os.replace(dst, old)
    os.replace(tmp, dst)
    if old.exists():
        shutil.rmtree(old)


def _scene_folders(scene_dirs, out: Path) -> list[Path]:
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


def _dataset_scenes(out: Path) -> dict[int, str] | None:
    """{scene_id: name} of the dataset in ``out`` (None when ``out`` holds none)."""
    path = out / "dataset_info.json"
    if not path.exists():
        return None
    info = read_json(path)
    if not isinstance(info, dict) or not isinstance(info.get("scenes"), dict) or not isinstance(info.get("layout"), dict):
        raise TdofError("not a tdof20 dataset_info.json (needs 'scenes' and 'layout'); choose another --out", path)
    try:
        return {int(k): str(v) for k, v in info["scenes"].items()}
    except ValueError:
        raise TdofError("not a tdof20 dataset_info.json (scene keys must be integer ids)", path) from None


def build_dataset(scene_dirs: list[str | Path], out: str | Path, show_progress: bool = True,
                  add: bool = False) -> dict:
    """Gather annotated scenes into the dataset ``out``; returns its stats (see :func:`stats`).

    ``out`` must be empty or new, or hold the dataset of exactly these scenes (built again from
    them: a resume, or new labels). ``add=True`` adds the scenes to the dataset in ``out``
    (scenes, models, models_info, splits, targets and dataset_info stay consistent). Everything
    given is checked before anything is written: a refusal leaves ``out`` as it was."""
    out = Path(out)
    dirs = _scene_folders(scene_dirs, out)

    # read and check every input
    new, sizes, _ = _read_scenes(dirs)

    # what is in --out, and what this build makes of it
    existing = _dataset_scenes(out)
    marker = out / BUILD_MARKER
    pending = read_json(marker) if marker.exists() else None
    target = {sid: info["scene_id"] for sid, (info, _) in new.items()}
    if add and existing is not None:
        target.update(existing)
    if pending is not None:
        if not isinstance(pending, dict) or sorted(pending.get("scenes", [])) != sorted(target):
            raise TdofError(f"an unfinished build of other scenes is here ({BUILD_MARKER}): run that build again to "
                            "finish it, or choose another --out", out)
        if add and existing is not None:  # an interrupted --add: scenes it listed already are its own
            existing = {k: v for k, v in existing.items() if k not in new}
    elif existing is not None and add:
        again = sorted(set(new) & set(existing))
        if again:
            raise TdofError(f"{_names(again)} {'is' if len(again) == 1 else 'are'} already in the dataset: --add adds "
                            "new scenes only (to rebuild with new labels, give the full scene list without --add)", out)
    elif existing is not None and set(existing) != set(new):
        dropped = sorted(set(existing) - set(new))
        raise TdofError(f"holds the dataset of {_names(existing)}; building {_names(new)} here would "
                        + (f"drop {_names(dropped)}" if dropped else "redefine it")
                        + ": add scenes with --add, rebuild it with its full scene list, or choose another --out", out)
    elif existing is None and add:
        raise TdofError("--add needs an existing dataset (no dataset_info.json here): build it without --add first",
                        out)
    elif existing is None and pending is None and out.exists() and any(out.iterdir()):
        raise TdofError("folder is not empty and holds no dataset; choose another --out", out)
    keep = add and existing is not None  # the dataset's scenes and models stay; the new ones join them

    # one image size for the whole dataset (shards and camera.json need it)
    if keep:
        cam = read_json(out / "camera.json")
        if not isinstance(cam, dict) or not all(isinstance(cam.get(k), int) for k in ("width", "height")):
            raise TdofError("needs integer 'width' and 'height' (the dataset's image size)", out / "camera.json")
        ref_size, ref_what = (cam["height"], cam["width"]), f"the dataset {out} (camera.json)"
    else:
        first = min(new)
        ref_size, ref_what = sizes[first], f"{new[first][0]['scene_id']} ({new[first][1]})"
    for sid, hw in sizes.items():
        if hw != ref_size:
            raise TdofError(f"its images are {hw[1]}x{hw[0]} (width x height), those of {ref_what} are "
                            f"{ref_size[1]}x{ref_size[0]}: a dataset has one image size", new[sid][1])

    # models: one per object across all scenes (and the dataset's own when adding)
    sources = [d for _, (_, d) in sorted(new.items())]
    models, model_copies = _plan_models(sources, "models", out, keep)
    evals, eval_copies = _plan_models(sources, "models_eval", out, keep)
    if evals and set(evals) != set(models):
        raise TdofError(f"models_eval/ covers objects {sorted(evals)} but models/ has {sorted(models)}: give every "
                        "scene a models_eval/ with its objects, or none", sources[0])

    # write: the marker first, dataset_info.json last (a rerun of the same build finishes an interrupted one)
    out.mkdir(parents=True, exist_ok=True)
    write_json(marker, {"scenes": sorted(target)})
    for src, dst in model_copies + eval_copies:
        _copy_file(src, dst)
    with progress(show_progress) as bar:
        task = bar.add_task("copying scenes", total=len(new))
        for sid, (info, d) in sorted(new.items()):
            _copy_scene(d, out / "scenes" / f"{sid:06d}")
            bar.advance(task)
    write_json(out / "models" / "models_info.json", {str(k): v for k, v in sorted(models.items())})
    if evals:
        write_json(out / "models_eval" / "models_info.json", {str(k): v for k, v in sorted(evals.items())})
    if keep:
        info_all = read_json(out / "dataset_info.json")
    else:
        first = read_scene(out / "scenes" / f"{min(new):06d}")
        im0 = first.im_ids()[0]
        K = first.K(im0)
        h, w = ref_size
        write_json(out / "camera.json", {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                                         "fy": float(K[1, 1]), "width": int(w), "height": int(h),
                                         "depth_scale": float(first.depth_scale(im0))})
        info_all = {"name": "tdof20", "format": "bop", "scenes": {}, "layout": {}}
    for sid, (info, _) in new.items():
        info_all["scenes"][str(sid)] = scene_name(scene_number(info["scene_id"]))  # aliases -> names
        info_all["layout"][str(sid)] = {"n_arms": info["n_arms"], "steps": info["steps"]}
    order = sorted(info_all["scenes"], key=int)
    info_all["scenes"] = {k: info_all["scenes"][k] for k in order}
    info_all["layout"] = {k: info_all["layout"][k] for k in order}
    info_all["splits"] = dict(SPLIT_RULES)
    info_all["target_min_visib_fract"] = TARGET_MIN_VISIB
    write_splits(out, info_all)
    write_json(out / "dataset_info.json", info_all)
    marker.unlink()
    return stats(out)


def write_splits(root: Path, info: dict | None = None) -> None:
    """splits/{split}_{part}.json and test_targets_{split}.json from the scenes in ``root``
    (those ``info`` lists: default, ROOT/dataset_info.json)."""
    root = Path(root)
    info = read_json(root / "dataset_info.json") if info is None else info
    members = {(s, p): defaultdict(list) for s in SPLITS for p in PARTS}
    targets = {s: [] for s in SPLITS}
    for sid_s, layout in info["layout"].items():
        sid = int(sid_s)
        scene = read_scene(root / "scenes" / f"{sid:06d}")
        for im_id in scene.im_ids():
            for split in SPLITS:
                part = part_of(split, sid, im_id, layout["steps"], layout["n_arms"])
                if part is None:
                    continue
                members[(split, part)][str(sid)].append(im_id)
                if part == "test":
                    counts = Counter(g["obj_id"] for g, gi in zip(scene.gt[im_id], scene.gt_info.get(im_id, []))
                                     if gi["visib_fract"] >= TARGET_MIN_VISIB)
                    targets[split] += [{"scene_id": sid, "im_id": im_id, "obj_id": int(o), "inst_count": int(n)}
                                       for o, n in sorted(counts.items())]
    for (split, part), m in members.items():
        write_json(root / "splits" / f"{split}_{part}.json", {k: sorted(v) for k, v in sorted(m.items(), key=lambda x: int(x[0]))})
    for split, t in targets.items():
        write_json(root / f"test_targets_{split}.json", t, indent=None)


def split_images(root: str | Path, split: str, part: str) -> list[tuple[int, int]]:
    """(scene_id, im_id) of a split part, in order (any layout: :meth:`tdof20.dataset.reader.Dataset.frames`)."""
    ds = open_dataset(root)
    if ds.layout == "tdof20" and (split not in SPLITS or part not in PARTS):
        raise TdofError(f"split must be one of {SPLITS} and part one of {PARTS}, got {split}/{part}")
    return ds.frames(split, part)


def stats(root: str | Path) -> dict:
    """Counts per split part, per scene and per object, with the paper's figures beside them.

    Both layouts: "layout", "scenes", "images", "per_scene" {name: images}, "per_object" {obj_id:
    instances}, "objects" {obj_id: name}, "splits". tdof20: "splits" {"simple_train": n, ...,
    "simple_targets": n}; BOP: "splits" {"<folder>": images, ..., "targets": n} and "split_folders"
    {"<folder>": {"scenes", "images", "test_images", "targets"}}."""
    ds = open_dataset(root)
    out: dict = {"layout": ds.layout, "scenes": 0, "images": 0, "splits": {}, "per_scene": {}, "per_object": {},
                 "objects": {o: ds.object_name(o) for o in ds.obj_ids}}
    obj_count: Counter = Counter()
    folders = [None] if ds.layout == "tdof20" else ds.splits()
    for folder in folders:
        n_folder = 0
        ids = ds.scene_ids(folder)
        for sid in ids:
            sc = ds.scene(sid, folder, require_gt=False)
            out["per_scene"][ds.scene_name(sid, folder)] = len(sc.im_ids())
            n_folder += len(sc.im_ids())
            for insts in sc.gt.values():
                obj_count.update(int(g["obj_id"]) for g in insts)
        out["scenes"] += len(ids)
        out["images"] += n_folder
        if folder is not None:
            n_targets = len(ds.read_targets()) if folder == ds.targets_split() and ds.targets_path().is_file() else 0
            out.setdefault("split_folders", {})[folder] = {
                "scenes": len(ids), "images": n_folder, "test_images": len(ds.frames(folder, "test")),
                "targets": n_targets}
            out["splits"][folder] = n_folder
    out["per_object"] = {int(k): v for k, v in sorted(obj_count.items())}
    if ds.layout == "bop":
        out["splits"]["targets"] = len(ds.read_targets()) if ds.targets_path().is_file() else 0
        return out
    for split in dict.fromkeys(list(SPLITS) + ds.splits()):
        if not any((ds.root / "splits" / f"{split}_{p}.json").is_file() for p in PARTS):
            continue
        for part in PARTS:
            path = ds.root / "splits" / f"{split}_{part}.json"
            out["splits"][f"{split}_{part}"] = len(ds.frames(split, part)) if path.is_file() else 0
        tp = ds.targets_path(split)
        out["splits"][f"{split}_targets"] = len(ds.read_targets(split)) if tp.is_file() else 0
    return out


def empty_part_reason(root: str | Path, split: str, part: str) -> str:
    """Why the ``part`` of ``split`` of the dataset in ``root`` has no images, for a message:
    what the dataset holds against what the split needs."""
    info = read_json(Path(root) / "dataset_info.json")
    scenes = {int(k): str(v) for k, v in (info.get("scenes") or {}).items()} if isinstance(info, dict) else {}
    layout = (info.get("layout") or {}) if isinstance(info, dict) else {}
    n_single = sum(1 for s in scenes if s <= 20)
    holds = (f"the dataset has {n_single} single-object and {len(scenes) - n_single} multi-object "
             f"scene{'s' if len(scenes) - n_single != 1 else ''} ({', '.join(scenes[s] for s in sorted(scenes)) or 'none'})")
    serving = sorted(s for s in scenes if scene_can_serve(split, part, s))
    if not serving:
        return f"{holds}; {part_needs(split, part)}"
    if split == "simple" and part == "test":
        steps = sorted({layout.get(str(s), {}).get("steps") for s in serving} - {None})
        return (f"its single-object scenes have {', '.join(map(str, steps)) or 'too few'} steps per arm position: "
                f"a test arc needs at least {min_simple_steps()}")
    return f"{holds}, and its {split}/{part} scenes list no images"


def pack(root: str | Path, split: str, part: str, out: str | Path, show_progress: bool = True,
         cache_dir: str | Path | None = None) -> Path:
    """Pack a split part of the dataset (either layout) into one HDF5 shard (see
    tdof20.dataset.shards). Restored depth the dataset lacks is rendered first, once, and cached
    (under ROOT/.cache/ or ``cache_dir``)."""
    from tdof20.dataset.shards import pack_shard

    root = Path(root)
    out = Path(out)
    check_output_file(out, "--out", "HDF5 file")
    ds = open_dataset(root, cache_dir=cache_dir)
    split = ds.check_split(split)
    if ds.layout == "tdof20" and (split not in ds.splits() or part not in PARTS):
        split_images(root, split, part)  # the message naming the valid splits and parts
    images = ds.frames(split, part)
    if not images:
        if ds.layout == "bop":
            raise TdofError(f"nothing to pack: the split folder {split}/ has no images", root)
        raise TdofError(f"nothing to pack: the {split} split's {part} part has no images "
                        f"(splits/{split}_{part}.json): {empty_part_reason(root, split, part)}", root)
    ds.render_restored(images, split, show_progress=show_progress)
    with progress(show_progress) as bar:
        task = bar.add_task(f"packing {split}/{part}", total=len(images))
        return pack_shard(images, ds, out, {"split": split, "part": part, "dataset": str(root.resolve()),
                                            "layout": ds.layout},
                          models_dir=ds.models_dir, progress_bar=lambda: bar.advance(task), split=split)


# ---------------------------------------------------------------------------------------------
# the standard BOP layout (dataset build --layout bop)
# ---------------------------------------------------------------------------------------------
BOP_PARTS = {"train": "train", "test": "test"}  # protocol part -> BOP split folder
_BOP_SCENE_JSON = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json")


def _bop_scene_part(src: Path, dst: Path, im_ids: list[int]) -> None:
    """Write the frames ``im_ids`` of the scene ``src`` as the BOP scene ``dst`` (whole: a copy
    beside it, then renames): the three JSON files cut to those frames, and every per-image file
    (rgb, depth, depth_* and the masks) of them."""
    from tdof20.formats.bop import dumps_bop_json
    from tdof20.formats.io import atomic_write_bytes

    keep = {str(i) for i in im_ids}
    tmp, old = dst.with_name(f".{dst.name}.tmp"), dst.with_name(f".{dst.name}.old")
    for p in (tmp, old):
        if p.exists():
            shutil.rmtree(p)
    tmp.mkdir(parents=True)
    for name in _BOP_SCENE_JSON:
        if (src / name).exists():
            data = read_json(src / name)
            atomic_write_bytes(tmp / name, dumps_bop_json({k: v for k, v in data.items() if k in keep}).encode())
    stems = {f"{i:06d}" for i in im_ids}
    for sub in sorted(p for p in src.iterdir() if p.is_dir() and p.name not in ("models", "models_eval", "qa")):
        files = [f for f in sub.iterdir() if f.is_file() and f.name[:6] in stems and not f.name.startswith(".")]
        if files:
            (tmp / sub.name).mkdir()
        for f in files:
            try:
                os.link(f, tmp / sub.name / f.name)  # same file system: no copy
            except OSError:
                shutil.copyfile(f, tmp / sub.name / f.name)
    if dst.exists():
        os.replace(dst, old)
    os.replace(tmp, dst)
    if old.exists():
        shutil.rmtree(old)


def build_bop_dataset(scene_dirs: list[str | Path], out: str | Path, split: str, show_progress: bool = True) -> dict:
    """Gather annotated scenes into ``out`` in the standard BOP layout, one protocol (``split``:
    'simple' or 'hard') deciding which frames go to ``train/`` and which to ``test/``::

        out/camera.json  out/models/ [out/models_eval/]  out/test_targets_bop19.json
        out/train/{scene_id:06d}/  out/test/{scene_id:06d}/     BOP scenes (rgb, depth, depth_restored,
                                                                mask, mask_visib, scene_*.json)
        out/tdof20_bop.json        protocol, scene names;  out/object_names.json  {id: name}

    Scene ids are tdof20's (single/<class> -> 1..20, multi/NN -> 21..40); a simple-split scene
    has frames in both folders. ``out`` must be empty or new, or hold an earlier BOP build of
    the same scenes and protocol (rebuilt). Returns :func:`stats` of the result."""
    from tdof20.dataset.splits import SPLITS as PROTOCOLS
    from tdof20.dataset.reader import BOP_INFO, BOP_TARGETS, NAMES_FILE

    out = Path(out)
    if split not in PROTOCOLS:
        raise TdofError(f"--layout bop writes one protocol: --split must be one of {', '.join(PROTOCOLS)}, "
                        f"got '{split}'")
    dirs = _scene_folders(scene_dirs, out)
    new, sizes, scenes = _read_scenes(dirs)
    first = min(new)
    for sid, hw in sizes.items():
        if hw != sizes[first]:
            raise TdofError(f"its images are {hw[1]}x{hw[0]} (width x height), those of {new[first][0]['scene_id']} "
                            f"are {sizes[first][1]}x{sizes[first][0]}: a dataset has one image size", new[sid][1])
    marker = out / BUILD_MARKER
    previous = read_json(out / BOP_INFO) if (out / BOP_INFO).is_file() else None
    if previous is not None:
        if not isinstance(previous, dict) or sorted(int(k) for k in previous.get("scenes", {})) != sorted(new) \
                or previous.get("protocol") != split:
            raise TdofError(f"holds a BOP build of other scenes or another protocol ({BOP_INFO}): choose another --out",
                            out)
    elif marker.exists():
        pending = read_json(marker)
        if not isinstance(pending, dict) or sorted(pending.get("scenes", [])) != sorted(new) \
                or pending.get("layout") != "bop":
            raise TdofError(f"an unfinished build of other scenes is here ({BUILD_MARKER}): run that build again to "
                            "finish it, or choose another --out", out)
    elif out.exists() and any(out.iterdir()):
        raise TdofError("folder is not empty and holds no dataset; choose another --out", out)
    sources = [d for _, (_, d) in sorted(new.items())]
    models, model_copies = _plan_models(sources, "models", out, False)
    evals, eval_copies = _plan_models(sources, "models_eval", out, False)
    if evals and set(evals) != set(models):
        raise TdofError(f"models_eval/ covers objects {sorted(evals)} but models/ has {sorted(models)}: give every "
                        "scene a models_eval/ with its objects, or none", sources[0])

    # which frames go where
    members: dict[str, dict[int, list[int]]] = {p: defaultdict(list) for p in BOP_PARTS}
    targets = []
    for sid, (info, _) in sorted(new.items()):
        sc = scenes[sid]
        for im in sc.im_ids():
            part = part_of(split, sid, im, info["steps"], info["n_arms"])
            if part is None:
                continue
            members[part][sid].append(im)
            if part == "test":
                counts = Counter(g["obj_id"] for g, gi in zip(sc.gt.get(im, []), sc.gt_info.get(im, []))
                                 if gi["visib_fract"] >= TARGET_MIN_VISIB)
                targets += [{"im_id": im, "inst_count": int(n), "obj_id": int(o), "scene_id": sid}
                            for o, n in sorted(counts.items())]
    if not any(members[p] for p in BOP_PARTS):
        raise TdofError(f"none of the scenes' frames is in the {split} protocol: "
                        f"{part_needs(split, 'train')}", sources[0])

    out.mkdir(parents=True, exist_ok=True)
    write_json(marker, {"scenes": sorted(new), "layout": "bop"})
    for src, dst in model_copies + eval_copies:
        _copy_file(src, dst)
    write_json(out / "models" / "models_info.json", {str(k): v for k, v in sorted(models.items())})
    if evals:
        write_json(out / "models_eval" / "models_info.json", {str(k): v for k, v in sorted(evals.items())})
    sc0 = scenes[first]
    im0 = sc0.im_ids()[0]
    K = sc0.K(im0)
    h, w = sizes[first]
    write_json(out / "camera.json", {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_scale": float(sc0.depth_scale(im0)),
                                     "fx": float(K[0, 0]), "fy": float(K[1, 1]), "height": int(h), "width": int(w)})
    for part, folder in BOP_PARTS.items():  # a rebuild drops scenes a part no longer has
        if (out / folder).is_dir():
            for p in (out / folder).iterdir():
                if p.is_dir() and p.name.isdigit() and int(p.name) not in members[part]:
                    shutil.rmtree(p)
    with progress(show_progress) as bar:
        task = bar.add_task("writing BOP scenes", total=sum(len(m) for m in members.values()))
        for part, folder in BOP_PARTS.items():
            for sid, ims in sorted(members[part].items()):
                _bop_scene_part(new[sid][1], out / folder / f"{sid:06d}", sorted(ims))
                bar.advance(task)
    from tdof20.formats.io import atomic_write_bytes

    body = ",\n".join("  " + json.dumps(t, sort_keys=True) for t in targets)
    atomic_write_bytes(out / BOP_TARGETS, ("[\n" + body + ("\n" if targets else "") + "]\n").encode())
    write_json(out / NAMES_FILE, {str(o): _object_name(o) for o in sorted(models)})
    write_json(out / BOP_INFO, {"source": "tdof20 dataset build --layout bop", "protocol": split,
                                "split_rule": SPLIT_RULES[split],
                                "folders": {folder: part for part, folder in BOP_PARTS.items()},
                                "scenes": {str(sid): info["scene_id"] for sid, (info, _) in sorted(new.items())}})
    marker.unlink()
    return stats(out)


def _object_name(obj_id: int) -> str:
    from tdof20.objects import get_object

    try:
        return get_object(int(obj_id)).name
    except TdofError:
        return f"obj_{int(obj_id):06d}"
