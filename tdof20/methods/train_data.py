"""The images a training takes (the split's train part, the train part minus its validation part,
or a list) and the HDF5 shard it reads them from.

    subset, part = train_images(ROOT, "simple", "train-val")    # (images, 'train-val'); (None, 'train')
    shard = shard_for(ROOT, "simple", RUN, None, rank=0, show=True, images=subset, part=part)
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import h5py

from tdof20.dataset.build import pack
from tdof20.dataset.reader import open_dataset
from tdof20.dataset.shards import pack_shard
from tdof20.dataset.validation import split_with_val
from tdof20.errors import TdofError
from tdof20.formats.io import safe_inside
from tdof20.progress import progress as progress_bar


def dataset_digest(dataset_root: str | Path, split: str, images: list[tuple[int, int]] | None = None) -> str:
    """A short content digest of what a training shard is made from: the dataset's models_info (what
    each object id means), the images (``images``, else the split's train part) and the bytes of
    their scenes' scene_gt.json and scene_camera.json (poses and cameras). Content, not sizes and
    mtimes: a copied dataset keeps its digest, a rebuilt or another one does not. Cheap (the label
    files, not the images; a changed image with the same labels is not seen)."""
    ds = open_dataset(dataset_root)
    folder = ds.scene_folder(split)
    frames = sorted(images) if images is not None else sorted(ds.part_frames(split, "train", "train on"))
    h = hashlib.sha256(json.dumps({str(k): v for k, v in sorted(ds.models_info.items())}, sort_keys=True,
                                  default=str).encode())
    h.update(json.dumps([list(x) for x in frames]).encode())
    for sid in sorted({s for s, _ in frames}):
        d = ds.scene_dir(sid, folder)
        for name in ("scene_gt.json", "scene_camera.json"):
            p = d / name
            h.update(f"{sid}/{name}".encode())
            if p.is_file():
                h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()[:16]


DIGEST_ATTR = "dataset_sha256"


def _shard_attrs(path: Path) -> dict:
    try:
        with h5py.File(path, "r") as f:
            return dict(f.attrs)
    except OSError as e:
        raise TdofError(f"not a readable tdof20 shard ({e})", path) from None


def check_shard_dataset(path: Path, dataset_root: Path, digest: str | None) -> None:
    """Refuse a shard made from another dataset: its recorded digest differs, or an object id it
    uses means another object (another models_info entry) in ``dataset_root``."""
    attrs = _shard_attrs(path)
    old = attrs.get(DIGEST_ATTR)
    if digest is not None and old is not None and str(old) != digest:
        raise TdofError(f"was made from other data (dataset digest {old}, {dataset_root} has {digest}): "
                        "pack it again from this dataset or give the dataset it came from", path)
    info = attrs.get("models_info")
    if info:
        try:
            theirs = {int(k): v for k, v in json.loads(info).items()}
        except (ValueError, TypeError, AttributeError):
            raise TdofError("its models_info attribute is not JSON of object ids", path) from None
        ours = open_dataset(dataset_root).models_info
        with h5py.File(path, "r") as f:
            used = sorted({int(o) for o in f["obj_id"][:].ravel() if o > 0}) if "obj_id" in f else []
        for o in used:
            a, b = theirs.get(o), ours.get(o)
            da = None if not isinstance(a, dict) else a.get("diameter")
            db = None if not isinstance(b, dict) else b.get("diameter")
            if b is None or (da is not None and db is not None and abs(float(da) - float(db)) > 1e-3):
                what = "has no such object" if b is None else f"its diameter is {float(db):g} mm, the shard's {float(da):g} mm"
                raise TdofError(f"was made from another dataset: object {o} in it is another object in {dataset_root} "
                                f"({what})", path)


def _stamp(path: Path, digest: str) -> None:
    with h5py.File(path, "r+") as f:
        f.attrs[DIGEST_ATTR] = digest


def shard_for(dataset_root: Path, split: str, out_run: Path, shard: str | Path | None, rank: int,
               show: bool, cache_dir: str | Path | None = None, images: list | None = None,
               part: str = "train", digest: str | None = None) -> Path:
    """The HDF5 shard a training reads: ``shard`` as given, else the split's train part (or the
    ``images`` of ``part``) packed into RUN/data/ by process 0 on first use. ``digest``
    (:func:`dataset_digest`): recorded in a shard packed here; a shard made from other data (its
    digest or its objects differ) is refused, a cached one included (the run's data/ is the run's,
    not a cache to refresh behind its back)."""
    if cache_dir is None:  # the restored-depth cache inside the dataset: no symlink out of it
        safe_inside(dataset_root, dataset_root / ".cache")
    if shard is not None:
        path = Path(shard)
        if not path.exists():
            raise TdofError("no such shard (write one with `tdof20 dataset pack`)", path)
        check_shard_dataset(path, dataset_root, digest)
        return path
    if images is None:
        path = out_run / "data" / f"{split}_train.h5"
        if rank == 0:
            if path.exists():
                check_shard_dataset(path, dataset_root, digest)
            else:
                pack(dataset_root, split, "train", path, show_progress=show, cache_dir=cache_dir)
                if digest is not None:
                    _stamp(path, digest)
        return path
    # a subset of the train part (train minus validation, or an explicit list)
    path = out_run / "data" / f"{split}_{part}.h5"
    if rank == 0 and path.exists():
        check_shard_dataset(path, dataset_root, digest)
    elif rank == 0:
        ds = open_dataset(dataset_root, cache_dir=cache_dir)
        scene_folder = ds.scene_folder(split)
        ds.render_restored(images, scene_folder, show_progress=show)
        with progress_bar(show) as bar:
            task = bar.add_task(f"packing {split}/{part}", total=len(images))
            pack_shard(images, ds, path, {"split": split, "part": part, "dataset": str(dataset_root.resolve()),
                                          "layout": ds.layout, **({DIGEST_ATTR: digest} if digest else {})},
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
