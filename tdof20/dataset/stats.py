"""A built dataset's split parts (either layout): their images, the dataset's counts, and a part
packed into one HDF5 shard (:mod:`tdof20.dataset.shards`).

    split_images(ROOT, "simple", "test")      # [(scene_id, im_id), ...]
    stats(ROOT)                               # counts per split part, scene and object; label-noise floor
    pack(ROOT, "simple", "train", OUT.h5)     # the part's images in one shard
"""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.layouts.base import PARTS
from tdof20.dataset.shards import pack_shard
from tdof20.errors import TdofError
from tdof20.formats import check_output_file
from tdof20.formats.bop_uncertainty import BOUNDS, read_uncertainty
from tdof20.progress import progress


def split_images(root: str | Path, split: str, part: str) -> list[tuple[int, int]]:
    """(scene_id, im_id) of a split part, in order (any layout: :meth:`tdof20.dataset.layouts.base.DatasetReader.frames`)."""
    ds = open_dataset(root)
    ds.check_part_request(split, part)
    return ds.frames(split, part)


def stats(root: str | Path) -> dict:
    """Counts per split part, per scene and per object, with the paper's figures beside them.

    Both layouts: "layout", "scenes", "images", "per_scene" {name: images}, "per_object" {obj_id:
    instances}, "objects" {obj_id: name}, "splits". tdof20: "splits" {"simple_train": n, ...,
    "simple_targets": n}; BOP: "splits" {"<folder>": images, ..., "targets": n} and "split_folders"
    {"<folder>": {"scenes", "images", "test_images", "targets"}}.

    "label_noise" {obj_id: {"labels", "bounded", "trans_mm", "rot_deg", "surface_mm"}}: the
    label-noise floor of each object from the scenes' scene_gt_uncertainty.json (95 % bounds on
    each label's own error): of its ``labels`` instances, ``bounded`` carry a bound, and each
    bound's {"median", "p95"} over them (None where none does: not recorded)."""
    ds = open_dataset(root)
    out: dict = {"layout": ds.layout, "scenes": 0, "images": 0, "splits": {}, "per_scene": {}, "per_object": {},
                 "objects": {o: ds.object_name(o) for o in ds.obj_ids}}
    obj_count: Counter = Counter()
    bounds: dict[int, dict[str, list[float]]] = defaultdict(lambda: {k: [] for k in BOUNDS})
    for folder in ds.stats_folders():
        n_folder = 0
        ids = ds.scene_ids(folder)
        for sid in ids:
            sc = ds.scene(sid, folder, require_gt=False)
            out["per_scene"][ds.scene_name(sid, folder)] = len(sc.im_ids())
            n_folder += len(sc.im_ids())
            for insts in sc.gt.values():
                obj_count.update(int(g["obj_id"]) for g in insts)
            unc = read_uncertainty(ds.scene_dir(sid, folder), sc.gt) if sc.gt else None
            for entries in (unc or {}).values():
                for e in entries:
                    for k in BOUNDS:
                        bounds[int(e["obj_id"])][k].append(float(e[k]))
        out["scenes"] += len(ids)
        out["images"] += n_folder
        if folder is not None:
            n_targets = len(ds.read_targets()) if folder == ds.targets_split() and ds.targets_path().is_file() else 0
            out.setdefault("split_folders", {})[folder] = {
                "scenes": len(ids), "images": n_folder, "test_images": len(ds.frames(folder, "test")),
                "targets": n_targets}
            out["splits"][folder] = n_folder
    out["per_object"] = {int(k): v for k, v in sorted(obj_count.items())}
    out["label_noise"] = {o: label_floor(n, bounds.get(o)) for o, n in out["per_object"].items()}
    out["splits"].update(ds.split_counts())
    return out


def label_floor(n_labels: int, bounds: dict[str, list[float]] | None) -> dict:
    """One object's label-noise floor: {"labels": n_labels, "bounded": how many carry a bound, and
    per bound (rot_deg, trans_mm, surface_mm) {"median", "p95"} over them, or None: not recorded}."""
    n = len(bounds[BOUNDS[0]]) if bounds else 0
    out: dict = {"labels": int(n_labels), "bounded": n}
    for k in ("trans_mm", "rot_deg", "surface_mm"):
        v = np.asarray(bounds[k], np.float64) if n else None
        out[k] = None if v is None else {"median": round(float(np.median(v)), 4),
                                         "p95": round(float(np.percentile(v, 95)), 4)}
    return out


def pack(root: str | Path, split: str, part: str, out: str | Path, show_progress: bool = True,
         cache_dir: str | Path | None = None) -> Path:
    """Pack a split part of the dataset (either layout) into one HDF5 shard (see
    tdof20.dataset.shards). Restored depth the dataset lacks is rendered first, once, and cached
    (under ROOT/.cache/ or ``cache_dir``)."""
    root = Path(root)
    out = Path(out)
    check_output_file(out, "--out", "HDF5 file")
    ds = open_dataset(root, cache_dir=cache_dir)
    split = ds.check_split(split)
    if split is None or part not in PARTS:
        ds.check_part_request(split, part)  # the message naming the valid splits and parts
    images = ds.frames(split, part)
    if not images:
        raise TdofError(f"nothing to pack: {ds.empty_part_text(split, part)}", root)
    ds.render_restored(images, split, show_progress=show_progress)
    with progress(show_progress) as bar:
        task = bar.add_task(f"packing {split}/{part}", total=len(images))
        return pack_shard(images, ds, out, {"split": split, "part": part, "dataset": str(root.resolve()),
                                            "layout": ds.layout},
                          models_dir=ds.models_dir, progress_bar=lambda: bar.advance(task), split=split)


__all__ = ["label_floor", "pack", "split_images", "stats"]
