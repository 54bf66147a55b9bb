"""The released TDoF20 dataset (MightyCrane/HFF6DoF's README), read and checked (torch-free).

    rel = read_release(SRC)                    # config, lists, scene folders; every listed frame present
    geo = read_geometry(rel)                   # models, diameters, farthest keypoints in mm (units found)
    pose = read_pose(rel.frame_path("multi/02", 5, "pose"), len(rel.classes))   # raw units

The layout (docs/tdof20_release.md states every assumption the README leaves open)::

    SRC/dataset_config/classes.txt         one class name a line; class id = line number (1-based)
    SRC/dataset_config/intrinsics.json     {fx, fy, cx, cy, [width, height], depth_scale} or {"K": 3x3, ...}
    SRC/dataset_config/{train,test,hard_train,hard_test}_data_list.txt, visual_data_list.txt or visual_data.txt
    SRC/models/<class>.ply  SRC/diameters/<class>_diameter.txt  SRC/farthest/<class>_farthest.txt (8x3)
    SRC/single_data/<class>/ and SRC/multi_data/NN/ with rgb/<stem>.jpg, broken_depth/<stem>.png,
        depth/<stem>.png, mask/<stem>.png (class id per pixel), labels/<stem>.txt (not read), pose/<stem>.pkl

Scene names: ``single/<class>`` and ``multi/NN``. Every problem is one :class:`TdofError` line naming
the file (and the list line) and what differs. Units are detected, never guessed: see
:func:`model_units`, :func:`pose_units`, :func:`~tdof20.formats.tdof20_files.depth_scale_mm`. The
readers of single files (classes, intrinsics, poses, masks) are :mod:`tdof20.formats.tdof20_files`;
their names stay importable from here.
"""

from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop_models import read_model_mesh
from tdof20.formats.io import read_text
from tdof20.formats.tdof20_files import (FramePose, Intrinsics, depth_scale_mm, image_size, load_pickle,
                                         read_class_mask, read_classes, read_intrinsics, read_numbers, read_pose)

CONFIG = "dataset_config"
LISTS = ("train", "test", "hard_train", "hard_test", "visual")
REQUIRED_LISTS = ("train", "test", "hard_train", "hard_test")
LIST_FILES = {"train": ("train_data_list.txt",), "test": ("test_data_list.txt",),
              "hard_train": ("hard_train_data_list.txt",), "hard_test": ("hard_test_data_list.txt",),
              "visual": ("visual_data_list.txt", "visual_data.txt")}
#: the per-frame files every listed frame must have: folder -> accepted extensions
FRAME_FILES = {"rgb": (".jpg", ".jpeg"), "broken_depth": (".png",), "depth": (".png",), "mask": (".png",),
               "pose": (".pkl",)}
OPTIONAL_DIRS = ("labels",)
_EXTS = (".jpg", ".jpeg", ".png", ".pkl", ".txt")
# plausible ranges that tell metres from millimetres (a cup is 1-100 cm across, 10-300 cm from the camera)
DIAMETER_MM = (10.0, 1000.0)
DIAMETER_M = (0.01, 1.0)
DISTANCE_MM = (100.0, 3000.0)
DISTANCE_M = (0.1, 3.0)
SCALE_TOL = 0.10  # the model's extent and the diameter file agree within 10 %


# ---------------------------------------------------------------------------------------------
# the release: config, lists, scene folders
# ---------------------------------------------------------------------------------------------
@dataclass
class ReleaseScene:
    """One scene folder: its name (single/<class> or multi/NN), folder, the stem of every image id,
    the per-folder file names, and the im_id rule."""

    name: str
    folder: Path
    stems: dict[int, str]
    files: dict[str, dict[str, str]]
    im_id_rule: str

    def im_id(self, stem: str) -> int | None:
        return self._by_stem.get(stem)

    def __post_init__(self) -> None:
        self._by_stem = {s: i for i, s in self.stems.items()}


