"""The dataset reader's interface and everything the layouts share (docs/dataset.md).

A layout (:mod:`tdof20.dataset.layouts.tdof20`, :mod:`tdof20.dataset.layouts.bop`) is one subclass
of :class:`DatasetReader`: it says whether a folder is in its layout (:meth:`DatasetReader.detect`),
reads its own index files, and answers the questions whose answer depends on the layout — its
splits and scenes, its frames and targets, and the decisions the builders, the methods and the
scorer would otherwise make on the layout's name (:attr:`~DatasetReader.uses_catalog_ids`,
:meth:`~DatasetReader.scene_folder`, :meth:`~DatasetReader.part_frames`, ...). Everything else —
objects, models, keypoints, scenes, images, depth modes, the restored depth rendered where a
dataset has none, the summary — is here, once.

Depth modes: ``raw`` (depth/), ``filled`` (computed from raw by the methods), ``stabilized``
(depth_stabilized/, where a dataset brings one), ``restored`` (depth_restored/; where a dataset
has none it is rendered once from the models and the ground-truth poses — the model surfaces'
depth composited into the sensor depth — and cached under ``ROOT/.cache/depth_restored/``, or
under ``cache_dir`` when ROOT is read-only).
"""

from __future__ import annotations

import os
import re
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop import (MODELS_INFO, SCENE_CAMERA, BopScene, colour_path, model_path, read_colour,
                                read_model_mesh, read_models_info, read_scene)
from tdof20.formats.io import png_header, read_json, read_png, safe_inside, write_json, write_png
from tdof20.geometry.camera import PinholeCamera
from tdof20.objects.keypoints import surface_keypoints
from tdof20.progress import console, progress

PARTS = ("train", "test")
NAMES_FILE = "object_names.json"
KEYPOINTS_FILE = "keypoints.json"
CACHE_DIR = ".cache"
TARGET_MIN_VISIB = 0.1  # BOP: instances at least 10 % visible are targets
#: extra depth folders a scene may bring, by depth mode
DEPTH_DIRS = {"raw": "depth", "stabilized": "depth_stabilized", "restored": "depth_restored"}
DEPTH_MODES = ("raw", "filled", "stabilized", "restored")
_SCENE_FOLDER = re.compile(r"^\d{6}$")


def is_scene(d: Path) -> bool:
    """Whether ``d`` is a BOP scene folder: ``{scene_id:06d}/`` with a scene_camera.json."""
    return d.is_dir() and bool(_SCENE_FOLDER.match(d.name)) and (d / SCENE_CAMERA).is_file()


def composite_model_depth(sensor_mm: np.ndarray, model_mm: np.ndarray) -> np.ndarray:
    """Restored depth (H,W) float32 mm: the model surfaces' depth ``model_mm`` (0 = no surface)
    wherever a surface is nearer than the sensor's depth or the sensor has none, the sensor's
    depth elsewhere (0 stays 0)."""
    s = np.asarray(sensor_mm, np.float32)
    m = np.asarray(model_mm, np.float32)
    take = (m > 0) & ((s <= 0) | (m < s))
    return np.where(take, m, s).astype(np.float32)


