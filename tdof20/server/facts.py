"""What the server may say about its dataset (read once at start): its protocols, scenes, images
and objects — all public in the published release — and the median distance of the objects from
the camera over the train images, which the metres check of a submission names (the scorer's own
check names the test images' median: a label, so the server checks before the scorer does), and
each protocol's validation part: its targets (the dataset's own cache ROOT/.cache/val_targets_{split}.json
where it holds any, else computed by :func:`tdof20.dataset.validation.val_targets`) less every image
that is a test image of any protocol (TDoF20's simple test images are hard train images): the
labels of what is left are in the public release, so their per-image errors may be shown.

Per object, the ADD(S) threshold (10 % of the diameter, models_eval/'s where the dataset has one,
as the scorer) and the dataset's label-noise floor beside it: the median ``trans_mm`` bound
(scene_gt_uncertainty.json) over the object's labels in each protocol's test part (and
validation part), an aggregate of at least :data:`FLOOR_MIN_LABELS` bounded labels; never a
per-image value."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.results import Results, check_against_dataset, read_results
from tdof20.dataset.validation import val_targets
from tdof20.errors import TdofError
from tdof20.formats.bop_models import read_models_info
from tdof20.formats.bop_uncertainty import SCENE_GT_UNCERTAINTY, read_uncertainty
from tdof20.formats.io import read_json
from tdof20.scoring.evaluation import ADD_THRESHOLD
from tdof20.server.publish import hidden_frames

PARTS = ("test", "val")
FLOOR_MIN_LABELS = 5  # fewer bounded labels of an object in a part: no floor shown (a median of one is its value)


def validation_targets(root: str | Path, split: str, hidden: dict[int, set[int]] | None = None) -> list[dict]:
    """BOP targets of ``split``'s validation part without any hidden (test) image; [] when it has none."""
    root = Path(root)
    hidden = hidden_frames(root) if hidden is None else hidden
    cached = root / ".cache" / f"val_targets_{split}.json"
    targets = read_json(cached) if cached.is_file() else []
    if not targets:
        try:
            targets = val_targets(root, split)
        except TdofError:  # a layout without turntable arcs: no validation part
            targets = []
    return [t for t in targets if int(t["im_id"]) not in hidden.get(int(t["scene_id"]), set())]


def label_floors(ds, frames, folder: str | None = None) -> dict[int, dict]:
    """{obj_id: {"bounded": n, "floor_mm": median trans_mm bound or None}} over the labels of the
    images ``frames`` [(scene_id, im_id)] (scenes without scene_gt_uncertainty.json: no bounds);
    ``floor_mm`` is None under :data:`FLOOR_MIN_LABELS` bounded labels."""
    want: dict[int, set[int]] = {}
    for sid, im in frames:
        want.setdefault(int(sid), set()).add(int(im))
    vals: dict[int, list[float]] = {}
    for sid, ims in sorted(want.items()):
        d = ds.scene_dir(sid, folder)
        if not (d / SCENE_GT_UNCERTAINTY).is_file():
            continue
        unc = read_uncertainty(d, ds.scene(sid, folder).gt) or {}
        for im in ims:
            for e in unc.get(im, []):
                vals.setdefault(int(e["obj_id"]), []).append(float(e["trans_mm"]))
    return {o: {"bounded": len(v), "floor_mm": float(np.median(v)) if len(v) >= FLOOR_MIN_LABELS else None}
            for o, v in vals.items()}


class DatasetFacts:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        ds = open_dataset(self.root)
        self.splits = [s for s in ds.splits() if ds.scoring_targets_path(s).is_file()]
        if not self.splits:
            raise TdofError("the dataset has no protocol with test targets (test_targets_{split}.json)", self.root)
        self.scene_ids = set(ds.scene_ids())
        self.images = {s: set(ds.image_ids(s)) for s in self.scene_ids}
        self.obj_ids = set(ds.obj_ids)
        hidden = hidden_frames(self.root)
        dists = []
        for s in sorted(self.scene_ids):
            gt = read_json(ds.scene_dir(s) / "scene_gt.json")
            for im, insts in gt.items():
                if int(im) not in hidden.get(s, set()):
                    dists += [float(np.linalg.norm(g["cam_t_m2c"])) for g in insts]
        self.train_distance_mm = float(np.median(dists)) if dists else None
        self.val_targets = {s: validation_targets(self.root, s, hidden) for s in self.splits}
        self.val_images = {s: {(int(t["scene_id"]), int(t["im_id"])) for t in tg} for s, tg in self.val_targets.items()}
        eval_dir = ds.models_eval_dir
        infos = read_models_info(eval_dir) if eval_dir is not None else ds.models_info
        thresholds = {int(o): ADD_THRESHOLD * float(e["diameter"]) for o, e in infos.items()}
        self.objects: dict[tuple[str, str], dict[str, dict]] = {}
        for s in self.splits:
            folder = ds.scene_folder(s)
            for part, frames in (("test", ds.frames(s, "test")), ("val", sorted(self.val_images[s]))):
                floors = label_floors(ds, frames, folder)
                self.objects[(s, part)] = {str(o): {"threshold_mm": thr, **floors.get(o, {"bounded": 0, "floor_mm": None})}
                                           for o, thr in sorted(thresholds.items())}

    def object_facts(self, split: str, part: str = "test") -> dict[str, dict]:
        """{str(obj_id): {"threshold_mm", "bounded", "floor_mm"}} of ``split``'s ``part``: each object's
        ADD(S) threshold and label-noise floor (None: not recorded, or too few bounded labels)."""
        return self.objects.get((split, part), {})

    def parts(self, split: str) -> tuple[str, ...]:
        """The parts of ``split`` a submission may be scored on."""
        return PARTS if self.val_targets.get(split) else PARTS[:1]

    def check(self, path: Path, split: str, part: str = "test") -> Results:
        """The strict checks of a results file (the reader's, then ids and units against the
        dataset); a TdofError with a line number on the first problem."""
        if split not in self.splits:
            raise TdofError(f"split must be one of {', '.join(self.splits)}, got {split[:40]!r}")
        if part not in self.parts(split):
            raise TdofError(f"part must be one of {', '.join(self.parts(split))} for {split}, got {part[:40]!r}")
        res = read_results(path)
        check_against_dataset(res, self.scene_ids, lambda s: self.images[s], self.obj_ids, self.train_distance_mm)
        return res


__all__ = ["DatasetFacts", "FLOOR_MIN_LABELS", "PARTS", "label_floors", "validation_targets"]
