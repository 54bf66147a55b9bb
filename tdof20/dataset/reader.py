"""One dataset reader for tdof20's layout and BOP's standard one (docs/dataset.md).

    ds = open_dataset(ROOT)                        # detects the layout
    ds.layout, ds.obj_ids, ds.object_name(5)       # "tdof20" | "bop", [1, 5, 30], "obj_000005"
    ds.frames("simple", "train")                   # [(scene_id, im_id), ...] of a split part
    ds.scene(28).rgb(0); ds.depth_mm(28, 0, "restored")

Two layouts, one answer to every question stats, packing, training, prediction and scoring ask:

- **tdof20** (``tdof20 dataset build``; the TDoF20 importer's output too)::

      ROOT/dataset_info.json   {"scenes": {"<scene_id>": "single/cube_136", ...}, ["objects": {id: name}]}
      ROOT/camera.json  ROOT/models/ [ROOT/models_eval/]
      ROOT/scenes/{scene_id:06d}/               BOP scenes (+ depth_restored/, depth_stabilized/ ...)
      ROOT/splits/{split}_{train,test}.json     {"<scene_id>": [im_id, ...]}
      ROOT/test_targets_{split}.json            BOP targets of a split's test part

  A split is a protocol (``simple``, ``hard``) with a train and a test part.

- **BOP** (the BOP toolkit's standard layout, e.g. YCB-Video, or ``dataset build --layout bop``)::

      ROOT/camera.json  ROOT/models/ [ROOT/models_eval/]  ROOT/test_targets_bop19.json
      ROOT/{train,train_pbr,train_real,val,test,test_*}/{scene_id:06d}/   BOP scenes

  A split is a split folder (``train_pbr``, ``test`` ...); its frames are every image of its
  scenes, except in the folder the targets belong to ("test", else the only ``test*`` folder),
  whose test part is the images test_targets_bop19.json names. Object names are
  ``obj_000005``-style unless ``ROOT/object_names.json`` ({"<obj_id>": name}) or ``names=`` gives
  them. Scene ids are only unique within a split folder: a Dataset opened with ``split=`` (or a
  dataset with one split folder) looks scenes up in that folder.

Depth modes: ``raw`` (depth/), ``filled`` (computed from raw by the methods), ``stabilized``
(depth_stabilized/, where a dataset brings one), ``restored`` (depth_restored/; where a dataset
has none it is rendered once from the models and the ground-truth poses — the model surfaces'
depth composited into the sensor depth — and cached under ``ROOT/.cache/depth_restored/``, or
under ``cache_dir`` when ROOT is read-only).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop import (MODELS_INFO, SCENE_CAMERA, BopScene, colour_path, model_path, read_model_mesh,
                                read_models_info, read_scene)
from tdof20.formats.io import read_json, read_png, write_json, write_png

LAYOUTS = ("tdof20", "bop")
PARTS = ("train", "test")
DATASET_INFO = "dataset_info.json"
BOP_TARGETS = "test_targets_bop19.json"
BOP_INFO = "tdof20_bop.json"  # what `dataset build --layout bop` adds: protocol, scene names
NAMES_FILE = "object_names.json"
KEYPOINTS_FILE = "keypoints.json"
CACHE_DIR = ".cache"
NOT_A_DATASET = ("not a dataset: neither a tdof20 dataset (dataset_info.json) nor a BOP dataset "
                 "(split folders with scenes)")
SPLIT_FOLDER = re.compile(r"^(train|val|test)(_[A-Za-z0-9]+)?$")
_SCENE_FOLDER = re.compile(r"^\d{6}$")
#: extra depth folders a scene may bring, by depth mode
DEPTH_DIRS = {"raw": "depth", "stabilized": "depth_stabilized", "restored": "depth_restored"}
DEPTH_MODES = ("raw", "filled", "stabilized", "restored")


def _is_scene(d: Path) -> bool:
    return d.is_dir() and bool(_SCENE_FOLDER.match(d.name)) and (d / SCENE_CAMERA).is_file()


def bop_split_folders(root: str | Path) -> list[str]:
    """The split folders of a BOP dataset root: names like train, train_pbr, val, test, test_primesense
    holding at least one ``{scene_id:06d}/`` scene with a scene_camera.json."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and SPLIT_FOLDER.match(p.name)
                  and any(_is_scene(s) for s in p.iterdir()))


