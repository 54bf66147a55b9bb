"""The images a training takes (the split's train part, the train part minus its validation part,
or a list) and the HDF5 shard it reads them from.

    subset, part = train_images(ROOT, "simple", "train-val")    # (images, 'train-val'); (None, 'train')
    shard = shard_for(ROOT, "simple", RUN, None, rank=0, show=True, images=subset, part=part)
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from tdof20.dataset.build import pack
from tdof20.dataset.reader import open_dataset
from tdof20.dataset.shards import pack_shard
from tdof20.dataset.validation import split_with_val
from tdof20.errors import TdofError
from tdof20.progress import progress as progress_bar


def shard_for(dataset_root: Path, split: str, out_run: Path, shard: str | Path | None, rank: int,
               show: bool, cache_dir: str | Path | None = None, images: list | None = None,
               part: str = "train") -> Path:
    """The HDF5 shard a training reads: ``shard`` as given, else the split's train part (or the
    ``images`` of ``part``) packed into RUN/data/ by process 0 on first use."""
    if shard is not None:
        path = Path(shard)
        if not path.exists():
            raise TdofError("no such shard (write one with `tdof20 dataset pack`)", path)
        return path
    if images is None:
        path = out_run / "data" / f"{split}_train.h5"
        if rank == 0 and not path.exists():
            pack(dataset_root, split, "train", path, show_progress=show, cache_dir=cache_dir)
        return path
    # a subset of the train part (train minus validation, or an explicit list)
    path = out_run / "data" / f"{split}_{part}.h5"
    if rank == 0 and not path.exists():
        ds = open_dataset(dataset_root, cache_dir=cache_dir)
        scene_folder = ds.scene_folder(split)
        ds.render_restored(images, scene_folder, show_progress=show)
        with progress_bar(show) as bar:
            task = bar.add_task(f"packing {split}/{part}", total=len(images))
            pack_shard(images, ds, path, {"split": split, "part": part, "dataset": str(dataset_root.resolve()),
                                          "layout": ds.layout},
                       models_dir=ds.models_dir, progress_bar=lambda: bar.advance(task), split=scene_folder)
    return path


TRAIN_PARTS = ("train", "train-val")


def train_images(dataset_root: str | Path, split: str, part: str = "train",
                 images: list[tuple[int, int]] | None = None) -> tuple[list[tuple[int, int]] | None, str]:
    """The images a training takes, and the part's name for the run: (None, 'train') = the whole
    train part (packed as `dataset pack` does); part 'train-val' = the train part minus the
    validation part (tdof20.dataset.validation); ``images`` = exactly these (part 'images';
    refused when one is outside the train part)."""
    if images is not None:
        images = sorted({(int(s), int(i)) for s, i in images})
        if not images:
            raise TdofError("the list of training images is empty", dataset_root)
        whole = set(open_dataset(dataset_root).part_frames(split, "train", "train on"))
        outside = [im for im in images if im not in whole]
        if outside:
            raise TdofError(f"{len(outside)} of the {len(images)} training images are not in the {split} split's "
                            f"train part (first: scene {outside[0][0]}, image {outside[0][1]})", dataset_root)
        return images, "images"
    if part not in TRAIN_PARTS:
        raise TdofError(f"--part must be one of {', '.join(TRAIN_PARTS)}, got '{part}'")
    if part == "train":
        return None, "train"
    keep, val = split_with_val(dataset_root, split)
    if not keep:
        raise TdofError(f"the {split} split's train part minus its validation part is empty: nothing to train on",
                        dataset_root)
    return keep, "train-val"


def images_digest(images: list[tuple[int, int]] | None) -> str | None:
    """A short digest of a list of training images (None: the whole train part), what a run records."""
    if images is None:
        return None
    return hashlib.sha256(json.dumps([list(x) for x in images]).encode()).hexdigest()[:16]
