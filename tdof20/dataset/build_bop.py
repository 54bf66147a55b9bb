"""Write annotated scenes as a dataset in the standard BOP layout (``dataset build --layout bop``;
read back by :class:`tdof20.dataset.layouts.bop.BopReader`)::

    out/camera.json  out/models/ [out/models_eval/]  out/test_targets_bop19.json
    out/train/{scene_id:06d}/  out/test/{scene_id:06d}/     BOP scenes of one protocol's two parts
    out/tdof20_bop.json        protocol, scene names;  out/object_names.json  {id: name}
"""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter, defaultdict
from pathlib import Path

from tdof20.dataset.layouts.base import NAMES_FILE, TARGET_MIN_VISIB
from tdof20.dataset.layouts.bop import BOP_INFO, BOP_TARGETS, BopReader
from tdof20.dataset.scene_input import BUILD_MARKER, copy_file, plan_models, read_scenes, scene_folders
from tdof20.dataset.splits import SPLIT_RULES, SPLITS, part_needs, part_of
from tdof20.dataset.stats import stats
from tdof20.errors import TdofError
from tdof20.formats import read_json, write_json
from tdof20.formats.bop import dumps_bop_json
from tdof20.formats.bop_uncertainty import SCENE_GT_UNCERTAINTY
from tdof20.formats.io import atomic_write_bytes
from tdof20.objects import get_object
from tdof20.progress import progress

BOP_PARTS = {"train": "train", "test": "test"}  # protocol part -> BOP split folder
_BOP_SCENE_JSON = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", SCENE_GT_UNCERTAINTY)  # cut per image


def _bop_scene_part(src: Path, dst: Path, im_ids: list[int]) -> None:
    """Write the frames ``im_ids`` of the scene ``src`` as the BOP scene ``dst`` (whole: a copy
    beside it, then renames): the JSON label files (scene_gt_uncertainty.json too, when the scene
    has one) cut to those frames, and every per-image file
    (rgb, depth, depth_* and the masks) of them."""
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
    out = Path(out)
    if split not in SPLITS:
        raise TdofError(f"--layout bop writes one protocol: --split must be one of {', '.join(SPLITS)}, "
                        f"got '{split}'")
    dirs = scene_folders(scene_dirs, out)
    new, sizes, scenes = read_scenes(dirs)
    first = min(new)
    for sid, hw in sizes.items():
        if hw != sizes[first]:
            raise TdofError(f"its images are {hw[1]}x{hw[0]} (width x height), those of {new[first][0]['scene_id']} "
                            f"are {sizes[first][1]}x{sizes[first][0]}: a dataset has one image size", new[sid][1])
    marker = out / BUILD_MARKER
    marker_entry = {"scenes": sorted(new), "layout": BopReader.layout}  # what this build's marker holds
    previous = read_json(out / BOP_INFO) if (out / BOP_INFO).is_file() else None
    if previous is not None:
        if not isinstance(previous, dict) or sorted(int(k) for k in previous.get("scenes", {})) != sorted(new) \
                or previous.get("protocol") != split:
            raise TdofError(f"holds a BOP build of other scenes or another protocol ({BOP_INFO}): choose another --out",
                            out)
    elif marker.exists():
        if read_json(marker) != marker_entry:
            raise TdofError(f"an unfinished build of other scenes is here ({BUILD_MARKER}): run that build again to "
                            "finish it, or choose another --out", out)
    elif out.exists() and any(out.iterdir()):
        raise TdofError("folder is not empty and holds no dataset; choose another --out", out)
    sources = [d for _, (_, d) in sorted(new.items())]
    models, model_copies = plan_models(sources, "models", out, False)
    evals, eval_copies = plan_models(sources, "models_eval", out, False)
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
    write_json(marker, marker_entry)
    for src, dst in model_copies + eval_copies:
        copy_file(src, dst)
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
    try:
        return get_object(int(obj_id)).name
    except TdofError:
        return f"obj_{int(obj_id):06d}"


def write_bop_layout(scene_dirs: list[str | Path], out: str | Path, *, split: str | None = None, add: bool = False,
                     show_progress: bool = True) -> dict:
    """``dataset build --layout bop``: the options checked (one protocol, ``--split``; no ``--add``),
    then :func:`build_bop_dataset`."""
    if split is None:
        raise TdofError("--layout bop needs --split simple or --split hard (the protocol whose train and test "
                        "parts become train/ and test/)")
    if add:
        raise TdofError("--add grows a tdof20-layout dataset; build a BOP layout from the full scene list")
    return build_bop_dataset(scene_dirs, out, split, show_progress=show_progress)


__all__ = ["BOP_PARTS", "build_bop_dataset", "write_bop_layout"]