@dataclass
class Release:
    root: Path
    classes: list[str]
    intrinsics: Intrinsics
    scenes: dict[str, ReleaseScene]
    lists: dict[str, list[tuple[str, int]]]
    list_files: dict[str, Path]
    list_forms: dict[str, list[str]]
    missing_scenes: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def class_id(self, name: str) -> int:
        return self.classes.index(name) + 1

    def scene_id(self, name: str) -> int:
        """single/<class> -> its class id; multi/NN -> 21 + NN (the project's numbering; with more than
        20 classes n_classes + 1 + NN, so that no multi id is a class id)."""
        kind, rest = name.split("/", 1)
        return self.class_id(rest) if kind == "single" else max(21, len(self.classes) + 1) + int(rest)

    def frame_path(self, scene: str, im_id: int, sub: str) -> Path:
        sc = self.scenes[scene]
        return sc.folder / sub / sc.files[sub][sc.stems[im_id]]

    def frames(self, scenes=None) -> dict[str, list[int]]:
        """{scene: sorted im_ids listed in any list} for the scenes read (or those given)."""
        out: dict[str, set] = {}
        for lst in self.lists.values():
            for s, i in lst:
                if s in self.scenes and (scenes is None or s in scenes):
                    out.setdefault(s, set()).add(i)
        return {s: sorted(v) for s, v in sorted(out.items(), key=lambda x: self.scene_id(x[0]))}


def _listing(folder: Path) -> dict[str, str]:
    """{stem: file name} of a folder's files (one scandir)."""
    try:
        with os.scandir(folder) as it:
            return {os.path.splitext(e.name)[0]: e.name for e in it if e.is_file() and not e.name.startswith(".")}
    except FileNotFoundError:
        return {}
    except NotADirectoryError:
        raise TdofError("is a file, not a folder", folder) from None


#: the largest list file read (the release's are under 2 MB)
MAX_LIST_BYTES = 256 * 2**20
#: the largest frame number used as an im_id (BOP's ids are int32; larger stems number by position)
MAX_ID = 2**31 - 1
#: the largest multi_data sequence number (its scene id is n_classes + 1 + NN)
MAX_SEQ = 9999


def _seq_number(tok: str) -> int | None:
    """A multi_data sequence number: ASCII digits, at most MAX_SEQ; else None."""
    return int(tok) if re.fullmatch(r"[0-9]{1,6}", tok) and int(tok) <= MAX_SEQ else None


def _im_ids(stems: list[str]) -> tuple[dict[int, str], str]:
    nums = {}
    for s in stems:
        m = re.search(r"([0-9]+)$", s)  # ASCII digits only (int() would also take "²" or "٣")
        nums[s] = int(m.group(1)) if m and int(m.group(1)) <= MAX_ID else None
    if stems and all(v is not None for v in nums.values()) and len(set(nums.values())) == len(stems):
        return {nums[s]: s for s in stems}, "im_id = the number at the end of the frame stem (000123 -> 123)"
    return {i: s for i, s in enumerate(sorted(stems))}, "im_id = the frame's position in sorted stem order"


def _scene_folders(root: Path, classes: list[str]) -> dict[str, Path]:
    out = {}
    sd = root / "single_data"
    if sd.is_dir():
        for p in sorted(sd.iterdir()):
            if p.is_dir() and not p.name.startswith("."):
                if p.name not in classes:
                    raise TdofError(f"single_data/{p.name} is not a class of classes.txt", p)
                out[f"single/{p.name}"] = p
    md = root / "multi_data"
    if md.is_dir():
        for p in sorted(md.iterdir()):
            if p.is_dir() and not p.name.startswith("."):
                if _seq_number(p.name) is None:
                    raise TdofError(f"a multi_data sequence folder must be named by its number (00-19, at most "
                                    f"{MAX_SEQ}; ASCII digits), not {p.name!r}", p)
                name = f"multi/{int(p.name):02d}"
                if name in out:
                    raise TdofError(f"two folders are sequence {name}", p)
                out[name] = p
    return out


def _read_scene(name: str, folder: Path) -> ReleaseScene:
    files = {sub: _listing(folder / sub) for sub in (*FRAME_FILES, *OPTIONAL_DIRS)}
    if not files["rgb"]:
        raise TdofError("has no rgb/*.jpg frames", folder)
    stems, rule = _im_ids(sorted(files["rgb"]))
    return ReleaseScene(name, folder, stems, files, rule)


def _strip_ext(s: str) -> tuple[str, str]:
    base, ext = os.path.splitext(s)
    return (base, ext) if ext.lower() in _EXTS else (s, "")