class DatasetReader(ABC):
    """A dataset root read through one interface; open one with
    :func:`tdof20.dataset.layouts.open_dataset`, which picks the layout's subclass.

    ``split``: the split bound at opening (the default of the methods that take one);
    ``info``: the layout's index file as read (tdof20: dataset_info.json; BOP: tdof20_bop.json or {});
    ``camera``: ROOT/camera.json (None when absent); ``object_names``: {obj_id: name} given by a
    names file or the index file."""

    #: the layout's name, for display, describe() and the shards' attributes only (never decide on it)
    layout: ClassVar[str]
    #: the file an index's "objects" names come from, for messages
    info_file: ClassVar[str]
    #: what a --split names in this layout, for messages ('simple or hard', 'a split folder such as test')
    split_hint: ClassVar[str]
    #: whether the object ids are the catalog's (1..20): a run then keeps the catalog's 20 classes when the
    #: dataset's ids lie within 1..20, and the objects models_info lacks come from the catalog
    uses_catalog_ids: ClassVar[bool] = False
    #: whether each scene's images lie on turntable arcs, so that a validation part can be carved out of
    #: a split's train part (:mod:`tdof20.dataset.validation`)
    has_validation_arcs: ClassVar[bool] = False

    def __init__(self, root: str | Path, *, names: str | Path | None = None, cache_dir: str | Path | None = None):
        self.root = Path(root)
        self.split: str | None = None
        self.cache_dir = Path(cache_dir) if cache_dir is not None else self.root / CACHE_DIR
        #: writes into the default cache (inside the dataset) never follow a symlink (formats.io.safe_inside)
        self._cache_inside = cache_dir is None
        self.camera: dict | None = None
        self.object_names: dict[int, str] = {}
        self._scenes: dict[Path, BopScene] = {}
        self._models_info: dict[int, dict] | None = None
        self._keypoints: dict[int, np.ndarray] = {}
        self.info: dict = self._read_info()
        self._load(names)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.root)!r}, split={self.split!r})"

    # ------------------------------------------------------------------ what a layout says
    @classmethod
    @abstractmethod
    def detect(cls, root: Path) -> bool:
        """Whether the folder ``root`` holds a dataset in this layout (cheap: its index files)."""

    @abstractmethod
    def _read_info(self) -> dict:
        """The layout's index file as a dict (checked), read when the dataset is opened."""

    @abstractmethod
    def splits(self) -> list[str]:
        """The dataset's splits, by name."""

    @abstractmethod
    def check_split(self, split: str | None) -> str | None:
        """``split`` checked against the dataset (None: the bound split, or the layout's default)."""

    @abstractmethod
    def scene_folder(self, split: str | None) -> str | None:
        """The split folder a split's scenes are looked up in (None where scene ids are unique in the dataset)."""

    @abstractmethod
    def _scenes_root(self, split: str | None = None) -> Path:
        """The folder holding the scenes ``{scene_id:06d}/`` of a split."""

    @abstractmethod
    def _default_scene_name(self, scene_id: int, split: str | None) -> str:
        """The name of a scene the index does not name."""

    @abstractmethod
    def targets_split(self) -> str | None:
        """The split folder the dataset's one targets file belongs to (None where each split has its own)."""

    @abstractmethod
    def targets_path(self, split: str | None = None) -> Path:
        """The test targets file of a split."""

    @abstractmethod
    def _frames_of(self, split: str | None, part: str) -> list[tuple[int, int]]:
        """(scene_id, im_id) of a checked split's part (``part`` in :data:`PARTS`)."""

    @abstractmethod
    def _cache_key(self, split: str | None) -> str:
        """The folder of a split's rendered restored depth under the cache."""

    # ------------------------------------------------------------------ decisions callers ask of the layout
    @abstractmethod
    def check_train_split(self, split: str | None) -> str:
        """The split a training or a prediction names, checked (a one-line error naming --split)."""

    def check_part_request(self, split: str | None, part: str) -> None:
        """Refuse a (split, part) the layout's protocols do not have, naming the valid ones (by
        default any split and part: :meth:`frames` checks them)."""

    @abstractmethod
    def part_frames(self, split: str | None, part: str, purpose: str) -> list[tuple[int, int]]:
        """(scene_id, im_id) of ``split``/``part``; a one-line TdofError naming the split, the part and
        the dataset root when the part is empty (``purpose``: 'train on', 'predict', ...)."""

    @abstractmethod
    def empty_part_text(self, split: str, part: str) -> str:
        """What is empty, and why, when ``part`` of ``split`` has no images (follows 'nothing to pack: ')."""

    def no_targets_reason(self, split: str) -> str:
        """Why a split has no test targets, for the scorer's refusal: ': <reason>', or '' (by default)."""
        return ""

    @abstractmethod
    def scoring_targets_path(self, split: str) -> Path:
        """The targets file a score with ``--split split`` is made against, checked."""

    @abstractmethod
    def stats_folders(self) -> list[str | None]:
        """The folders the dataset's stats count apart (None: the one scenes folder)."""

    @abstractmethod
    def split_counts(self) -> dict[str, int]:
        """Counts the stats list beside the split folders' images: parts' images and targets."""

    # ------------------------------------------------------------------ loading
    def _load(self, names: str | Path | None) -> None:
        """camera.json, the models folder's presence and the objects' names (``names``, else
        ROOT/object_names.json, else the index's "objects")."""
        r = self.root
        if (r / "camera.json").is_file():
            cam = read_json(r / "camera.json")
            self.camera = cam if isinstance(cam, dict) else None
        if not (self.models_dir / MODELS_INFO).is_file():
            raise TdofError(f"the dataset has no models/{MODELS_INFO} (a BOP models folder)", r)
        given = names if names is not None else (r / NAMES_FILE if (r / NAMES_FILE).is_file() else None)
        raw_names = read_json(given) if given is not None else self.info.get("objects")
        if raw_names is not None:
            where = Path(given) if given is not None else r / self.info_file
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
        """models_eval/ when the dataset has one; a models_eval/ without its own models_info.json is
        refused (its models are not models/'s: their diameters differ; the BOP toolkit needs it too)."""
        d = self.root / "models_eval"
        if not d.is_dir():
            return None
        if not (d / MODELS_INFO).is_file():
            raise TdofError(f"not found: a models_eval/ folder needs its own {MODELS_INFO} (its objects' diameters "
                            "and symmetries; models/'s are not used for it): add it, or remove models_eval/",
                            d / MODELS_INFO)
        return d

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
        """The object's name: a names file or the index's "objects", else ``obj_000005``."""
        obj_id = int(obj_id)
        return self.object_names.get(obj_id, f"obj_{obj_id:06d}")

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
        for o in ids:
            if o not in self._keypoints:
                V, F = read_model_mesh(model_path(self.models_dir, o))
                self._keypoints[o] = surface_keypoints(V, F)
        return {o: self._keypoints[o] for o in ids}

    # ------------------------------------------------------------------ scenes
    def _listed_scene_ids(self) -> set[int]:
        """Scene ids the index lists beside those on disk (none unless a layout has an index of scenes)."""
        return set()

    def scene_ids(self, split: str | None = None) -> list[int]:
        """The scene ids of a split's scenes folder (and those the layout's index lists)."""
        base = self._scenes_root(split)
        on_disk = {int(p.name) for p in base.iterdir() if is_scene(p)} if base.is_dir() else set()
        return sorted(on_disk | self._listed_scene_ids())

    def scene_dir(self, scene_id: int, split: str | None = None) -> Path:
        return self._scenes_root(split) / f"{int(scene_id):06d}"

    def scene_name(self, scene_id: int, split: str | None = None) -> str:
        """The index's name of the scene ('multi/08'), else the layout's default."""
        names = self.info.get("scenes") or {}
        if str(int(scene_id)) in names:
            return str(names[str(int(scene_id))])
        return self._default_scene_name(scene_id, split)

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

    def read_targets(self, split: str | None = None) -> list[dict]:
        path = self.targets_path(split)
        data = read_json(path)
        if not isinstance(data, list):
            raise TdofError(f"must hold a JSON list of targets, got {type(data).__name__}", path)
        return data

    def frames(self, split: str | None = None, part: str = "train") -> list[tuple[int, int]]:
        """(scene_id, im_id) of a split's part, in order (see the layouts for which)."""
        if part not in PARTS:
            raise TdofError(f"part must be one of {', '.join(PARTS)}, got '{part}'")
        return self._frames_of(self.check_split(split), part)

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
    def cached_restored_path(self, scene_id: int, im_id: int, split: str | None = None) -> Path:
        return (self.cache_dir / "depth_restored" / self._cache_key(split) / f"{int(scene_id):06d}"
                / f"{int(im_id):06d}.png")

    def _cache_write_path(self, path: Path) -> Path:
        """``path`` in the cache, checked by :func:`safe_inside` when the cache lies in the dataset."""
        return safe_inside(self.root, path) if self._cache_inside else path

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
        from tdof20.geometry.raycast import ModelRaycaster  # imports open3d at top level

        todo = self.missing_restored(frames, split)
        if not todo:
            return 0
        base = self.cached_restored_path(*todo[0], split).parents[2]
        self._cache_write_path(base)
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
                    rp = self.rgb_path(sid, im, split)
                    h, w = png_header(rp) if rp.suffix == ".png" else read_colour(rp).shape[:2]
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
                write_png(self._cache_write_path(self.cached_restored_path(sid, im, split)), rc.camera.mm_to_depth(out))
                bar.advance(task)
        write_json(self._cache_write_path(base.parent / "info.json"), {"what": "restored depth rendered from the models and poses "
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


def _check_writable(folder: Path, root: Path) -> None:
    """Refuse, before rendering, a cache folder that cannot be written (a read-only ROOT)."""
    for up in [folder, *folder.parents]:
        if up.exists():
            if not up.is_dir() or not os.access(up, os.W_OK | os.X_OK):
                raise TdofError(f"cannot write the rendered restored depth under {folder} (not writable): give a "
                                "cache folder of your own (--cache-dir)", root)
            return


__all__ = ["CACHE_DIR", "DEPTH_DIRS", "DEPTH_MODES", "DatasetReader", "KEYPOINTS_FILE", "NAMES_FILE", "PARTS",
           "TARGET_MIN_VISIB", "composite_model_depth", "is_scene"]
