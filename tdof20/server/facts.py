"""What the server may say about its dataset (read once at start): its protocols, scenes, images
and objects — all public in the published release — and the median distance of the objects from
the camera over the train images, which the metres check of a submission names (the scorer's own
check names the test images' median: a label, so the server checks before the scorer does), and
each protocol's validation part: its targets (the dataset's own cache ROOT/.cache/val_targets_{split}.json
where it holds any, else computed by :func:`tdof20.dataset.validation.val_targets`) less every image
that is a test image of any protocol (TDoF20's simple test images are hard train images): the
labels of what is left are in the public release, so their per-image errors may be shown."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.results import Results, check_against_dataset, read_results
from tdof20.dataset.validation import val_targets
from tdof20.errors import TdofError
from tdof20.formats.io import read_json
from tdof20.server.publish import hidden_frames

PARTS = ("test", "val")


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


__all__ = ["DatasetFacts", "PARTS", "validation_targets"]