def _parse_line(line: str, classes: list[str], folders: dict[str, Path],
                stem_index: dict[str, list[str]]) -> tuple[str | None, str, str]:
    """(scene name or None when not found, stem, the line's form) of one list line."""
    s = line.strip().replace("\\", "/")
    while s.startswith("./"):
        s = s[2:]
    parts = [p for p in s.split("/") if p]
    stem, ext = _strip_ext(parts[-1])
    for i, p in enumerate(parts[:-1]):
        if p in ("single_data", "multi_data") and i + 1 < len(parts) - 1:
            tok = parts[i + 1]
            mid = "/".join(parts[i + 2:-1])
            form = f"{p}/<{'class' if p == 'single_data' else 'NN'}>/{mid + '/' if mid else ''}<stem>{ext}"
            if p == "single_data":
                return (f"single/{tok}" if tok in classes else None), stem, form
            return (f"multi/{int(tok):02d}" if _seq_number(tok) is not None else None), stem, form
    if len(parts) >= 2:
        tok, mid = parts[-2], ""
        if tok in FRAME_FILES or tok in OPTIONAL_DIRS:
            mid = tok + "/"
            tok = parts[-3] if len(parts) >= 3 else ""
        if tok in classes:
            return f"single/{tok}", stem, f"<class>/{mid}<stem>{ext}"
        if _seq_number(tok) is not None:
            return f"multi/{int(tok):02d}", stem, f"<NN>/{mid}<stem>{ext}"
        return None, stem, f"<?>/{mid}<stem>{ext}"
    where = stem_index.get(stem, [])
    return (where[0] if len(where) == 1 else None), stem, f"<stem>{ext}"


def read_release(src: str | Path, scenes: list[str] | None = None) -> Release:
    """Read and check the release in ``src``: classes, intrinsics, the lists (every listed frame
    of the scenes read must have all of :data:`FRAME_FILES`), the scene folders. ``scenes``:
    read only these (names ``single/<class>``, ``multi/NN``); the others' frames are not checked."""
    root = Path(src)
    if not root.is_dir():
        raise TdofError("no such folder (the TDoF20 release: dataset_config/, models/, single_data/, ...)", root)
    cfg = root / CONFIG
    if not cfg.is_dir():
        raise TdofError("has no dataset_config/ folder: not the TDoF20 release layout", root)
    classes = read_classes(cfg / "classes.txt")
    intr = read_intrinsics(cfg / "intrinsics.json")
    folders = _scene_folders(root, classes)
    wanted = None
    if scenes is not None:
        wanted = []
        for s in scenes:
            s = str(s).strip()
            m = re.fullmatch(r"multi/([0-9]{1,2})", s)
            s = f"multi/{int(m.group(1)):02d}" if m else s
            if s not in folders:
                raise TdofError(f"scene {s!r} is not in the release (found: {', '.join(folders) or 'none'})", root)
            wanted.append(s)
    read = {n: _read_scene(n, p) for n, p in folders.items() if wanted is None or n in wanted}
    stem_index: dict[str, list[str]] = {}
    for n, sc in read.items():
        for st in sc.stems.values():
            stem_index.setdefault(st, []).append(n)

    lists, files, forms = {}, {}, {}
    missing_scenes: set[str] = set()
    for key in LISTS:
        path = next((cfg / f for f in LIST_FILES[key] if (cfg / f).exists()), None)
        if path is None:
            if key in REQUIRED_LISTS:
                raise TdofError(f"list file not found: the {key} split needs {LIST_FILES[key][0]}",
                                cfg / LIST_FILES[key][0])
            continue
        files[key] = path
        entries, seen, kinds = [], {}, Counter()
        for n, line in enumerate(read_text(path, "list file", max_size=MAX_LIST_BYTES).splitlines(), 1):
            if not line.strip() or line.strip().startswith("#"):
                continue
            scene, stem, form = _parse_line(line, classes, folders, stem_index)
            kinds[form] += 1
            if scene is None:
                raise TdofError(f"line {n}: {line.strip()!r} names no scene of the release (form {form}; "
                                "expected single_data/<class>/<stem>, <class>/<stem> or multi_data/NN/<stem>)", path)
            if scene not in folders:
                raise TdofError(f"line {n}: {line.strip()!r}: the release has no folder for scene {scene}", path)
            if scene not in read:
                missing_scenes.add(scene)
                if wanted is None:
                    raise TdofError(f"line {n}: scene {scene} was not read", path)
                continue
            sc = read[scene]
            im = sc.im_id(stem)
            if im is None:
                raise TdofError(f"line {n}: {line.strip()!r}: no rgb/{stem}.jpg in {sc.folder}", path)
            for sub, exts in FRAME_FILES.items():
                fname = sc.files[sub].get(stem)
                if fname is None or os.path.splitext(fname)[1].lower() not in exts:
                    why = f"found {fname}" if fname else "missing"
                    raise TdofError(f"line {n}: frame {stem} of {scene} has no {sub}/{stem}{exts[0]} ({why})", path)
            if (scene, im) in seen:
                raise TdofError(f"line {n}: frame {stem} of {scene} is listed twice (first at line {seen[(scene, im)]})",
                                path)
            seen[(scene, im)] = n
            entries.append((scene, im))
        lists[key] = entries
        forms[key] = [f"{f} ({c})" for f, c in kinds.most_common()]
    rel = Release(root, classes, intr, read, lists, files, forms,
                  missing_scenes=sorted(missing_scenes) if wanted is not None else [])
    for a, b in (("train", "test"), ("hard_train", "hard_test")):
        both = set(lists[a]) & set(lists[b])
        if both:
            s, i = sorted(both)[0]
            raise TdofError(f"frame {read[s].stems[i]} of {s} is in both {files[a].name} and {files[b].name} "
                            f"({len(both)} frames are): train and test must not overlap", files[b])
    if "visual" in lists and not set(lists["visual"]) <= set(lists["test"]):
        rel.notes.append(f"{files['visual'].name} lists {len(set(lists['visual']) - set(lists['test']))} frames "
                         "outside the test list (the README says it is sampled from it)")
    if "visual" not in lists:
        rel.notes.append("no visual list (visual_data_list.txt or visual_data.txt): splits/visual.json is empty")
    unlisted = sum(len(set(sc.stems) - {i for lst in lists.values() for s, i in lst if s == n})
                   for n, sc in read.items())
    if unlisted:
        rel.notes.append(f"{unlisted} frames on disk are in no list: not imported")
    return rel


