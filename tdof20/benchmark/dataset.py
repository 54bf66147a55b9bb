"""Assemble annotated scenes into one BOP dataset with the paper's two protocols.

    ROOT/dataset_info.json        {"name", "scenes": {"<scene_id>": "single/01", ...}, "splits": ...}
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
import os
import shutil
from collections import Counter, defaultdict
from pathlib import Path

from tdof20.benchmark.splits import (PARTS, SPLITS, min_simple_steps, part_needs, part_of, scene_can_serve,
                                     scene_name, scene_number)
from tdof20.errors import TdofError
from tdof20.formats import (check_output_dir, check_output_file, check_scene_images, read_bytes, read_json,
                            read_models_info, read_scene, write_json)
from tdof20.progress import progress

TARGET_MIN_VISIB = 0.1  # BOP: instances at least 10 % visible are targets
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")
BUILD_MARKER = ".build.json"  # the scene list of a build under way; removed when it is done
SPLIT_RULES = {"simple": "single-object scenes, contiguous test arc per arm position (docs/dataset.md)",
               "hard": "train: single + multi 01,03-07,12-14,16-20; test: multi 02,08,09,10,11,15"}


def _scene_info(scene_dir: Path) -> dict:
    info = read_json(scene_dir / "scene_info.json")
    if not isinstance(info, dict):
        raise TdofError(f"must hold a JSON object, got {type(info).__name__}", scene_dir / "scene_info.json")
    for k in ("scene_id", "steps", "n_arms"):
        if k not in info:
            raise TdofError(f"missing field '{k}'", scene_dir / "scene_info.json")
    for k in ("steps", "n_arms"):
        if isinstance(info[k], bool) or not isinstance(info[k], int) or info[k] < 1:
            raise TdofError(f"{k} must be an integer >= 1, got {info[k]!r}", scene_dir / "scene_info.json")
    try:
        scene_number(info["scene_id"])  # checks the name
    except TdofError as e:
        raise TdofError(str(e), scene_dir / "scene_info.json") from None
    return info


def _file_hash(p: Path) -> str:
    return hashlib.sha256(read_bytes(p, "model file")).hexdigest()


def _names(ids) -> str:
    return ", ".join(scene_name(i) for i in sorted(ids)) or "none"


def _plan_models(sources: list[Path], sub: str, out: Path, keep: bool) -> tuple[dict[int, dict], list[tuple[Path, Path]]]:
    """The models of ``out/sub`` after the build: (models_info entries, [(model file to copy, destination)]).
    One object must keep one model across scenes (and, with ``keep``, the dataset's own)."""
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
        for obj_id, entry in read_models_info(d / sub).items():
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
    dirs = [Path(d) for d in scene_dirs]
    if not dirs:
        raise TdofError("give at least one annotated scene folder")
    check_output_dir(out, "--out", "folder for the dataset")
    for d in dirs:
        if not d.is_dir():
            raise TdofError("no such scene folder", d)
    _check_not_nested(dirs, out)

    # read and check every input
    new: dict[int, tuple[dict, Path]] = {}
    sizes: dict[int, tuple[int, int]] = {}
    for d in dirs:
        info = _scene_info(d)
        sid = scene_number(info["scene_id"])
        if sid in new:
            raise TdofError(f"scene {info['scene_id']} is given twice ({new[sid][1]} and {d})")
        sizes[sid] = check_scene_images(read_scene(d))  # JSON files agree; every image is a PNG of its kind
        new[sid] = (info, d)

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
        info_all["scenes"][str(sid)] = info["scene_id"]
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
    """(scene_id, im_id) of a split part, in order."""
    if split not in SPLITS or part not in PARTS:
        raise TdofError(f"split must be one of {SPLITS} and part one of {PARTS}, got {split}/{part}")
    m = read_json(Path(root) / "splits" / f"{split}_{part}.json")
    return [(int(s), i) for s, ims in m.items() for i in ims]


def stats(root: str | Path) -> dict:
    """Counts per split part, per scene and per object, with the paper's figures beside them."""
    root = Path(root)
    info = read_json(root / "dataset_info.json")
    out: dict = {"scenes": len(info["scenes"]), "images": 0, "splits": {}, "per_scene": {}, "per_object": {}}
    obj_count: Counter = Counter()
    for sid_s, name in info["scenes"].items():
        gt = read_json(root / "scenes" / f"{int(sid_s):06d}" / "scene_gt.json")
        out["per_scene"][name] = len(gt)
        out["images"] += len(gt)
        for insts in gt.values():
            obj_count.update(g["obj_id"] for g in insts)
    out["per_object"] = {int(k): v for k, v in sorted(obj_count.items())}
    for split in SPLITS:
        for part in PARTS:
            ims = split_images(root, split, part)
            out["splits"][f"{split}_{part}"] = len(ims)
        out["splits"][f"{split}_targets"] = len(read_json(root / f"test_targets_{split}.json"))
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


def pack(root: str | Path, split: str, part: str, out: str | Path, show_progress: bool = True) -> Path:
    """Pack a split part of the dataset into one HDF5 shard (see tdof20.formats.shards)."""
    from tdof20.formats.shards import pack_shard

    root = Path(root)
    out = Path(out)
    check_output_file(out, "--out", "HDF5 file")
    if not (root / "dataset_info.json").exists():
        raise TdofError("not a tdof20 dataset (no dataset_info.json)", root)
    images = split_images(root, split, part)
    if not images:
        raise TdofError(f"nothing to pack: the {split} split's {part} part has no images "
                        f"(splits/{split}_{part}.json): {empty_part_reason(root, split, part)}", root)
    with progress(show_progress) as bar:
        task = bar.add_task(f"packing {split}/{part}", total=len(images))
        return pack_shard(images, root / "scenes", out, {"split": split, "part": part, "dataset": str(root.resolve())},
                          models_dir=root / "models", progress_bar=lambda: bar.advance(task))
