"""What the tables of a ``tdof20 reproduce`` say about the run: their entries from the scores
written, what was chosen on validation (and on which figures), and the header of tables.md.

    entries, fusion, seg_on, seg_off = table_entries(out, cfg, state)
    rows = choices(cfg, state)          # [{"result", "choice", "chosen", "validation"}]
    val = validation_rows(cfg, state, out)   # each result's validation figure, seed by seed
"""

from __future__ import annotations

import json
from pathlib import Path

from tdof20.errors import TdofError
from tdof20.experiments.entries import Entry, mean_spread, over_seeds
from tdof20.experiments.reproduce_config import ReproduceConfig
from tdof20.experiments.reproduce_plan import candidate_grid, choice_source, plan, planned_predictions
from tdof20.experiments.tables import models_info_objects
from tdof20.formats.io import read_json
from tdof20.scoring.scoring import DatasetView


def table_entries(out: Path, cfg: ReproduceConfig, state):
    """The tables' inputs from the scores written: (entries, fusion, seg_on, seg_off), one entry
    per row with its seeds' scores combined (:func:`over_seeds`: the mean and the spread). HFF6DoF's
    main row (the pose recovery its method options select: bearing + PnP by default, 3D voting with
    [method_options.hff6dof] voting = "3d") carries extra["primary"]: it stands for HFF6DoF
    in the agreement claims, fixed before any result (no choice between separately trained rows);
    its 3D-voting row is a row of its own. A row marked oracle (ground-truth masks) carries
    oracle_masks and stays outside every claim."""
    entries, fusion, seg_on, seg_off = [], {}, None, None
    rows: dict[str, list[dict]] = {}
    for p in planned_predictions(cfg):
        rows.setdefault(p["row"], []).append(p)
    for row, preds in rows.items():
        got = [(p, out / "scores" / f"{p['name']}.json") for p in preds]
        got = [(p, f) for p, f in got if f.exists()]
        if not got:
            continue
        p = got[0][0]
        s = over_seeds([read_json(f) for _, f in got], [q["seed"] for q, _ in got])
        primary = p["role"] == "main" and p["method"] == "hff6dof" and not p["options"]
        e = Entry(p["label"], p["method"], p["split"], s, oracle_masks=bool(s.get("oracle_masks")) or p["oracle"],
                  note=s.get("note", ""), extra={"primary": True} if primary else {})
        if p["role"] == "main":
            entries.append(e)
            if row == "hff6dof_hard":
                if cfg.ablations.fuse_stages:  # the main hard run is the 3-stage row of the fusion ablation
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


def absolute_options(out: Path, options: dict) -> dict:
    """Options with the segmentation network's run folder (relative to DIR in the plan) made absolute."""
    if "seg_run" in options and not Path(options["seg_run"]).is_absolute():
        return {**options, "seg_run": str(Path(out) / options["seg_run"])}
    return options


def test_options(cfg: ReproduceConfig, state, p: dict) -> dict:
    """The options the test prediction of ``p`` uses: the row's own, and those chosen on validation
    (the first candidate set while its choice is not done)."""
    src = choice_source(cfg, p)
    c = f"choose/{src['name']}"
    chosen = state.get(c)["options"] if state.done(c) else candidate_grid(cfg, src)[0]
    return {**{k: v for k, v in chosen.items() if k not in p["options"]}, **p["options"]}


def _same_options(a: dict, b: dict) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def validation_rows(cfg: ReproduceConfig, state, out: Path) -> list[dict]:
    """Each result's figure on the validation part, seed by seed, from the figures the choices were
    made on (reproduce.json's "validation"): its kept checkpoint predicted with the options its test
    prediction uses; where those were never validated (an ablation's run takes the options chosen
    for HFF6DoF's main hard run, validated with the first candidate set), the kept checkpoint's
    figure with the options it was validated with. [{"row", "label", "split", "role", "seed",
    "epoch", "options", "same_options", "add_s", "proj2d", "targets"}], the results whose training
    is done; add_s None where nothing was validated (select.epochs = "last" and no candidates)."""
    rows = []
    cache = state.data.get("validation", {})
    for p in planned_predictions(cfg):
        t = f"train/{p['run']}"
        if not state.done(t):
            continue
        k = state.get(t)
        want = absolute_options(out, test_options(cfg, state, p))
        figs = [f for f in cache.get(p["run"], []) if f["step"] == k["kept_step"]]
        f = next((f for f in figs if _same_options(f["options"], want)), None)
        same = f is not None
        f = f or (figs[0] if figs else {})
        rows.append({"row": p["row"], "label": p["label"], "split": p["split"], "role": p["role"],
                     "seed": p["seed"], "epoch": k["kept_epoch"],
                     "options": {key: v for key, v in f.get("options", want).items() if key != "seg_run"},
                     "same_options": same, "add_s": f.get("add_s"), "proj2d": f.get("proj2d"),
                     "targets": f.get("targets")})
    return rows