# ---------------------------------------------------------------------------------------------
# geometry and units
# ---------------------------------------------------------------------------------------------
def hull_diameter(V: np.ndarray) -> float:
    """The largest distance between two vertices (on the convex hull)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    try:
        P = V[ConvexHull(V).vertices]
    except Exception:  # flat or degenerate: all vertices
        P = V
    if len(P) > 4000:
        P = P[np.random.default_rng(0).choice(len(P), 4000, replace=False)]
    return float(pdist(P).max()) if len(P) > 1 else 0.0


def _in(v: float, rng: tuple[float, float]) -> bool:
    return rng[0] <= v <= rng[1]


def model_units(mesh_extent: float, file_diameter: float, mesh_path: Path, diam_path: Path) -> tuple[float, float, str]:
    """(mm per model unit, mm per diameter-file unit, 'the model in m, the diameter in mm'-style text).
    The diameter file is read as m when it is 0.01-1, as mm when 10-1000 (else refused); the model is
    in the unit that makes its extent agree with the diameter within 10 % (else refused)."""
    if _in(file_diameter, DIAMETER_MM):
        f_file, u_file = 1.0, "mm"
    elif _in(file_diameter, DIAMETER_M):
        f_file, u_file = 1000.0, "m"
    else:
        raise TdofError(f"diameter {file_diameter:g} is neither {DIAMETER_M[0]:g}-{DIAMETER_M[1]:g} (m) nor "
                        f"{DIAMETER_MM[0]:g}-{DIAMETER_MM[1]:g} (mm): its unit is ambiguous", diam_path)
    d_mm = file_diameter * f_file
    for f_mesh, u_mesh in ((1.0, "mm"), (1000.0, "m")):
        if abs(mesh_extent * f_mesh / d_mm - 1.0) <= SCALE_TOL:
            return f_mesh, f_file, f"model in {u_mesh}, diameter in {u_file}"
    raise TdofError(f"the model's extent {mesh_extent:g} (largest vertex distance) matches the diameter "
                    f"{file_diameter:g} of {diam_path.name} neither in mm nor in m (within {SCALE_TOL:.0%}): "
                    "wrong model or wrong diameter", mesh_path)


def keypoint_units(kp: np.ndarray, V_mm: np.ndarray, diameter_mm: float, path: Path) -> float:
    """mm per unit of the farthest/ keypoints: the unit (1 or 1000) that puts them on the model
    (inside its bounding box grown by 10 % of its diameter) and spreads them over it (their
    largest distance at least 30 % of the diameter, as farthest points of its surface are)."""
    from scipy.spatial.distance import pdist

    lo, hi = V_mm.min(0) - 0.1 * diameter_mm, V_mm.max(0) + 0.1 * diameter_mm
    ok = [f for f in (1.0, 1000.0) if np.all((kp * f >= lo) & (kp * f <= hi))
          and pdist(kp * f).max() >= 0.3 * diameter_mm]
    if len(ok) != 1:
        raise TdofError("the keypoints do not lie on the model in mm or in m (outside its bounding box, or "
                        "bunched in a corner of it): wrong file or another model frame", path)
    return ok[0]


@dataclass
class ClassGeometry:
    """One class in mm: mesh, the released diameter, the mesh's own extent, 9 keypoints (centre + 8)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    diameter: float
    mesh_extent: float
    keypoints: np.ndarray
    units: str
    paths: dict[str, Path]


