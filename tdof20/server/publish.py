"""``tdof20 dataset publish ROOT --out PUBLIC``: the release a researcher downloads.

PUBLIC is ROOT (tdof20's layout) less everything from which a test pose can be computed with the
train labels. For each image in the test part of a protocol (splits/{split}_test.json, every
protocol by default):

- its entries in the label files (:data:`LABEL_FILES`: scene_gt.json, scene_gt_info.json,
  scene_gt_uncertainty.json), its masks (mask/, mask_visib/), its restored or opaque-twin depth
  and any other per-image file of a folder that is not a sensor's (:data:`SENSOR_FOLDERS`);
- its world-to-camera extrinsics: its scene_camera.json entry keeps only :data:`CAMERA_FIELDS`
  (cam_K, depth_scale). With ``cam_R_w2c``/``cam_t_w2c`` of a test image and of a labelled image
  of the same static scene, T_w2c(test) T_w2c(train)^-1 T_m2c(train) is the test pose exactly.

Scene files other than the scene and label files (scene_info.json: the rig's registration,
turntable step, source session) and root entries other than :data:`ROOT_ENTRIES` (shards, caches,
anything unknown) are not published; ``publish.json`` lists them. Files are copied without their
times (a copy's mtime is the publish time), colour and depth images without their metadata
chunks (PNG text and time chunks, JPEG EXIF/APPn segments). An image that is in one protocol's
test part and in another's train part (TDoF20's simple test images are hard train images) loses
its labels too, and the train lists of PUBLIC drop it. The server keeps ROOT and scores against it.

``publish.json`` writes the rule down (what was dropped and why, what was kept and why it gives
no test pose) and says per protocol whether its test labels are still derivable from public
images: where a test image shares a static scene with labelled public images (TDoF20-simple:
each turntable arc's objects turn with the table, so a train image of the same scene, or a train
pose turned by the steps between them, gives every test pose) nothing a release leaves out can
hide them; that is said, not hidden (docs/server.md).
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.layouts.tdof20 import Tdof20Reader
from tdof20.errors import TdofError
from tdof20.formats.io import atomic_write_bytes, read_json, write_json

SENSOR_FOLDERS = ("rgb", "gray", "depth", "depth_stabilized")  # per-image folders a test image keeps
PUBLIC_SCENE_FILES = ("scene_camera.json",)  # scene files published (test images' entries trimmed)
LABEL_FILES = ("scene_gt.json", "scene_gt_info.json", "scene_gt_uncertainty.json")  # filtered by image id
CAMERA_FIELDS = ("cam_K", "depth_scale")  # what a test image's scene_camera.json entry keeps
ROOT_ENTRIES = ("dataset_info.json", "camera.json", "models", "models_eval", "splits", "scenes")
PUBLISH_INFO = "publish.json"
DERIVABLE = "test labels derivable from public images"

#: the rule publish.json writes: each published field or file, and why it gives no test pose
RULE = {
    "dropped for test images": {
        "scene_camera.json cam_R_w2c, cam_t_w2c (and every field but cam_K, depth_scale)":
            "world-to-camera extrinsics: T_w2c(test) T_w2c(train)^-1 T_m2c(train) is the test pose where a "
            "labelled image shares the static scene, and one test pose found gives all of its scene's others",
        "scene_gt.json, scene_gt_info.json, scene_gt_uncertainty.json entries": "the labels, their boxes, "
            "visible fractions and error bounds",
        "mask/, mask_visib/, depth_restored/, depth_opaque/ and any non-sensor per-image file":
            "drawn from the poses (masks, models rendered into depth) or the opaque twin's depth (model fitting)",
        "train list entries of an image that is another protocol's test image": "its labels are hidden",
    },
    "dropped for every image": {
        "scene_info.json": "the rig's registration and turntable step of the scene: not needed to use the images",
        "file times, PNG text/time chunks, JPEG APPn segments": "when and how a file was made, not its pixels",
        "root entries other than dataset_info.json, camera.json, models/, models_eval/, splits/, scenes/, "
        "test_targets_*.json (e.g. .cache/, shards)": "restored depth, validation caches and packed labels",
    },
    "kept for test images, and why no test pose follows from it": {
        "cam_K, depth_scale": "the intrinsics a method needs; identical for every image of the rig",
        "rgb/, gray/, depth/, depth_stabilized/": "the sensor's images (depth_stabilized: the TDoF20 "
            "release's own hole-filled sensor depth, released for every image): the input of the task",
        "test_targets_{split}.json": "which objects to find and how many (BOP targets: each is at least "
            "10 % visible): one bit per object per image, not a pose",
        "im_id, splits/, dataset_info.json layout (n_arms, steps)": "im_id = arm * steps + step: which arm "
            "position and turntable step an image is. Within a scene with labelled public images that alone "
            "gives the test poses (a train pose turned by the steps between them); elsewhere it gives the "
            "camera motion between a test scene's images but no object's place in it",
        "models/, models_info.json, camera.json": "the objects and the camera, the same in every scene",
        "train images' extrinsics and labels": "of their own scenes; a test scene's objects stand elsewhere",
    },
}


def hidden_frames(root: str | Path, splits: list[str] | None = None) -> dict[int, set[int]]:
    """{scene_id: {im_id, ...}} of the images in the test part of ``splits`` (default: every protocol)."""
    ds = _reader(root)
    names = ds.splits() if splits is None else [ds.check_split(s) for s in splits]
    out: dict[int, set[int]] = {}
    for split in names:
        if (ds.root / "splits" / f"{split}_test.json").is_file():
            for s, i in ds.frames(split, "test"):
                out.setdefault(int(s), set()).add(int(i))
    return out


def _reader(root: str | Path) -> Tdof20Reader:
    ds = open_dataset(root)
    if not isinstance(ds, Tdof20Reader):
        raise TdofError("dataset publish reads tdof20's layout (dataset_info.json); this is a "
                        f"{ds.layout} dataset", root)
    return ds


def _image_id(name: str) -> int | None:
    """The image id of a per-image file ('000003.png', '000003_000001.png'), else None."""
    head = name.split(".", 1)[0].split("_", 1)[0]
    return int(head) if head.isdigit() else None


PNG_DROPPED = (b"tEXt", b"zTXt", b"iTXt", b"tIME", b"eXIf")


def _png_without_metadata(data: bytes) -> bytes:
    """A PNG's bytes without its text, time and EXIF chunks (the pixels untouched)."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        return data
    out, i = [data[:8]], 8
    while i + 8 <= len(data):
        (length,), tag = struct.unpack(">I", data[i:i + 4]), data[i + 4:i + 8]
        end = i + 12 + length
        if end > len(data):
            return data  # not a whole PNG: copied as it is (the readers say what is wrong with it)
        if tag not in PNG_DROPPED:
            out.append(data[i:end])
        i = end
        if tag == b"IEND":
            break
    return b"".join(out)


