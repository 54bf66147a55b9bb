"""A synthetic dataset for the server's benchmarks and screenshots (no tests here).

``make(root, n_images)`` writes benchmarks/score_speed.py's synthetic TDoF20-hard workload (20
catalog objects with their symmetries, the 6 hard test scenes multi/02, 08, 09, 10, 11, 15 sharing
``n_images`` 640x480 images with 3-5 objects each and a ray-cast depth image per image, the test
targets; 9,139 images is TDoF20-hard's size) and the protocol files the server reads
(splits/hard_test.json, an empty hard train part). ``results(root, ...)`` writes a method's results
CSV: every target's ground truth perturbed by a rotation and a translation drawn at the given
scales, some targets left without an estimate."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from score_speed import SCENES, make_workload  # noqa: E402

from tdof20.dataset.results import format_results_csv  # noqa: E402
from tdof20.formats.io import read_json, write_json  # noqa: E402


def make(root: Path, n_images: int, seed: int = 0) -> dict:
    """Write the dataset at ``root`` (reused when its targets are there); returns its counts."""
    root = Path(root)
    if (root / "test_targets_hard.json").is_file() and (root / "splits" / "hard_test.json").is_file():
        return {"targets": len(read_json(root / "test_targets_hard.json")), "images": n_images, "reused": True}
    info = make_workload(root, n_images, seed)
    per_scene = np.array_split(np.arange(n_images), len(SCENES))
    write_json(root / "splits" / "hard_test.json", {str(s): list(range(len(ims))) for s, ims in zip(SCENES, per_scene)})
    write_json(root / "splits" / "hard_train.json", {})
    return info


def results(root: Path, rot_deg: float, trans_mm: float, missing: float = 0.03, seed: int = 0,
            time_s: float = 0.03) -> bytes:
    """A results CSV for every target of ``root``'s hard test part: rotation errors of about
    ``rot_deg`` degrees and translation errors of about ``trans_mm`` mm (half-normal), a fraction
    ``missing`` of targets left out."""
    rng = np.random.default_rng(seed)
    rows = []
    for sid in SCENES:
        gt = read_json(root / "scenes" / f"{sid:06d}" / "scene_gt.json")
        for im, insts in gt.items():
            for g in insts:
                if rng.random() < missing:
                    continue
                R = np.array(g["cam_R_m2c"]).reshape(3, 3)
                t = np.array(g["cam_t_m2c"])
                axis = rng.normal(size=3)
                dR = Rotation.from_rotvec(np.deg2rad(abs(rng.normal(0, rot_deg))) * axis / np.linalg.norm(axis))
                dt = rng.normal(0, trans_mm / np.sqrt(3), 3)
                rows.append((sid, int(im), g["obj_id"], float(rng.uniform(0.5, 1)), dR.as_matrix() @ R, t + dt,
                             time_s))
    return format_results_csv(rows).encode()


__all__ = ["make", "results"]
