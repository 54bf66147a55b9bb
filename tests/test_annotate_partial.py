"""One failed object does not sink a scene (issue 25, part 2): the others are labelled, the failed
one is flagged with its reason in work/summary.json and qa/, and the run says "partial" (the CLI's
exit code 3; a batch row's status "partial")."""
import json
import shutil
from pathlib import Path

import numpy as np
import trimesh

from tdof20.annotate.batch import annotate_many
from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.label import LabelConfig
from tdof20.annotate.pipeline import annotate, summary_text
from tdof20.capture import run_capture, sim_config
from tdof20.formats import read_json

CFG = AnnotateConfig(label=LabelConfig(workers=1))


def _broken_models(raw: Path, dst: Path) -> int:
    """A copy of the truth's models with one object's mesh made 1.4x too big (as a model in the
    wrong units would be): returns that object's id."""
    shutil.copytree(raw / "truth" / "models", dst)
    gt = read_json(raw / "truth" / "scene_gt.json")
    o = int(next(iter(gt.values()))[0]["obj_id"])
    m = trimesh.load(dst / f"obj_{o:06d}.ply", force="mesh")
    m.apply_scale(1.4)
    m.export(dst / f"obj_{o:06d}.ply")
    for extra in dst.glob(f"obj_{o:06d}_samples.npy"):
        np.save(extra, np.load(extra) * 1.4)
    info = json.loads((dst / "models_info.json").read_text())   # a consistent, but wrong, model
    for k in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"):
        if k in info[str(o)]:
            info[str(o)][k] *= 1.4
    (dst / "models_info.json").write_text(json.dumps(info))
    return o


def test_a_wrong_model_for_one_object_gives_a_partial_scene(tmp_path: Path):
    raw = tmp_path / "raw"
    run_capture(sim_config("multi/08", steps=12, step_deg=30.0, n_arms=1, width=160, height=120), raw, yes=True,
                show_progress=False)
    models = tmp_path / "models"
    bad = _broken_models(raw, models)
    # the scene folder a batch into tmp_path/"batch" gives this session (DIR/multi/08), so that
    # the batch below resumes this run instead of annotating the scene a second time
    out = tmp_path / "batch" / "multi" / "08"
    s = annotate(raw, out, models_dir=models, cfg=CFG, progress=False)
    assert s["partial"] is True
    assert [f["obj_id"] for f in s["failed_objects"]] == [bad]
    assert "fits its cluster badly" in s["failed_objects"][0]["reason"]
    assert bad not in {p["obj_id"] for p in s["objects"]} and len(s["objects"]) >= 2
    assert s["label"]["labelled"] >= 10                     # the others are labelled
    gt = read_json(out / "scene_gt.json")
    assert gt and all(bad not in {e["obj_id"] for e in v} for v in gt.values())
    qa = read_json(out / "qa" / "qa.json")
    assert [f["obj_id"] for f in qa["failed_objects"]] == [bad]
    assert "Objects not labelled" in (out / "qa" / "report.html").read_text()
    assert read_json(out / "work" / "summary.json")["partial"] is True
    assert f"object {bad}: FAILED" in summary_text(s) and "partial" in summary_text(s)
    # a batch shows it: the scene's row says "partial", the summary lists it (here the batch finds
    # every stage of the scene up to date: a partial scene stays partial on a rerun, not "up to date")
    b = annotate_many([raw], tmp_path / "batch", models_dir=models, cfg=CFG, progress=False)
    assert b["scenes"][0]["out"] == str(out.resolve())
    assert b["scenes"][0]["status"] == "partial" and b["partial"] == ["multi/08"] and b["failed"] == []
    assert {st["status"] for st in read_json(out / "work" / "summary.json")["stages"].values()} == {"up to date"}
