"""tdof20's own layout (``tdof20 dataset build``; the TDoF20 importer's output too)::

    ROOT/dataset_info.json   {"scenes": {"<scene_id>": "single/cube_136", ...}, ["objects": {id: name}],
                              ["layout": {"<scene_id>": {"steps", "n_arms"}}]}
    ROOT/camera.json  ROOT/models/ [ROOT/models_eval/]
    ROOT/scenes/{scene_id:06d}/               BOP scenes (+ depth_restored/, depth_stabilized/ ...)
    ROOT/splits/{split}_{train,test}.json     {"<scene_id>": [im_id, ...]}
    ROOT/test_targets_{split}.json            BOP targets of a split's test part

A split is a protocol (``simple``, ``hard``: :mod:`tdof20.dataset.splits`) with a train and a test
part. Scene ids are unique in the dataset (single/<class> -> 1..20, multi/NN -> 21..40) and object
ids are the catalog's (1..20), which names the objects no names file names.
"""

from __future__ import annotations

from pathlib import Path

from tdof20.dataset.layouts.base import PARTS, TARGET_MIN_VISIB, DatasetReader
from tdof20.dataset.naming import MULTI_ID_OFFSET
from tdof20.dataset.splits import SPLIT_PART_SCENES, SPLITS, min_simple_steps, part_needs, scene_can_serve
from tdof20.errors import TdofError
from tdof20.formats.io import read_json
from tdof20.objects import get_object

DATASET_INFO = "dataset_info.json"