def _class_file(folder: Path, name: str, suffix: str, what: str) -> Path:
    p = folder / f"{name}{suffix}"
    if p.is_file():
        return p
    raise TdofError(f"{what} of class {name} not found (expected {p.name})", p)


def read_geometry(rel: Release, class_ids=None) -> dict[int, ClassGeometry]:
    """{class id: geometry in mm} for the classes (default: all of classes.txt); units detected per class."""
    out = {}
    ids = range(1, len(rel.classes) + 1) if class_ids is None else sorted(class_ids)
    for cid in ids:
        name = rel.classes[cid - 1]
        mp = _class_file(rel.root / "models", name, ".ply", "the model")
        dp = _class_file(rel.root / "diameters", name, "_diameter.txt", "the diameter file")
        fp = _class_file(rel.root / "farthest", name, "_farthest.txt", "the farthest-keypoint file")
        V, F = read_model_mesh(mp)
        d = read_numbers(dp, "diameter file")
        if d.size != 1:
            raise TdofError(f"must hold one number (the diameter), found {d.size}", dp)
        d = float(d.reshape(-1)[0])
        extent = hull_diameter(V)
        f_mesh, f_file, units = model_units(extent, d, mp, dp)
        V = V * f_mesh
        kp8 = read_numbers(fp, "keypoint file")
        if kp8.shape != (8, 3):
            raise TdofError(f"must hold 8 keypoints of 3 numbers (8x3), found {kp8.shape[0]}x{kp8.shape[1]}", fp)
        f_kp = keypoint_units(kp8, V, d * f_file, fp)
        centre = 0.5 * (V.min(0) + V.max(0))
        kp = np.vstack([centre, kp8 * f_kp])
        units += f", keypoints in {'mm' if f_kp == 1 else 'm'}"
        out[cid] = ClassGeometry(name, V, F, d * f_file, extent * f_mesh, kp, units,
                                 {"model": mp, "diameter": dp, "farthest": fp})
    return out


def pose_units(poses: dict[tuple[str, int], FramePose], paths: dict[tuple[str, int], Path]) -> tuple[float, str]:
    """(mm per pose unit, text) from the translations (and center_3ds): a camera 0.1-3 m from
    every object. Every instance must fall in the range of one unit, all frames in the same one."""
    votes: dict[str, tuple[str, int]] = {}
    counts: Counter = Counter()
    for key, p in poses.items():
        for what, vecs in (("translation", p.t), ("center_3ds", p.center_3ds)):
            if vecs is None:
                continue
            for i, v in enumerate(np.linalg.norm(vecs, axis=1)):
                u = "mm" if _in(v, DISTANCE_MM) else "m" if _in(v, DISTANCE_M) else None
                if u is None:
                    raise TdofError(f"instance {i}: the {what} is {v:g} from the camera: neither "
                                    f"{DISTANCE_M[0]:g}-{DISTANCE_M[1]:g} m nor {DISTANCE_MM[0]:g}-{DISTANCE_MM[1]:g} mm, "
                                    "so its unit is ambiguous", paths[key])
                counts[u] += 1
                votes.setdefault(u, key)
    if not counts:
        raise TdofError("no poses to read")
    if len(counts) > 1:
        minority = min(counts, key=counts.get)
        major = max(counts, key=counts.get)
        raise TdofError(f"its poses are in {minority} where {counts[major]} other instances are in {major}: "
                        "one unit for the whole release", paths[votes[minority]])
    u = next(iter(counts))
    return (1.0 if u == "mm" else 1000.0), f"poses in {u} ({counts[u]} translations and centres 0.1-3 m away)"


__all__ = ["Release", "ReleaseScene", "Intrinsics", "FramePose", "ClassGeometry", "read_release", "read_classes",
           "read_intrinsics", "read_pose", "read_class_mask", "read_geometry", "image_size", "load_pickle",
           "model_units", "keypoint_units", "pose_units", "depth_scale_mm", "hull_diameter",
           "FRAME_FILES", "LISTS", "LIST_FILES"]