def detect_layout(root: str | Path) -> str:
    """'tdof20' or 'bop'; a one-line TdofError for a folder that is neither."""
    root = Path(root)
    if not root.is_dir():
        raise TdofError("no such dataset folder", root)
    if (root / DATASET_INFO).is_file():
        return "tdof20"
    if bop_split_folders(root):
        return "bop"
    raise TdofError(NOT_A_DATASET, root)


def open_dataset(root: str | Path, split: str | None = None, *, names: str | Path | None = None,
                 cache_dir: str | Path | None = None) -> "Dataset":
    """The dataset at ``root`` in either layout (see the module docstring). ``split``: the split the
    caller works on (tdof20: a protocol such as 'simple'; BOP: a split folder such as 'test'),
    the default of the methods that take one. ``names``: a JSON file {"<obj_id>": name} naming
    a BOP dataset's objects. ``cache_dir``: where rendered restored depth goes (default ROOT/.cache)."""
    root = Path(root)
    layout = detect_layout(root)
    ds = Dataset(root, layout, cache_dir=Path(cache_dir) if cache_dir is not None else root / CACHE_DIR)
    ds._load(names)
    if split is not None:
        ds.split = ds.check_split(split)
    return ds


def composite_model_depth(sensor_mm: np.ndarray, model_mm: np.ndarray) -> np.ndarray:
    """Restored depth (H,W) float32 mm: the model surfaces' depth ``model_mm`` (0 = no surface)
    wherever a surface is nearer than the sensor's depth or the sensor has none, the sensor's
    depth elsewhere (0 stays 0)."""
    s = np.asarray(sensor_mm, np.float32)
    m = np.asarray(model_mm, np.float32)
    take = (m > 0) & ((s <= 0) | (m < s))
    return np.where(take, m, s).astype(np.float32)