def _jpeg_without_metadata(data: bytes) -> bytes:
    """A JPEG's bytes without its APP1-APP15 and comment segments (EXIF, XMP: camera, times)."""
    if data[:2] != b"\xff\xd8":
        return data
    out, i = [data[:2]], 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xDA:  # start of scan: the rest is the image
            out.append(data[i:])
            return b"".join(out)
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if not (0xE1 <= marker <= 0xEF or marker == 0xFE):
            out.append(data[i:i + 2 + length])
        i += 2 + length
    return data


def _copy_image(src: Path, dst: Path) -> None:
    data = src.read_bytes()
    suffix = src.suffix.lower()
    if suffix == ".png":
        data = _png_without_metadata(data)
    elif suffix in (".jpg", ".jpeg"):
        data = _jpeg_without_metadata(data)
    atomic_write_bytes(dst, data)


def _copy_scene(src: Path, dst: Path, hidden: set[int], left_out: set[str]) -> int:
    """Copy one scene folder without the labels of the images in ``hidden``; returns files dropped."""
    dropped = 0
    dst.mkdir(parents=True)
    for p in sorted(src.iterdir()):
        if p.is_dir():
            keep_all = p.name in SENSOR_FOLDERS
            (dst / p.name).mkdir()
            for f in sorted(p.iterdir()):
                if f.is_file() and (keep_all or _image_id(f.name) not in hidden):
                    _copy_image(f, dst / p.name / f.name)
                else:
                    dropped += 1
        elif p.name in PUBLIC_SCENE_FILES:
            data = _by_image(p)
            write_json(dst / p.name, {k: ({f: v for f, v in e.items() if f in CAMERA_FIELDS}
                                          if _hidden(k, hidden) and isinstance(e, dict) else e)
                                      for k, e in data.items()})
        elif p.name in LABEL_FILES:
            data = _by_image(p)
            write_json(dst / p.name, {k: v for k, v in data.items() if not _hidden(k, hidden)})
        else:
            dropped += 1  # an unknown scene file may hold labels: not published
            left_out.add(p.name)
    return dropped


def _by_image(p: Path) -> dict:
    data = read_json(p)
    if not isinstance(data, dict):
        raise TdofError("must hold a JSON object keyed by image id", p)
    return data


def _hidden(k: str, hidden: set[int]) -> bool:
    """Whether the key ``k`` names a hidden image; a key that is no image id is treated as hidden."""
    return not str(k).isdigit() or int(k) in hidden


