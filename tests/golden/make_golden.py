"""Writes the fixed inputs of tests/test_golden.py and scores them with the installed tdof20.

Run once before an architecture change (``python tests/golden/make_golden.py``): the JSON it writes
(tests/golden/score_bop_standard.json) is what tdof20 scored *before* the change; the test scores the
same inputs with the code of today and compares the JSON byte for byte.

The dataset is the documentation-only BOP fixture (tests/fixtures/bop_standard.py, no tdof20 code);
the results file is its test poses perturbed by a seeded generator, written here by hand in the
BOP results format (scene_id,im_id,obj_id,score,R,t,time).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from tests.fixtures.bop_standard import write_bop_dataset  # noqa: E402

DATASET_KW = dict(obj_ids=(1, 5, 30), splits=("test",), scenes_per_split=2, images_per_scene=6,
                  size=(96, 72), seed=7)


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.deg2rad(deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def write_results(truth: dict, path: Path, seed: int = 3) -> None:
    """The truth's test poses, each perturbed by a rotation of 0-25 deg and a shift of 0-12 mm;
    every fifth one left out (a missed target)."""
    rng = np.random.default_rng(seed)
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    k = 0
    for sid, scene in sorted(truth["splits"]["test"].items()):
        for im, image in sorted(scene["images"].items()):
            for g in image["poses"]:
                k += 1
                if k % 5 == 0:
                    continue
                R = rotation(rng.normal(size=3), rng.uniform(0, 25)) @ np.asarray(g["R"], float).reshape(3, 3)
                t = np.asarray(g["t_mm"], float).reshape(3) + rng.uniform(-12, 12, size=3)
                lines.append(f"{sid},{im},{g['obj_id']},{rng.uniform(0.2, 1):.4f},"
                             + " ".join(f"{v:.6f}" for v in R.reshape(-1)) + ","
                             + " ".join(f"{v:.4f}" for v in t) + ",0.0125")
    path.write_text("\n".join(lines) + "\n")


def make_inputs(root: Path) -> tuple[Path, Path]:
    truth = write_bop_dataset(root / "bop", **DATASET_KW)
    results = root / "results.csv"
    write_results(truth, results)
    return root / "bop", results


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        ds, res = make_inputs(Path(tmp))
        out = HERE / "score_bop_standard.json"
        subprocess.run([sys.executable, "-m", "tdof20", "benchmark", "score", str(res), "--dataset", str(ds),
                        "--split", "test", "--json", str(out)], check=True)
        print("wrote", out)