@dataclass
class Dataset:
    """A dataset root read through one interface; see :func:`open_dataset`."""

    root: Path
    layout: str
    split: str | None = None
    cache_dir: Path | None = None
    info: dict = field(default_factory=dict)
    camera: dict | None = None
    object_names: dict[int, str] = field(default_factory=dict)
    _scenes: dict = field(default_factory=dict, repr=False)
    _models_info: dict | None = field(default=None, repr=False)
    _keypoints: dict = field(default_factory=dict, repr=False)
    _folders: list[str] = field(default_factory=list, repr=False)

    # ------------------------------------------------------------------ loading
    def _load(self, names: str | Path | None) -> None:
        r = self.root
        if self.layout == "tdof20":
            info = read_json(r / DATASET_INFO)
            if not isinstance(info, dict) or not isinstance(info.get("scenes", {}), dict):
                raise TdofError("not a tdof20 dataset_info.json (a JSON object with 'scenes' "
                                "{\"<scene_id>\": name})", r / DATASET_INFO)
            self.info = info
        else:
            self._folders = bop_split_folders(r)
            self.info = read_json(r / BOP_INFO) if (r / BOP_INFO).is_file() else {}
            if not isinstance(self.info, dict):
                raise TdofError("must hold a JSON object", r / BOP_INFO)
        if (r / "camera.json").is_file():
            cam = read_json(r / "camera.json")
            self.camera = cam if isinstance(cam, dict) else None
        if not (self.models_dir / MODELS_INFO).is_file():
            raise TdofError(f"the dataset has no models/{MODELS_INFO} (a BOP models folder)", r)
        given = names if names is not None else (r / NAMES_FILE if (r / NAMES_FILE).is_file() else None)
        raw_names = read_json(given) if given is not None else self.info.get("objects")
        if raw_names is not None:
            where = Path(given) if given is not None else r / (DATASET_INFO if self.layout == "tdof20" else BOP_INFO)
            if not isinstance(raw_names, dict):
                raise TdofError("object names must be a JSON object {\"<obj_id>\": name}", where)
            try:
                self.object_names = {int(k): str(v) for k, v in raw_names.items()}
            except ValueError:
                raise TdofError("object names must be keyed by integer object ids", where) from None

    # ------------------------------------------------------------------ objects and models
    @property
    def models_dir(self) -> Path:
        return self.root / "models"

    @property
    def models_eval_dir(self) -> Path | None:
        d = self.root / "models_eval"
        return d if (d / MODELS_INFO).is_file() else None

    @property
    def models_info(self) -> dict[int, dict]:
        if self._models_info is None:
            self._models_info = read_models_info(self.models_dir)
        return self._models_info

    @property
    def obj_ids(self) -> list[int]:
        """The dataset's objects (models/models_info.json), ascending: any ids, any count."""
        return sorted(self.models_info)

    def object_name(self, obj_id: int) -> str:
        """The object's name: a names file or dataset_info's "objects"; for a tdof20 dataset the
        catalog's name; else ``obj_000005``."""
        obj_id = int(obj_id)
        if obj_id in self.object_names:
            return self.object_names[obj_id]
        if self.layout == "tdof20":
            try:
                from tdof20.objects import get_object  # the catalog (a higher room; names only)

                return get_object(obj_id).name
            except (TdofError, KeyError, ValueError, ImportError):
                pass
        return f"obj_{obj_id:06d}"

    def keypoints(self, obj_ids: list[int] | None = None) -> dict[int, np.ndarray]:
        """{obj_id: (9,3) mm}: models/keypoints.json when present, else the project's keypoint
        definition (:func:`tdof20.objects.keypoints.surface_keypoints`) of each PLY, cached."""
        ids = self.obj_ids if obj_ids is None else [int(o) for o in obj_ids]
        kp_file = self.models_dir / KEYPOINTS_FILE
        if kp_file.is_file() and not self._keypoints:
            data = read_json(kp_file)
            if not isinstance(data, dict):
                raise TdofError("must hold a JSON object {\"<obj_id>\": [[x, y, z], ...]}", kp_file)
            for k, v in data.items():
                try:
                    a = np.asarray(v, dtype=np.float64)
                    oid = int(k)
                except (ValueError, TypeError):
                    raise TdofError(f"object {k!r}: keypoints must be a list of [x, y, z] mm", kp_file) from None
                if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
                    raise TdofError(f"object {k}: keypoints must be a list of [x, y, z] mm", kp_file)
                self._keypoints[oid] = a
        missing = [o for o in ids if o not in self._keypoints]
        if missing:
            from tdof20.objects.keypoints import surface_keypoints  # the one keypoint definition

            for o in missing:
                V, F = read_model_mesh(model_path(self.models_dir, o))
                self._keypoints[o] = surface_keypoints(V, F)
        return {o: self._keypoints[o] for o in ids}

    # ------------------------------------------------------------------ splits and scenes
    def splits(self) -> list[str]:
        """tdof20: the protocols with split files (splits/{split}_{part}.json); BOP: the split folders."""
        if self.layout == "bop":
            return list(self._folders)
        d = self.root / "splits"
        found = {p.stem.rsplit("_", 1)[0] for p in d.glob("*.json") if p.stem.rsplit("_", 1)[-1] in PARTS} \
            if d.is_dir() else set()
        return sorted(found)

    def check_split(self, split: str | None) -> str | None:
        """``split`` checked against the dataset (None: the bound split, or a BOP dataset's only folder)."""
        split = split if split is not None else self.split
        if self.layout == "bop":
            if split is None:
                if len(self._folders) == 1:
                    return self._folders[0]
                raise TdofError(f"give a split: the BOP dataset has the split folders {', '.join(self._folders)}",
                                self.root)
            if split not in self._folders:
                raise TdofError(f"no split folder '{split}' with scenes (the dataset has "
                                f"{', '.join(self._folders)})", self.root)
            return split
        if split is not None and split not in self.splits():
            have = ", ".join(self.splits()) or "none"
            raise TdofError(f"unknown split '{split}' (this dataset's splits: {have})", self.root)
        return split

    def _scenes_root(self, split: str | None = None) -> Path:
        if self.layout == "tdof20":
            return self.root / "scenes"
        return self.root / self.check_split(split)

    def scene_ids(self, split: str | None = None) -> list[int]:
        """Scene ids (tdof20: every scene; BOP: those of the split folder)."""
        base = self._scenes_root(split)
        on_disk = {int(p.name) for p in base.iterdir() if _is_scene(p)} if base.is_dir() else set()
        if self.layout == "tdof20":
            on_disk |= {int(k) for k in self.info.get("scenes", {}) if str(k).isdigit()}
        return sorted(on_disk)

    def scene_dir(self, scene_id: int, split: str | None = None) -> Path:
        return self._scenes_root(split) / f"{int(scene_id):06d}"

    def scene_name(self, scene_id: int, split: str | None = None) -> str:
        """tdof20: dataset_info's name ('multi/08'); BOP: the name `--layout bop` recorded, else
        '<split>/000001'."""
        names = self.info.get("scenes") or {}
        if str(int(scene_id)) in names:
            return str(names[str(int(scene_id))])
        if self.layout == "bop":
            return f"{self.check_split(split)}/{int(scene_id):06d}"
        return str(scene_id)

    def scene(self, scene_id: int, split: str | None = None, require_gt: bool = True) -> BopScene:
        """The BOP scene (cached)."""
        d = self.scene_dir(scene_id, split)
        if d not in self._scenes:
            if not d.is_dir():
                raise TdofError(f"scene {scene_id} is not in the dataset", d)
            self._scenes[d] = read_scene(d, require_gt=require_gt)
        return self._scenes[d]

    def image_ids(self, scene_id: int, split: str | None = None) -> list[int]:
        return self.scene(scene_id, split).im_ids()

    def targets_split(self) -> str | None:
        """BOP: the split folder test_targets_bop19.json belongs to ('test', else the only test* folder)."""
        if self.layout != "bop":
            return None
        if "test" in self._folders:
            return "test"
        tests = [f for f in self._folders if f.startswith("test")]
        return tests[0] if len(tests) == 1 else None

    def targets_path(self, split: str | None = None) -> Path:
        """The test targets of a split: tdof20 ROOT/test_targets_{split}.json; BOP ROOT/test_targets_bop19.json."""
        if self.layout == "tdof20":
            split = split if split is not None else self.split
            if split is None:
                raise TdofError("give a split (its test targets are test_targets_{split}.json)", self.root)
            return self.root / f"test_targets_{split}.json"
        return self.root / BOP_TARGETS

    def read_targets(self, split: str | None = None) -> list[dict]:
        path = self.targets_path(split)
        data = read_json(path)
        if not isinstance(data, list):
            raise TdofError(f"must hold a JSON list of targets, got {type(data).__name__}", path)
        return data

    def frames(self, split: str | None = None, part: str = "train") -> list[tuple[int, int]]:
        """(scene_id, im_id) of a split's part, in order. tdof20: splits/{split}_{part}.json; BOP:
        every image of the split folder's scenes, except the test part of the targets' folder:
        the images of test_targets_bop19.json."""
        if part not in PARTS:
            raise TdofError(f"part must be one of {', '.join(PARTS)}, got '{part}'")
        split = self.check_split(split)
        if self.layout == "tdof20":
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
        if part == "test" and split == self.targets_split() and (self.root / BOP_TARGETS).is_file():
            seen = dict.fromkeys((int(t["scene_id"]), int(t["im_id"])) for t in self.read_targets()
                                 if isinstance(t, dict) and "scene_id" in t and "im_id" in t)
            return sorted(seen)
        out = []
        for sid in self.scene_ids(split):
            out += [(sid, im) for im in self.scene(sid, split, require_gt=False).im_ids()]
        return out

    # ------------------------------------------------------------------ images
    def rgb_path(self, scene_id: int, im_id: int, split: str | None = None) -> Path:
        """rgb/{im_id:06d}.png or .jpg (BOP allows both)."""
        return colour_path(self.scene_dir(scene_id, split) / "rgb", im_id)

    def depth_path(self, scene_id: int, im_id: int, mode: str = "raw", split: str | None = None) -> Path:
        """The stored depth PNG of a mode (raw, stabilized, restored; 'filled' is computed from raw)."""
        sub = DEPTH_DIRS.get("raw" if mode == "filled" else mode)
        if sub is None:
            raise TdofError(f"unknown depth mode '{mode}' (valid: {', '.join(DEPTH_MODES)})")
        return self.scene_dir(scene_id, split) / sub / f"{int(im_id):06d}.png"

    def depth_modes(self, split: str | None = None) -> tuple[str, ...]:
        """The depth modes this dataset offers (judged on the first scene of the split): raw and filled
        with depth/, stabilized with depth_stabilized/, restored always (stored or rendered)."""
        ids = self.scene_ids(split)
        modes = []
        if ids:
            d = self.scene_dir(ids[0], split)
            if (d / "depth").is_dir():
                modes += ["raw", "filled"]
            if (d / "depth_stabilized").is_dir():
                modes.append("stabilized")
        return tuple(modes + ["restored"])

    def restored_source(self, split: str | None = None) -> str:
        """'stored' when the scenes bring depth_restored/, else 'rendered'."""
        ids = self.scene_ids(split)
        return "stored" if ids and (self.scene_dir(ids[0], split) / "depth_restored").is_dir() else "rendered"

    def depth_mm(self, scene_id: int, im_id: int, mode: str = "raw", split: str | None = None) -> np.ndarray:
        """(H,W) float32 depth in mm of a stored mode (restored: stored, else the cached render,
        rendered now if missing). 'filled' is the raw depth here (the methods fill it)."""
        sc = self.scene(scene_id, split)
        s = np.float32(sc.depth_scale(im_id))
        if mode == "restored":
            p = self.restored_path(scene_id, im_id, split)
            if p is None:
                self.render_restored([(scene_id, im_id)], split, show_progress=False)
                p = self.restored_path(scene_id, im_id, split)
            return read_png(p, kind="depth").astype(np.float32) * s
        return read_png(self.depth_path(scene_id, im_id, mode, split), kind="depth").astype(np.float32) * s

    # ------------------------------------------------------------------ restored depth
    def _cache_key(self, split: str | None) -> str:
        return "scenes" if self.layout == "tdof20" else str(self.check_split(split))

    def cached_restored_path(self, scene_id: int, im_id: int, split: str | None = None) -> Path:
        base = self.cache_dir if self.cache_dir is not None else self.root / CACHE_DIR
        return base / "depth_restored" / self._cache_key(split) / f"{int(scene_id):06d}" / f"{int(im_id):06d}.png"

    def restored_path(self, scene_id: int, im_id: int, split: str | None = None) -> Path | None:
        """The restored depth PNG of an image: the scene's depth_restored/, else the cached render;
        None when neither exists yet."""
        p = self.depth_path(scene_id, im_id, "restored", split)
        if p.is_file():
            return p
        c = self.cached_restored_path(scene_id, im_id, split)
        return c if c.is_file() else None

    def missing_restored(self, frames: list[tuple[int, int]], split: str | None = None) -> list[tuple[int, int]]:
        return [(s, i) for s, i in frames if self.restored_path(s, i, split) is None]

    def render_restored(self, frames: list[tuple[int, int]], split: str | None = None,
                        show_progress: bool = True) -> int:
        """Render the restored depth of the ``frames`` that have none (stored or cached), once: the
        models' depth in the ground-truth poses (the project's ray caster) composited into the
        sensor depth (:func:`composite_model_depth`), written under the cache folder. Returns the
        number rendered; a one-line note and a progress bar say what happens."""
        from tdof20.geometry.camera import PinholeCamera
        from tdof20.geometry.raycast import ModelRaycaster
        from tdof20.progress import console, progress

        todo = self.missing_restored(frames, split)
        if not todo:
            return 0
        base = self.cached_restored_path(*todo[0], split).parents[2]
        _check_writable(base, self.root)
        if show_progress:
            console.print(f"note: {self.root} has no restored depth (depth_restored/) for {len(todo)} image(s): "
                          f"rendering it once from the models and poses into {base}", markup=False)
        meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        casters: dict[tuple, ModelRaycaster] = {}
        with progress(show_progress) as bar:
            task = bar.add_task("rendering restored depth", total=len(todo))
            for sid, im in todo:
                sc = self.scene(sid, split)
                raw_path = self.depth_path(sid, im, "raw", split)
                raw = read_png(raw_path, kind="depth") if raw_path.is_file() else None
                if raw is not None:
                    h, w = raw.shape
                else:
                    from tdof20.formats.io import png_header

                    rp = self.rgb_path(sid, im, split)
                    h, w = png_header(rp) if rp.suffix == ".png" else _jpeg_size(rp)
                ds = sc.depth_scale(im)
                gts = sc.gt.get(im, [])
                for g in gts:
                    o = int(g["obj_id"])
                    if o not in meshes:
                        meshes[o] = read_model_mesh(model_path(self.models_dir, o))
                key = (tuple(np.round(sc.K(im).reshape(-1), 9)), w, h, tuple(sorted({int(g["obj_id"]) for g in gts})))
                if key not in casters:
                    if len(casters) > 8:
                        casters.clear()
                    cam = PinholeCamera(sc.K(im), int(w), int(h), float(ds))
                    casters[key] = ModelRaycaster({o: meshes[o] for o in key[3]}, cam)
                rc = casters[key]
                poses = []
                for g in gts:
                    T = np.eye(4)
                    T[:3, :3], T[:3, 3] = g["cam_R_m2c"], g["cam_t_m2c"]
                    poses.append((int(g["obj_id"]), T))
                model = rc.render(poses).depth if poses else np.zeros((h, w), np.float32)
                sensor = raw.astype(np.float32) * np.float32(ds) if raw is not None else np.zeros((h, w), np.float32)
                out = composite_model_depth(sensor, model)
                write_png(self.cached_restored_path(sid, im, split), rc.camera.mm_to_depth(out))
                bar.advance(task)
        write_json(base.parent / "info.json", {"what": "restored depth rendered from the models and poses "
                                               "(tdof20.dataset.reader.render_restored)",
                                               "dataset": str(self.root.resolve())})
        return len(todo)

    # ------------------------------------------------------------------ summaries
    def describe(self) -> dict[str, Any]:
        """A short summary: layout, splits, objects (id -> name), models_eval, depth modes."""
        return {"layout": self.layout, "splits": self.splits(),
                "objects": {o: self.object_name(o) for o in self.obj_ids},
                "models_eval": self.models_eval_dir is not None,
                "source": self.info.get("source")}


def _jpeg_size(path: Path) -> tuple[int, int]:
    from tdof20.formats.bop import read_colour

    h, w = read_colour(path).shape[:2]
    return h, w


def _check_writable(folder: Path, root: Path) -> None:
    """Refuse, before rendering, a cache folder that cannot be written (a read-only ROOT)."""
    for up in [folder, *folder.parents]:
        if up.exists():
            if not up.is_dir() or not os.access(up, os.W_OK | os.X_OK):
                raise TdofError(f"cannot write the rendered restored depth under {folder} (not writable): give a "
                                "cache folder of your own (--cache-dir)", root)
            return


__all__ = ["Dataset", "open_dataset", "detect_layout", "bop_split_folders", "composite_model_depth", "LAYOUTS",
           "NOT_A_DATASET", "BOP_TARGETS", "BOP_INFO", "NAMES_FILE", "DEPTH_MODES", "PARTS"]