def derivable(root: str | Path, hidden: dict[int, set[int]]) -> dict[str, dict]:
    """Per protocol of ``root``: {DERIVABLE: bool, "why": ...} for a release that hides ``hidden``."""
    ds = _reader(root)
    out = {}
    for split in ds.splits():
        if not (ds.root / "splits" / f"{split}_test.json").is_file():
            continue
        test: dict[int, set[int]] = {}
        for s, i in ds.frames(split, "test"):
            test.setdefault(int(s), set()).add(int(i))
        if any(not ims <= hidden.get(s, set()) for s, ims in test.items()):
            out[split] = {DERIVABLE: True, "why": "this release was published without hiding this protocol's "
                                                  "test labels (publish --split)"}
            continue
        shared = sorted(s for s in test if set(ds.image_ids(s)) - hidden.get(s, set()))
        if shared:
            names = ", ".join(ds.scene_name(s) for s in shared[:6]) + (" ..." if len(shared) > 6 else "")
            out[split] = {DERIVABLE: True, "scenes": shared, "why": (
                f"its test images share a static scene with labelled public images ({names}): the objects stay "
                "put on the turntable (they turn with it), so registering a test image to a labelled image of "
                "its scene from the pixels, turning a train pose of the same arm position by the turntable "
                "steps between the two images (im_id = arm * steps + step), or chaining a train label with "
                "another scene's extrinsics at the same arm position and step (the rig repeats them) gives its "
                "poses; nothing a release leaves out can hide them. Its test score measures a method, not a "
                "secret")}
        else:
            out[split] = {DERIVABLE: False, "why": (
                "no test image shares a scene with a labelled public image, and no test image's extrinsics are "
                "published: a test pose cannot be computed from public files and train labels. The rig repeats "
                "its arm positions and turntable steps, so the camera motion between a test scene's images can "
                "be estimated (and is in the pixels): one test pose found gives its scene's others")}
    return out


def publish(root: str | Path, out: str | Path, splits: list[str] | None = None) -> dict:
    """Write the public release of ``root`` to ``out`` (a new folder); returns what publish.json says."""
    root, out = Path(root), Path(out)
    hidden = hidden_frames(root, splits)
    if out.exists():
        raise TdofError("already exists: publish writes a new folder", out)
    if out.resolve().is_relative_to(root.resolve()):
        raise TdofError(f"--out must lie outside the dataset {root}", out)
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    dropped = 0
    trimmed: dict[str, int] = {}
    left_out: set[str] = set()
    for p in sorted(root.iterdir()):
        if p.name == "scenes":
            for sd in sorted(p.iterdir()):
                if sd.is_dir() and sd.name.isdigit():
                    dropped += _copy_scene(sd, tmp / "scenes" / sd.name, hidden.get(int(sd.name), set()), left_out)
        elif p.name == "splits":
            (tmp / "splits").mkdir()
            for f in sorted(p.glob("*.json")):
                lists = read_json(f)
                if f.stem.endswith("_train") and isinstance(lists, dict):
                    kept = {s: [i for i in ims if int(i) not in hidden.get(int(s), set())] for s, ims in lists.items()}
                    trimmed[f.stem] = sum(len(v) for v in lists.values()) - sum(len(v) for v in kept.values())
                    write_json(tmp / "splits" / f.name, kept)
                else:
                    shutil.copyfile(f, tmp / "splits" / f.name)
        elif p.name in ROOT_ENTRIES and p.is_dir():
            shutil.copytree(p, tmp / p.name, copy_function=shutil.copyfile)
        elif p.is_file() and (p.name in ROOT_ENTRIES or (p.name.startswith("test_targets_")
                                                         and p.suffix == ".json")):
            shutil.copyfile(p, tmp / p.name)
        else:
            left_out.add(p.name + ("/" if p.is_dir() else ""))  # .cache, shards, anything unknown
    info = {"source": root.name, "hidden_test_images": sum(len(v) for v in hidden.values()),
            "label_files_dropped": dropped, "train_images_dropped": {k: v for k, v in trimmed.items() if v},
            "not_published": sorted(left_out),
            "note": "test labels (poses, extrinsics, masks, gt_info, restored depth) are kept by the benchmark server",
            "rule": RULE, "splits": derivable(root, hidden)}
    write_json(tmp / PUBLISH_INFO, info)
    tmp.rename(out)
    return info


__all__ = ["CAMERA_FIELDS", "DERIVABLE", "LABEL_FILES", "PUBLISH_INFO", "ROOT_ENTRIES", "RULE", "SENSOR_FOLDERS",
           "derivable", "hidden_frames", "publish"]