def validation_summary(rows: list[dict]) -> list[dict]:
    """:func:`validation_rows` row by row over the seeds: [{"label", "split", "role", "seeds",
    "add_s", "add_s_spread", "proj2d", "proj2d_spread", "per_seed", "same_options"}] (the mean over
    the seeds and half their range, as the test tables give them)."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["row"], []).append(r)
    out = []
    for g in groups.values():
        mean, spread = mean_spread([{k: r[k] for k in ("add_s", "proj2d")} for r in g])
        out.append({"label": g[0]["label"], "split": g[0]["split"], "role": g[0]["role"],
                    "seeds": [r["seed"] for r in g], "add_s": mean.get("add_s"),
                    "add_s_spread": spread.get("add_s") if len(g) > 1 else None, "proj2d": mean.get("proj2d"),
                    "proj2d_spread": spread.get("proj2d") if len(g) > 1 else None,
                    "per_seed": {str(r["seed"]): r["add_s"] for r in g},
                    "same_options": all(r["same_options"] for r in g)})
    return out


def choices(cfg: ReproduceConfig, state) -> list[dict]:
    """What was chosen on validation, per result, with the validation figures behind each choice: [{"result", "choice", "chosen", "validation"}]."""
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


def _n_sets(cfg: ReproduceConfig) -> int:
    return max((len(candidate_grid(cfg, p)) for p in planned_predictions(cfg) if p["role"] == "main"), default=1)


def tables_header(cfg: ReproduceConfig, root: Path, state) -> list[str]:
    d = cfg.data
    src = (_given_source(root) if cfg.dataset else
           f"simulated: {len(d.scenes)} scenes ({', '.join(d.scenes)}), {d.n_arms} arm positions x {d.steps} steps "
           f"of {d.step_deg:g} deg at {d.width}x{d.height}, oracle labels")
    secs = sum(j.get("seconds", 0.0) for j in state.data["jobs"].values())
    cpu = sum(j.get("cpu_seconds", 0.0) for j in state.data["jobs"].values())
    pl = plan(cfg)
    steps = ", ".join(dict.fromkeys(f"{r['method']} {r['steps']} x {r['batch']}" for r in pl["runs"]
                                    if r["row"] == f"{r['method']}_{r['split']}"))
    passes = ", ".join(f"{p} {cfg.train.images / max(1, n['train-val']):.1f}" for p, n in pl["parts"].items())
    sched = f"{steps}; epochs over the train-val images: {passes}"
    seg = ""
    if cfg.ablations.segmentation:
        seg = (f" The segmentation ablation's row without the head: the segmentation network "
               f"({cfg.segnet_images()} images) + HFF6DoF without its head ({cfg.train.images - cfg.segnet_images()})"
               if cfg.ablations.segmentation_masks == "segnet" else
               " The segmentation ablation's row without the head predicts with ground-truth masks: an oracle row, "
               "outside every claim") + "."
    sel = cfg.select
    return [f"# tdof20 reproduce — preset {cfg.preset}", "",
            f"Dataset: {src} ({root}). Training: on each protocol's train part minus its validation part, "
            f"{cfg.train.image_size[0]}x{cfg.train.image_size[1]}; every run the same budget, "
            f"{cfg.train.images} images seen (optimiser steps x batch: {sched}); "
            f"{len(cfg.train.seeds)} seed(s) per row ({', '.join(map(str, cfg.train.seeds))}): each value is the mean "
            "over the seeds ± half their range; device " + f"{cfg.device}." + seg,
            f"Choices on the validation part only (the test part is predicted once, with what was chosen): "
            f"epochs {'the validation-best' if sel.epochs == 'best' else 'the last'}"
            + (f" (every {sel.every} epochs)" if sel.epochs == "best" and sel.every > 1 else "")
            + f"; candidates {json.dumps(cfg.candidates) if cfg.candidates else 'none'}"
            + f" ({_n_sets(cfg)} candidate set(s) per compared row)"
            + (f"; at most {sel.max_images} validation images per protocol" if sel.max_images else "") + ".",
            f"Work so far: {secs:.0f} s of wall time, {cpu:.0f} s of CPU, over {len(state.data['jobs'])} jobs "
            "(DIR/reproduce.json)."]
