"""The validation part of a dataset's protocols, computed from the rules of
:mod:`tdof20.dataset.splits` (the dataset holds no validation files: a dataset built before the
rules, or an imported TDoF20, gets the same part).

    val = part_images(ROOT, "simple", "val")           # [(scene_id, im_id), ...]
    fit = part_images(ROOT, "simple", "train-val")     # the train part without them
    tg = write_val_targets(ROOT, "simple")             # ROOT/.cache/val_targets_simple.json

Parts: ``train`` and ``test`` (as splits/{split}_{part}.json list them), ``val`` (simple: the
held-out arcs of the train part; hard: its held-out training scenes, arcs where a dataset has too
few training scenes of a kind to spare one, :func:`tdof20.dataset.splits.hard_val_scenes`, decided
among the scenes of the dataset's train part) and ``train-val`` (the train part minus ``val``).
Where an image sits on its
arm position's turntable: a tdof20 dataset built here records each scene's ``steps`` and ``n_arms``
(dataset_info.json "layout"; im_id = arm * steps + step); a scene without them (an imported
TDoF20) is taken as 4 arm positions of equally many frames, in the order of its image ids.
A BOP-layout dataset has no arm positions: it gets no validation part (a one-line error).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.layouts.base import TARGET_MIN_VISIB
from tdof20.dataset.splits import VAL_PART, part_of
from tdof20.dataset.stats import split_images
from tdof20.errors import TdofError
from tdof20.formats import write_json
from tdof20.formats.io import safe_inside

PARTS_WITH_VAL = ("train", "test", "val", "train-val")


def check_part(part: str, allowed: tuple[str, ...] = PARTS_WITH_VAL, option: str = "--part") -> str:
    if part not in allowed:
        raise TdofError(f"{option} must be one of {', '.join(allowed)}, got '{part}'")
    return part


def _positions(ds, sid: int) -> dict:
    """{"steps", "n_arms", "index"} of scene ``sid``: index None (im_id = arm * steps + step) or
    {im_id: position in the scene's sorted image ids}."""
    lay = (ds.info.get("layout") or {}).get(str(int(sid))) or {}
    if "steps" in lay:
        steps, n_arms = int(lay["steps"]), int(lay.get("n_arms", 4))
        return {"steps": steps, "n_arms": n_arms, "index": None}
    ims = sorted(ds.image_ids(sid))
    steps = max(1, -(-len(ims) // 4))
    return {"steps": steps, "n_arms": 4, "index": {im: n for n, im in enumerate(ims)}}


def split_with_val(root: str | Path, split: str) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(train minus validation, validation) of ``split``'s train part of the dataset at ``root``."""
    ds = open_dataset(root)
    if not ds.has_validation_arcs:
        raise TdofError("a BOP-layout dataset has no validation part (no turntable arcs): train on its split "
                        "folder and hold images out with an explicit list", root)
    train_images = ds.frames(split, "train")
    scenes = {sid for sid, _ in train_images}
    keep, val = [], []
    pos: dict[int, dict] = {}
    for sid, im in train_images:
        if sid not in pos:
            pos[sid] = _positions(ds, sid)
        p = pos[sid]
        k = im if p["index"] is None else p["index"].get(im, im)
        part = part_of(split, sid, k, p["steps"], p["n_arms"], with_val=True, scenes=scenes)
        (val if part == VAL_PART else keep).append((sid, im))
    return keep, val


def part_images(root: str | Path, split: str, part: str) -> list[tuple[int, int]]:
    """(scene_id, im_id) of ``part`` ('train', 'test', 'val', 'train-val') of ``split``."""
    check_part(part)
    if part in ("train", "test"):
        return split_images(root, split, part)
    keep, val = split_with_val(root, split)
    return val if part == "val" else keep


def val_targets(root: str | Path, split: str) -> list[dict]:
    """BOP targets [{"scene_id", "im_id", "obj_id", "inst_count"}] of the validation images: every
    object instance at least 10 % visible, as the test targets."""
    ds = open_dataset(root)
    out = []
    for sid, im in split_with_val(root, split)[1]:
        sc = ds.scene(sid)
        infos = sc.gt_info.get(im, [])
        counts = Counter(g["obj_id"] for g, gi in zip(sc.gt.get(im, []), infos)
                         if gi.get("visib_fract", 1.0) >= TARGET_MIN_VISIB)
        out += [{"scene_id": int(sid), "im_id": int(im), "obj_id": int(o), "inst_count": int(n)}
                for o, n in sorted(counts.items())]
    return out


def write_val_targets(root: str | Path, split: str, path: str | Path | None = None) -> Path:
    """Write :func:`val_targets` (default: ROOT/.cache/val_targets_{split}.json, atomically); returns the path.
    A validation part without targets is refused."""
    root = Path(root)
    path = Path(path) if path is not None else safe_inside(root, root / ".cache" / f"val_targets_{split}.json")
    tg = val_targets(root, split)
    if not tg:
        raise TdofError(f"the {split} split's validation part has no targets (too few turntable steps per arm "
                        "position for a validation arc, or no training scenes)", root)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, tg, indent=None)
    return path


__all__ = ["PARTS_WITH_VAL", "check_part", "part_images", "split_with_val", "val_targets", "write_val_targets"]
