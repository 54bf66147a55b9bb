"""A built dataset's split parts (either layout): their images, the dataset's counts, and a part
packed into one HDF5 shard (:mod:`tdof20.dataset.shards`).

    split_images(ROOT, "simple", "test")      # [(scene_id, im_id), ...]
    stats(ROOT)                               # counts per split part, scene and object
    pack(ROOT, "simple", "train", OUT.h5)     # the part's images in one shard
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.layouts.base import PARTS
from tdof20.dataset.shards import pack_shard
from tdof20.errors import TdofError
from tdof20.formats import check_output_file
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
    {"<folder>": {"scenes", "images", "test_images", "targets"}}."""
    ds = open_dataset(root)
    out: dict = {"layout": ds.layout, "scenes": 0, "images": 0, "splits": {}, "per_scene": {}, "per_object": {},
                 "objects": {o: ds.object_name(o) for o in ds.obj_ids}}
    obj_count: Counter = Counter()
    for folder in ds.stats_folders():
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
    out["splits"].update(ds.split_counts())
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


__all__ = ["pack", "split_images", "stats"]
