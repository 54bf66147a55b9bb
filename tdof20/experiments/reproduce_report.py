"""What the tables of a ``tdof20 reproduce`` say about the run: their entries from the scores
written, what was chosen on validation (and on which figures), and the header of tables.md.

    entries, fusion, seg_on, seg_off = table_entries(out, cfg, state)
    rows = choices(cfg, state)          # [{"result", "choice", "chosen", "validation"}]
"""

from __future__ import annotations

import json
from pathlib import Path

from tdof20.errors import TdofError
from tdof20.experiments.entries import Entry
from tdof20.experiments.reproduce_config import LABELS, ReproduceConfig
from tdof20.experiments.reproduce_plan import choice_source, planned_predictions
from tdof20.experiments.tables import models_info_objects
from tdof20.formats.io import read_json
from tdof20.scoring.scoring import DatasetView


def table_entries(out: Path, cfg: ReproduceConfig, state):
    """The tables' inputs from the scores written: (entries, fusion, seg_on, seg_off); the HFF6DoF
    row chosen on validation to stand for HFF6DoF in the agreement claims carries extra["primary"]."""
    entries, fusion, seg_on, seg_off = [], {}, None, None
    for p in planned_predictions(cfg):
        f = out / "scores" / f"{p['name']}.json"
        if not f.exists():
            continue
        s = read_json(f)
        form = f"choose/formulation/{p['split']}"
        primary = state.done(form) and state.get(form).get("primary") == p["name"]
        e = Entry(p["label"], p["method"], p["split"], s, oracle_masks=bool(s.get("oracle_masks")),
                  note=s.get("note", ""), extra={"primary": True} if primary else {})
        if p["role"] == "main":
            entries.append(e)
            if p["method"] == "hff6dof" and p["split"] == "hard" and p["name"] == "hff6dof_hard":
                if 3 in cfg.ablations.fuse_stages:
                    fusion[3] = e
                seg_on = e
        elif p["role"].startswith("fuse"):
            fusion[int(p["role"][4:])] = e
        else:
            seg_off = e
    return entries, fusion, (seg_on if cfg.ablations.segmentation else None), seg_off


def dataset_objects(root: Path) -> dict:
    """The dataset's objects as the tables list them (names, diameters, symmetries)."""
    ds = DatasetView(root)
    return models_info_objects(ds.models_info, {int(o): ds.object_name(int(o)) for o in ds.models_info})


def _pcts(f: dict) -> str:
    a, b = f.get("add_s"), f.get("proj2d")
    return f"{'—' if a is None else f'{100 * a:.1f}'} / {'—' if b is None else f'{100 * b:.1f}'} %"


def _opts_text(options: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in options.items()) or "defaults"


def choices(cfg: ReproduceConfig, state) -> list[dict]:
    """What was chosen on validation, per result (and the HFF6DoF formulation per protocol), with
    the validation figures behind each choice: [{"result", "choice", "chosen", "validation"}]."""
    rows = []
    for p in planned_predictions(cfg):
        t = f"train/{p['run']}"
        if state.done(t):
            j = state.get(t)
            val = j.get("validation") or []
            if val:
                rows.append({"result": p["name"], "choice": "epoch",
                             "chosen": f"epoch {j['kept_epoch']} of {j['epochs']} (step {j['kept_step']})",
                             "validation": "; ".join(f"epoch {f['epoch']}: {_pcts(f)}" for f in val)})
        c = f"choose/{choice_source(cfg, p)['name']}"
        if state.done(c) and state.get(c).get("validation"):
            j = state.get(c)
            fixed = set(p["options"])
            rows.append({"result": p["name"], "choice": "options" if p["role"] == "main" else
                         f"options (those of {choice_source(cfg, p)['name']})",
                         "chosen": _opts_text({k: v for k, v in j["options"].items() if k not in fixed}),
                         "validation": "; ".join(_opts_text({k: v for k, v in f["options"].items() if k not in fixed})
                                                 + f": {_pcts(f)}" for f in j["validation"])})
    for split in cfg.protocols:
        c = f"choose/formulation/{split}"
        if state.done(c):
            j = state.get(c)
            rows.append({"result": f"HFF6DoF · {split}", "choice": "pose recovery standing for HFF6DoF "
                         "(agreement claims)", "chosen": LABELS[j["primary"].split("_")[0]],
                         "validation": "; ".join(f"{LABELS[n.split('_')[0]]}: {_pcts(f)}"
                                                 for n, f in j["validation"].items())})
    return rows


def _given_source(root: Path) -> str:
    """What a given dataset is, from its dataset_info.json: e.g. 'the given dataset, imported from
    the TDoF20 release at /data/TDoF20: 5 scenes, 3 objects'."""
    try:
        info = read_json(root / "dataset_info.json")
    except TdofError:
        return "the given dataset"
    origin = {"tdof20-release": "imported from the TDoF20 release"}
    src = origin.get(info.get("source"), "")
    src += f" at {info['source_path']}" if src and info.get("source_path") else ""
    counts = f"{len(info.get('scenes') or {})} scenes, {len(info.get('objects') or {})} objects"
    return f"the given dataset, {src}: {counts}" if src else f"the given dataset: {counts}"


def tables_header(cfg: ReproduceConfig, root: Path, state) -> list[str]:
    d = cfg.data
    src = (_given_source(root) if cfg.dataset else
           f"simulated: {len(d.scenes)} scenes ({', '.join(d.scenes)}), {d.n_arms} arm positions x {d.steps} steps "
           f"of {d.step_deg:g} deg at {d.width}x{d.height}, oracle labels")
    secs = sum(j.get("seconds", 0.0) for j in state.data["jobs"].values())
    cpu = sum(j.get("cpu_seconds", 0.0) for j in state.data["jobs"].values())
    ep = ", ".join(f"{m} {getattr(cfg.epochs, m)}" for m in cfg.methods)
    sel = cfg.select
    return [f"# tdof20 reproduce — preset {cfg.preset}", "",
            f"Dataset: {src} ({root}). Training: on each protocol's train part minus its validation part, "
            f"{cfg.train.image_size[0]}x{cfg.train.image_size[1]}, batch "
            f"{cfg.train.batch_size}, epochs {ep}" + (f", at most {cfg.train.max_steps} optimiser step(s) per run"
                                                     if cfg.train.max_steps else "") + f"; device {cfg.device}.",
            f"Choices on the validation part only (the test part is predicted once, with what was chosen): "
            f"epochs {'the validation-best' if sel.epochs == 'best' else 'the last'}"
            + (f" (every {sel.every} epochs)" if sel.epochs == "best" and sel.every > 1 else "")
            + f"; candidates {json.dumps(cfg.candidates) if cfg.candidates else 'none'}"
            + (f"; at most {sel.max_images} validation images per protocol" if sel.max_images else "") + ".",
            f"Work so far: {secs:.0f} s of wall time, {cpu:.0f} s of CPU, over {len(state.data['jobs'])} jobs "
            "(DIR/reproduce.json)."]
