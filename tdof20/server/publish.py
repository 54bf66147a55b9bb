"""``tdof20 dataset publish ROOT --out PUBLIC``: the release a researcher downloads.

PUBLIC is ROOT (tdof20's layout) less every label of a test image: for each image in the test
part of a protocol (splits/{split}_test.json, every protocol by default) its entries in
scene_gt.json and scene_gt_info.json, its masks (mask/, mask_visib/), its restored depth and any
other per-image file of a folder that is not a sensor's (:data:`SENSOR_FOLDERS`). Its colour and
sensor depth images, its camera and the test targets (which objects to find, how many) stay.
ROOT/.cache (restored depth, validation targets) is not copied. An image that is in one
protocol's test part and another's train part (TDoF20's simple test images are hard train images)
loses its labels too, and the train lists of PUBLIC drop it; ``publish.json`` says how many.
The server keeps ROOT and scores against it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.layouts.tdof20 import Tdof20Reader
from tdof20.errors import TdofError
from tdof20.formats.io import read_json, write_json

SENSOR_FOLDERS = ("rgb", "gray", "depth", "depth_stabilized")  # per-image folders a test image keeps
PUBLIC_SCENE_FILES = ("scene_camera.json",)  # scene files kept whole
LABEL_FILES = ("scene_gt.json", "scene_gt_info.json")  # scene files filtered by image id
PUBLISH_INFO = "publish.json"


def hidden_frames(root: str | Path, splits: list[str] | None = None) -> dict[int, set[int]]:
    """{scene_id: {im_id, ...}} of the images in the test part of ``splits`` (default: every protocol)."""
    ds = open_dataset(root)
    if not isinstance(ds, Tdof20Reader):
        raise TdofError("dataset publish reads tdof20's layout (dataset_info.json); this is a "
                        f"{ds.layout} dataset", root)
    names = ds.splits() if splits is None else [ds.check_split(s) for s in splits]
    out: dict[int, set[int]] = {}
    for split in names:
        if (ds.root / "splits" / f"{split}_test.json").is_file():
            for s, i in ds.frames(split, "test"):
                out.setdefault(int(s), set()).add(int(i))
    return out


def _image_id(name: str) -> int | None:
    """The image id of a per-image file ('000003.png', '000003_000001.png'), else None."""
    head = name.split(".", 1)[0].split("_", 1)[0]
    return int(head) if head.isdigit() else None


def _copy_scene(src: Path, dst: Path, hidden: set[int]) -> int:
    """Copy one scene folder without the labels of the images in ``hidden``; returns files dropped."""
    dropped = 0
    dst.mkdir(parents=True)
    for p in sorted(src.iterdir()):
        if p.is_dir():
            keep_all = p.name in SENSOR_FOLDERS
            (dst / p.name).mkdir()
            for f in sorted(p.iterdir()):
                if f.is_file() and (keep_all or _image_id(f.name) not in hidden):
                    shutil.copy2(f, dst / p.name / f.name)
                else:
                    dropped += 1
        elif p.name in PUBLIC_SCENE_FILES:
            shutil.copy2(p, dst / p.name)
        elif p.name in LABEL_FILES:
            data = read_json(p)
            if not isinstance(data, dict):
                raise TdofError("must hold a JSON object keyed by image id", p)
            write_json(dst / p.name, {k: v for k, v in data.items() if not (str(k).isdigit() and int(k) in hidden)})
        else:
            dropped += 1  # an unknown scene file may hold labels: not published
    return dropped


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
    for p in sorted(root.iterdir()):
        if p.name.startswith("."):
            continue  # .cache: restored depth and validation targets
        if p.name == "scenes":
            for sd in sorted(p.iterdir()):
                if sd.is_dir() and sd.name.isdigit():
                    dropped += _copy_scene(sd, tmp / "scenes" / sd.name, hidden.get(int(sd.name), set()))
        elif p.name == "splits":
            (tmp / "splits").mkdir()
            for f in sorted(p.glob("*.json")):
                lists = read_json(f)
                if f.stem.endswith("_train") and isinstance(lists, dict):
                    kept = {s: [i for i in ims if int(i) not in hidden.get(int(s), set())] for s, ims in lists.items()}
                    trimmed[f.stem] = sum(len(v) for v in lists.values()) - sum(len(v) for v in kept.values())
                    write_json(tmp / "splits" / f.name, kept)
                else:
                    shutil.copy2(f, tmp / "splits" / f.name)
        elif p.is_dir():
            shutil.copytree(p, tmp / p.name)
        else:
            shutil.copy2(p, tmp / p.name)
    info = {"source": root.name, "hidden_test_images": sum(len(v) for v in hidden.values()),
            "label_files_dropped": dropped, "train_images_dropped": {k: v for k, v in trimmed.items() if v},
            "note": "test labels (poses, masks, gt_info, restored depth) are kept by the benchmark server"}
    write_json(tmp / PUBLISH_INFO, info)
    tmp.rename(out)
    return info


__all__ = ["LABEL_FILES", "PUBLISH_INFO", "SENSOR_FOLDERS", "hidden_frames", "publish"]
