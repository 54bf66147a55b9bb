"""The 2D projection threshold: 5 px for a 640-pixel-wide image, scaled with the image width
(5 * w / 640) by default, ``proj_px`` to set it; the threshold used is in the summary ("proj_px")
and printed beside the table.

The datasets are the documentation-only BOP fixture (tests/fixtures/bop_standard.py) at two widths;
each estimate is its ground truth shifted along the camera's x axis, so every model point moves
by fx * dx / Z pixels and the mean reprojection error is known in closed form from the model's
points (read here from models_eval/ with trimesh, not with tdof20).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from tdof20.errors import TdofError
from tdof20.scoring.scoring import score, score_command
from tests.fixtures.bop_standard import write_bop_dataset

ERRORS_PX = (0.3, 0.75, 1.4, 2.2, 3.5)  # mean reprojection errors given to the estimates, in turn


def _rows(truth: dict) -> tuple[list, np.ndarray]:
    """Estimates with known 2D projection errors: (rows, their errors in px)."""
    root, K = truth["root"], truth["K"]
    pts = {o: np.asarray(trimesh.load(root / "models_eval" / f"obj_{o:06d}.ply", process=False).vertices)
           for o in truth["obj_ids"]}
    targets = {(t["scene_id"], t["im_id"], t["obj_id"]) for t in truth["targets"]}
    rows, errs = [], []
    for sid, scene in sorted(truth["splits"]["test"].items()):
        for im, image in sorted(scene["images"].items()):
            for p in image["poses"]:
                if (sid, im, p["obj_id"]) not in targets:
                    continue
                R, t = np.asarray(p["R"], float).reshape(3, 3), np.asarray(p["t_mm"], float)
                Z = (pts[p["obj_id"]] @ R.T + t)[:, 2]
                e = ERRORS_PX[len(rows) % len(ERRORS_PX)]
                dx = e / (K[0, 0] * np.mean(1.0 / Z))  # each point moves fx * dx / Z pixels along u
                rows.append((sid, im, p["obj_id"], 1.0, R, t + [dx, 0.0, 0.0], -1.0))
                errs.append(e)
    return rows, np.asarray(errs)


@pytest.fixture(scope="module", params=[(64, 48), (256, 192)], ids=["w64", "w256"])
def dataset(request, tmp_path_factory):
    truth = write_bop_dataset(tmp_path_factory.mktemp("bop"), obj_ids=(1, 5, 30), splits=("test",),
                              images_per_scene=3, size=request.param, seed=5)
    return truth, *_rows(truth)


def test_default_threshold_is_5px_at_640_scaled_with_the_width(dataset):
    truth, rows, errs = dataset
    w = truth["size"][0]
    thr = 5.0 * w / 640  # 0.5 px at 64 pixels wide, 2 px at 256
    out = score(rows, truth["root"], split="test", metrics="proj")
    assert out["proj_px"] == pytest.approx(thr)
    assert out["all"]["n"] == len(errs)
    assert out["all"]["proj2d"] == pytest.approx(np.mean(errs < thr))
    assert 0 < np.mean(errs < thr) < 1  # the threshold splits the estimates: the test can tell widths apart


def test_proj_px_sets_the_threshold(dataset, tmp_path):
    truth, rows, errs = dataset
    out = score(rows, truth["root"], split="test", metrics="proj", proj_px=1.0)
    assert out["proj_px"] == 1.0
    assert out["all"]["proj2d"] == pytest.approx(np.mean(errs < 1.0))
    csv = tmp_path / "r.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "".join(
        f"{s},{i},{o},{sc},{' '.join(f'{x:.12f}' for x in np.ravel(R))},{' '.join(f'{x:.12f}' for x in t)},{tm}\n"
        for s, i, o, sc, R, t, tm in rows))
    js = tmp_path / "s.json"
    text = score_command([csv], truth["root"], "test", None, js, None, metrics="proj", proj_px=3)
    assert "mean reprojection distance < 3 px" in text and "2D projection threshold: 3 px (--proj-px" in text
    data = json.loads(js.read_text())
    assert data["proj_px"] == 3.0 and data["all"]["proj2d"] == pytest.approx(np.mean(errs < 3.0))


@pytest.mark.parametrize("bad", [0, -2, "x", float("nan"), True])
def test_a_bad_proj_px_is_one_line(dataset, bad):
    truth, rows, _ = dataset
    with pytest.raises(TdofError, match="--proj-px: the 2D projection threshold must be a number of pixels > 0"):
        score(rows, truth["root"], split="test", metrics="proj", proj_px=bad)