class Tdof20Reader(DatasetReader):
    """A dataset in tdof20's layout (see the module docstring)."""

    layout = "tdof20"
    info_file = DATASET_INFO
    split_hint = "simple or hard"
    uses_catalog_ids = True
    has_validation_arcs = True

    @classmethod
    def detect(cls, root: Path) -> bool:
        return (root / DATASET_INFO).is_file()

    def _read_info(self) -> dict:
        path = self.root / DATASET_INFO
        info = read_json(path)
        if not isinstance(info, dict) or not isinstance(info.get("scenes", {}), dict):
            raise TdofError("not a tdof20 dataset_info.json (a JSON object with 'scenes' "
                            "{\"<scene_id>\": name})", path)
        return info

    def object_name(self, obj_id: int) -> str:
        """The object's name: a names file or dataset_info's "objects", else the catalog's name,
        else ``obj_000005``."""
        obj_id = int(obj_id)
        if obj_id not in self.object_names:
            try:
                return get_object(obj_id).name
            except (TdofError, KeyError, ValueError):
                pass
        return super().object_name(obj_id)

    # ------------------------------------------------------------------ splits and scenes
    def splits(self) -> list[str]:
        """The protocols with split files (splits/{split}_{part}.json)."""
        d = self.root / "splits"
        found = {p.stem.rsplit("_", 1)[0] for p in d.glob("*.json") if p.stem.rsplit("_", 1)[-1] in PARTS} \
            if d.is_dir() else set()
        return sorted(found)

    def check_split(self, split: str | None) -> str | None:
        """``split`` (default: the bound split; None stays None) checked against the split files."""
        split = split if split is not None else self.split
        if split is not None and split not in self.splits():
            have = ", ".join(self.splits()) or "none"
            raise TdofError(f"unknown split '{split}' (this dataset's splits: {have})", self.root)
        return split

    def scene_folder(self, split: str | None) -> None:
        """None: every scene lies in ROOT/scenes/, whatever the split."""
        return None

    def _scenes_root(self, split: str | None = None) -> Path:
        return self.root / "scenes"

    def _listed_scene_ids(self) -> set[int]:
        return {int(k) for k in self.info.get("scenes", {}) if str(k).isdigit()}

    def _default_scene_name(self, scene_id: int, split: str | None) -> str:
        return str(scene_id)

    def targets_split(self) -> None:
        """None: each protocol has its own targets file."""
        return None

    def targets_path(self, split: str | None = None) -> Path:
        """ROOT/test_targets_{split}.json (default: the bound split)."""
        split = split if split is not None else self.split
        if split is None:
            raise TdofError("give a split (its test targets are test_targets_{split}.json)", self.root)
        return self.root / f"test_targets_{split}.json"

    def _frames_of(self, split: str | None, part: str) -> list[tuple[int, int]]:
        """splits/{split}_{part}.json, whose scenes the dataset must hold."""
        if split is None:
            raise TdofError("give a split (simple or hard)", self.root)
        path = self.root / "splits" / f"{split}_{part}.json"
        m = read_json(path)
        if not isinstance(m, dict):
            raise TdofError("must hold a JSON object {\"<scene_id>\": [im_id, ...]}", path)
        try:
            frames = [(int(s), int(i)) for s, ims in m.items() for i in ims]
        except (TypeError, ValueError):
            raise TdofError("must hold a JSON object {\"<scene_id>\": [im_id, ...]}", path) from None
        held = self.scene_ids(split)
        unknown = sorted({s for s, _ in frames} - set(held))
        if unknown:
            raise TdofError(f"names scene{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown))}, which "
                            f"the dataset does not hold (scenes/: {', '.join(map(str, held))})", path)
        return frames

    def _cache_key(self, split: str | None) -> str:
        return "scenes"

    # ------------------------------------------------------------------ decisions
    def check_train_split(self, split: str | None) -> str:
        """One of the protocols (:data:`tdof20.dataset.splits.SPLITS`)."""
        if split not in SPLITS:
            raise TdofError(f"--split must be one of {', '.join(SPLITS)}, got '{split}'")
        return split

    def check_part_request(self, split: str | None, part: str) -> None:
        """A protocol's train or test part."""
        if split not in SPLITS or part not in PARTS:
            raise TdofError(f"split must be one of {SPLITS} and part one of {PARTS}, got {split}/{part}")

    def part_frames(self, split: str | None, part: str, purpose: str) -> list[tuple[int, int]]:
        self.check_part_request(split, part)
        images = self.frames(split, part)
        if not images:
            takes = SPLIT_PART_SCENES.get((split, part), "")
            raise TdofError(f"the {split} split's {part} part of this dataset is empty (splits/{split}_{part}.json "
                            f"lists no images{'; it takes ' + takes if takes else ''}): nothing to {purpose}",
                            self.root)
        return images

    def empty_part_reason(self, split: str, part: str) -> str:
        """Why the ``part`` of ``split`` has no images, for a message: what the dataset holds
        against what the split needs."""
        scenes = {int(k): str(v) for k, v in (self.info.get("scenes") or {}).items()}
        arcs = self.info.get("layout") or {}
        n_single = sum(1 for s in scenes if s < MULTI_ID_OFFSET)
        holds = (f"the dataset has {n_single} single-object and {len(scenes) - n_single} multi-object "
                 f"scene{'s' if len(scenes) - n_single != 1 else ''} "
                 f"({', '.join(scenes[s] for s in sorted(scenes)) or 'none'})")
        serving = sorted(s for s in scenes if scene_can_serve(split, part, s))
        if not serving:
            return f"{holds}; {part_needs(split, part)}"
        if split == "simple" and part == "test":
            steps = sorted({arcs.get(str(s), {}).get("steps") for s in serving} - {None})
            return (f"its single-object scenes have {', '.join(map(str, steps)) or 'too few'} steps per arm "
                    f"position: a test arc needs at least {min_simple_steps()}")
        return f"{holds}, and its {split}/{part} scenes list no images"

    def empty_part_text(self, split: str, part: str) -> str:
        return (f"the {split} split's {part} part has no images (splits/{split}_{part}.json): "
                f"{self.empty_part_reason(split, part)}")

    def no_targets_reason(self, split: str) -> str:
        """Either no test image holds a visible enough instance, or the test part is empty (and why)."""
        try:
            self.check_part_request(split, "test")
            has_test = bool(self.frames(split, "test"))
        except TdofError:
            has_test = False
        return (f": its test images hold no object instance at least {TARGET_MIN_VISIB:.0%} visible" if has_test
                else f": {self.empty_part_reason(split, 'test')}")

    def scoring_targets_path(self, split: str) -> Path:
        """ROOT/test_targets_{split}.json of a protocol."""
        if split not in SPLITS:
            raise TdofError(f"unknown split {split!r} (use one of: {', '.join(SPLITS)})")
        return self.root / f"test_targets_{split}.json"

    def stats_folders(self) -> list[None]:
        return [None]

    def split_counts(self) -> dict[str, int]:
        """{"<split>_train", "<split>_test", "<split>_targets"} of each protocol with split files."""
        out = {}
        for split in dict.fromkeys(list(SPLITS) + self.splits()):
            if not any((self.root / "splits" / f"{split}_{p}.json").is_file() for p in PARTS):
                continue
            for part in PARTS:
                path = self.root / "splits" / f"{split}_{part}.json"
                out[f"{split}_{part}"] = len(self.frames(split, part)) if path.is_file() else 0
            out[f"{split}_targets"] = len(self.read_targets(split)) if self.targets_path(split).is_file() else 0
        return out


__all__ = ["DATASET_INFO", "Tdof20Reader"]
