"""The BOP toolkit's standard layout (e.g. YCB-Video, or ``dataset build --layout bop``)::

    ROOT/camera.json  ROOT/models/ [ROOT/models_eval/]  ROOT/test_targets_bop19.json
    ROOT/{train,train_pbr,train_real,val,test,test_*}/{scene_id:06d}/   BOP scenes
    [ROOT/tdof20_bop.json]  [ROOT/object_names.json]

A split is a split folder (``train_pbr``, ``test`` ...); its frames are every image of its scenes,
except in the folder the targets belong to ("test", else the only ``test*`` folder), whose test
part is the images test_targets_bop19.json names. Object names are ``obj_000005``-style unless
``ROOT/object_names.json`` ({"<obj_id>": name}) or ``names=`` gives them. Scene ids are only
unique within a split folder: a dataset opened with ``split=`` (or a dataset with one split
folder) looks scenes up in that folder.
"""

from __future__ import annotations

import re
from pathlib import Path

from tdof20.dataset.layouts.base import DatasetReader, is_scene
from tdof20.errors import TdofError
from tdof20.formats.io import read_json

BOP_TARGETS = "test_targets_bop19.json"
BOP_INFO = "tdof20_bop.json"  # what `dataset build --layout bop` adds: protocol, scene names
SPLIT_FOLDER = re.compile(r"^(train|val|test)(_[A-Za-z0-9]+)?$")


def bop_split_folders(root: str | Path) -> list[str]:
    """The split folders of a BOP dataset root: names like train, train_pbr, val, test, test_primesense
    holding at least one ``{scene_id:06d}/`` scene with a scene_camera.json."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and SPLIT_FOLDER.match(p.name)
                  and any(is_scene(s) for s in p.iterdir()))


class BopReader(DatasetReader):
    """A dataset in the standard BOP layout (see the module docstring)."""

    layout = "bop"
    info_file = BOP_INFO
    split_hint = "a split folder such as test"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return bool(bop_split_folders(root))

    def _read_info(self) -> dict:
        self._folders = bop_split_folders(self.root)
        path = self.root / BOP_INFO
        info = read_json(path) if path.is_file() else {}
        if not isinstance(info, dict):
            raise TdofError("must hold a JSON object", path)
        return info

    # ------------------------------------------------------------------ splits and scenes
    def splits(self) -> list[str]:
        """The split folders."""
        return list(self._folders)

    def check_split(self, split: str | None) -> str:
        """A split folder with scenes (default: the bound split, else the only folder)."""
        split = split if split is not None else self.split
        if split is None:
            if len(self._folders) == 1:
                return self._folders[0]
            raise TdofError(f"give a split: the BOP dataset has the split folders {', '.join(self._folders)}",
                            self.root)
        if split not in self._folders:
            raise TdofError(f"no split folder '{split}' with scenes (the dataset has "
                            f"{', '.join(self._folders)})", self.root)
        return split

    def scene_folder(self, split: str | None) -> str:
        """The split folder itself, checked: scene ids are unique only within one."""
        return self.check_split(split)

    def _scenes_root(self, split: str | None = None) -> Path:
        return self.root / self.check_split(split)

    def _default_scene_name(self, scene_id: int, split: str | None) -> str:
        return f"{self.check_split(split)}/{int(scene_id):06d}"

    def targets_split(self) -> str | None:
        """The split folder test_targets_bop19.json belongs to ('test', else the only test* folder)."""
        if "test" in self._folders:
            return "test"
        tests = [f for f in self._folders if f.startswith("test")]
        return tests[0] if len(tests) == 1 else None

    def targets_path(self, split: str | None = None) -> Path:
        """ROOT/test_targets_bop19.json, whatever the split."""
        return self.root / BOP_TARGETS

    def _frames_of(self, split: str, part: str) -> list[tuple[int, int]]:
        """Every image of the split folder's scenes, except the test part of the targets' folder:
        the images of test_targets_bop19.json."""
        if part == "test" and split == self.targets_split() and (self.root / BOP_TARGETS).is_file():
            seen = dict.fromkeys((int(t["scene_id"]), int(t["im_id"])) for t in self.read_targets()
                                 if isinstance(t, dict) and "scene_id" in t and "im_id" in t)
            return sorted(seen)
        out = []
        for sid in self.scene_ids(split):
            out += [(sid, im) for im in self.scene(sid, split, require_gt=False).im_ids()]
        return out

    def _cache_key(self, split: str | None) -> str:
        return self.check_split(split)

    # ------------------------------------------------------------------ decisions
    def check_train_split(self, split: str | None) -> str:
        """A split folder with scenes."""
        return self.check_split(split)

    def part_frames(self, split: str | None, part: str, purpose: str) -> list[tuple[int, int]]:
        images = self.frames(split, part)
        if not images:
            raise TdofError(f"the split folder {self.check_split(split)}/ of this dataset has no "
                            f"{'images' if part == 'train' else 'test images'}: nothing to {purpose}", self.root)
        return images

    def empty_part_text(self, split: str, part: str) -> str:
        return f"the split folder {split}/ has no images"

    def scoring_targets_path(self, split: str) -> Path:
        """test_targets_bop19.json, which holds the targets of :meth:`targets_split` only."""
        if split != self.targets_split():
            raise TdofError(f"{self.targets_path().name} holds the targets of the split folder "
                            f"{self.targets_split()}/, not {split}/: score with --split "
                            f"{self.targets_split()} or give --targets FILE", self.root)
        return self.targets_path()

    def stats_folders(self) -> list[str]:
        return self.splits()

    def split_counts(self) -> dict[str, int]:
        """{"targets": the targets of test_targets_bop19.json}."""
        return {"targets": len(self.read_targets()) if self.targets_path().is_file() else 0}


__all__ = ["BOP_INFO", "BOP_TARGETS", "BopReader", "SPLIT_FOLDER", "bop_split_folders"]
