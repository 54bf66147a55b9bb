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
"""

from __future__ import annotations

import hashlib
import shutil
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from tdof20.benchmark.splits import PARTS, SPLITS, part_of, scene_name, scene_number
from tdof20.errors import TdofError
from tdof20.formats import read_json, read_models_info, read_scene, write_json
from tdof20.progress import progress

TARGET_MIN_VISIB = 0.1  # BOP: instances at least 10 % visible are targets
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")


def _scene_info(scene_dir: Path) -> dict:
    info = read_json(scene_dir / "scene_info.json")
    for k in ("scene_id", "steps", "n_arms"):
        if k not in info:
            raise TdofError(f"missing field '{k}'", scene_dir / "scene_info.json")
    scene_number(info["scene_id"])  # checks the name
    return info


def _file_hash(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _merge_models(scene_dirs: list[Path], sub: str, out: Path) -> bool:
    """Copy the models of every scene into ``out/sub``; one object must keep one model."""
    seen: dict[int, tuple[str, Path]] = {}
    infos: dict[int, dict] = {}
    for d in scene_dirs:
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
                seen[obj_id] = (h, d)
                infos[obj_id] = entry
                (out / sub).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(ply, out / sub / ply.name)
    if infos:
        write_json(out / sub / "models_info.json", {str(k): v for k, v in sorted(infos.items())})
    return bool(infos)


def build_dataset(scene_dirs: list[str | Path], out: str | Path, show_progress: bool = True) -> dict:
    """Gather annotated scenes into the dataset ``out``; returns its stats (see :func:`stats`)."""
    out = Path(out)
    dirs = [Path(d) for d in scene_dirs]
    if not dirs:
        raise TdofError("give at least one annotated scene folder")
    if out.exists() and any(out.iterdir()) and not (out / "dataset_info.json").exists():
        raise TdofError("folder is not empty and holds no dataset; choose another --out", out)
    infos = {}
    for d in dirs:
        info = _scene_info(d)
        sid = scene_number(info["scene_id"])
        if sid in infos:
            raise TdofError(f"scene {info['scene_id']} is given twice ({infos[sid][1]} and {d})")
        read_scene(d)  # every JSON file parses and agrees with itself
        infos[sid] = (info, d)
    _merge_models(dirs, "models", out)
    _merge_models(dirs, "models_eval", out)
    with progress(show_progress) as bar:
        task = bar.add_task("copying scenes", total=len(infos))
        for sid, (info, d) in sorted(infos.items()):
            dst = out / "scenes" / f"{sid:06d}"
            if dst.exists():
                shutil.rmtree(dst)
            shutil.copytree(d, dst, ignore=shutil.ignore_patterns("models", "models_eval", ".*.tmp"))
            bar.advance(task)
    first = read_scene(out / "scenes" / f"{min(infos):06d}")
    im0 = first.im_ids()[0]
    K = first.K(im0)
    rgb0 = first.image("rgb", im0) if (first.path / "rgb").exists() else None
    h, w = (rgb0.shape[:2] if rgb0 is not None else first.mask(im0, 0).shape)
    write_json(out / "camera.json", {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                                     "fy": float(K[1, 1]), "width": int(w), "height": int(h),
                                     "depth_scale": float(first.depth_scale(im0))})
    write_json(out / "dataset_info.json", {
        "name": "tdof20", "format": "bop",
        "scenes": {str(sid): info["scene_id"] for sid, (info, _) in sorted(infos.items())},
        "layout": {str(sid): {"n_arms": info["n_arms"], "steps": info["steps"]} for sid, (info, _) in sorted(infos.items())},
        "splits": {"simple": "single-object scenes, contiguous test arc per arm position (docs/dataset.md)",
                   "hard": "train: single + multi 01,03-07,12-14,16-20; test: multi 02,08,09,10,11,15"},
        "target_min_visib_fract": TARGET_MIN_VISIB,
    })
    write_splits(out)
    return stats(out)


def write_splits(root: Path) -> None:
    """splits/{split}_{part}.json and test_targets_{split}.json from the scenes in ``root``."""
    info = read_json(root / "dataset_info.json")
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


def pack(root: str | Path, split: str, part: str, out: str | Path, show_progress: bool = True) -> Path:
    """Pack a split part of the dataset into one HDF5 shard (see tdof20.formats.shards)."""
    from tdof20.formats.shards import pack_shard

    root = Path(root)
    if not (root / "dataset_info.json").exists():
        raise TdofError("not a tdof20 dataset (no dataset_info.json)", root)
    images = split_images(root, split, part)
    with progress(show_progress) as bar:
        task = bar.add_task(f"packing {split}/{part}", total=len(images))
        return pack_shard(images, root / "scenes", out, {"split": split, "part": part, "dataset": str(root.resolve())},
                          models_dir=root / "models", progress_bar=lambda: bar.advance(task))
