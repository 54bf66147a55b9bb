"""``scene_gt_uncertainty.json``: 95 % bounds on each label's own error, beside a scene's
scene_gt.json (optional: scenes annotated before issue 34 have none)::

    {"<im_id>": [{"obj_id": 5, "rot_deg": 0.4, "trans_mm": 0.6, "surface_mm": 0.5}, ...], ...}

Keyed as scene_gt.json (the same image ids), each image's list in scene_gt.json's order (one entry
per instance, the same obj_id): ``rot_deg`` the rotation's bound in degrees, ``trans_mm`` the
translation's in mm, ``surface_mm`` the mean model-surface distance's in mm; finite, >= 0.
:func:`read_uncertainty` reads and checks it against the scene's scene_gt; a problem is one
TdofError naming the file (docs/formats.md).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

from tdof20.errors import TdofError
from tdof20.formats.bop_json import by_image_id, is_int, is_num
from tdof20.formats.io import read_json

SCENE_GT_UNCERTAINTY = "scene_gt_uncertainty.json"
BOUNDS = ("rot_deg", "trans_mm", "surface_mm")  # the bounds of an entry, beside its obj_id


def parse_uncertainty(path: str | Path, data: Any, gt: dict[int, list[dict]]) -> dict[int, list[dict]]:
    """{im_id: [entry, ...]} of a scene_gt_uncertainty.json's ``data``, checked against the scene's
    ``gt`` ({im_id: scene_gt list}): the same image ids, the same list lengths, the same obj_id at
    each position, every bound a finite number >= 0. A TdofError (one line, naming ``path``) on
    the first problem."""
    path = Path(path)
    by_im = by_image_id(path, data)
    missing = sorted(set(gt) - set(by_im))
    if missing:
        raise TdofError(f"image {missing[0]} is in scene_gt.json but has no entry here"
                        + (f" ({len(missing) - 1} more images neither)" if len(missing) > 1 else ""), path)
    extra = sorted(set(by_im) - set(gt))
    if extra:
        raise TdofError(f"image {extra[0]} has an entry here but none in scene_gt.json"
                        + (f" ({len(extra) - 1} more images neither)" if len(extra) > 1 else ""), path)
    out: dict[int, list[dict]] = {}
    for im_id in sorted(by_im):
        lst, insts = by_im[im_id], gt[im_id]
        if not isinstance(lst, list):
            raise TdofError(f"image {im_id}: must be a list of entries, got {type(lst).__name__}", path)
        if len(lst) != len(insts):
            raise TdofError(f"image {im_id} lists {len(lst)} entries but scene_gt.json has {len(insts)} instances",
                            path)
        for n, (e, g) in enumerate(zip(lst, insts)):
            w = f"image {im_id} entry {n}"
            if not isinstance(e, dict):
                raise TdofError(f"{w}: must be an object, got {type(e).__name__}", path)
            if not is_int(e.get("obj_id")):
                raise TdofError(f"{w}: obj_id must be an integer, got {e.get('obj_id')!r}", path)
            if int(e["obj_id"]) != int(g["obj_id"]):
                raise TdofError(f"{w} is obj {e['obj_id']} but scene_gt.json has obj {g['obj_id']}", path)
            for k in BOUNDS:
                if k not in e:
                    raise TdofError(f"{w}: missing field '{k}'", path)
                if not is_num(e[k]) or e[k] < 0:
                    raise TdofError(f"{w}: {k} must be a finite number >= 0, got {e[k]!r}", path)
        out[im_id] = copy.deepcopy(lst)
    return out


def read_uncertainty(scene_dir: str | Path, gt: dict[int, list[dict]]) -> dict[int, list[dict]] | None:
    """The checked bounds of the scene folder ``scene_dir`` (:func:`parse_uncertainty` against its
    scene_gt ``gt``); None when the scene has no scene_gt_uncertainty.json."""
    path = Path(scene_dir) / SCENE_GT_UNCERTAINTY
    if not path.exists():
        return None
    return parse_uncertainty(path, read_json(path), gt)


__all__ = ["BOUNDS", "SCENE_GT_UNCERTAINTY", "parse_uncertainty", "read_uncertainty"]
