"""What a ``tdof20 reproduce`` config asks for, without running anything: its trainings, its
predictions (the result rows), the jobs in the order they run, and what they cost (counted, and
multiplied out from measured unit times: ``benchmarks/methods_profile.py --estimate PRESET``).

    runs = planned_runs(cfg)           # [{"name", "method", "split", "options", "epochs"}]
    jobs = job_plan(cfg)               # [{"name": "train/pvnet_simple", "stage": "train"}, ...]
    counts = plan(cfg)                 # frames, images per part, steps per run
"""

from __future__ import annotations

import itertools

from tdof20.dataset.naming import normalize_scene_id, scene_number
from tdof20.dataset.splits import VAL_PART, part_of
from tdof20.dataset.validation import part_images
from tdof20.experiments.reproduce_config import LABELS, ReproduceConfig
from tdof20.methods.registry import get_method


def planned_runs(cfg: ReproduceConfig) -> list[dict]:
    """Every training: {"name", "method", "split", "options"} (the main runs, then the ablations')."""
    runs = [{"name": f"{m}_{p}", "method": m, "split": p, "options": {}, "epochs": getattr(cfg.epochs, m)}
            for m in cfg.methods for p in cfg.protocols]
    if "hff6dof" in cfg.methods and cfg.ablations.voting_3d:  # the paper's pose recovery, its own targets
        runs += [{"name": f"hff6dof-3d_{p}", "method": "hff6dof", "split": p, "options": {"vector_origin": "observed"},
                  "epochs": cfg.epochs.hff6dof} for p in cfg.protocols]
    for k in cfg.ablations.fuse_stages:
        if k != 3:  # 3 is the main hard run
            runs.append({"name": f"hff6dof_fuse{k}_hard", "method": "hff6dof", "split": "hard",
                         "options": {"fuse_stages": k}, "epochs": cfg.epochs.hff6dof})
    if cfg.ablations.segmentation:
        runs.append({"name": "hff6dof_noseg_hard", "method": "hff6dof", "split": "hard",
                     "options": {"seg_head": False}, "epochs": cfg.epochs.hff6dof})
    return runs


def planned_predictions(cfg: ReproduceConfig) -> list[dict]:
    """Every prediction: {"name", "run", "label", "method", "split", "options", "role"}."""
    out = []
    for r in planned_runs(cfg):
        base = {"run": r["name"], "method": r["method"], "split": r["split"]}
        if r["name"] == f"{r['method']}_{r['split']}":
            out.append({**base, "name": r["name"], "label": LABELS[r["method"]], "options": {}, "role": "main"})
        elif r["name"] == f"hff6dof-3d_{r['split']}":
            out.append({**base, "name": r["name"], "label": LABELS["hff6dof-3d"], "options": {"voting": "3d"},
                        "role": "main"})
        elif "fuse_stages" in r["options"]:
            k = r["options"]["fuse_stages"]
            out.append({**base, "name": r["name"], "label": f"HFF6DoF {k} fused", "options": {}, "role": f"fuse{k}"})
        else:
            out.append({**base, "name": r["name"], "label": "HFF6DoF without segmentation head", "options": {},
                        "role": "noseg"})
    return out


def candidate_grid(cfg: ReproduceConfig, p: dict) -> list[dict]:
    """The candidate option sets of a main prediction ``p`` ([candidates.<method>], the product of
    its lists in the order given; the first set is the default), without the options that do not
    act on the row (its method record's ``unused_choices``: HFF6DoF's bearing_tol only with bearing
    voting, inlier_cos only with 3D voting).
    [{}] when nothing is listed."""
    table = dict(cfg.candidates.get(p["method"], {}))
    for k in get_method(p["method"]).reproduce.unused_choices(p["options"]):
        table.pop(k, None)
    keys = list(table)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(table[k] for k in keys))]


def choice_source(cfg: ReproduceConfig, p: dict) -> dict:
    """The main prediction whose chosen options ``p`` uses: itself, or for the ablations' runs
    HFF6DoF's main run on hard (the ablations change only the fusion or the head)."""
    if p["role"] == "main":
        return p
    return next(q for q in planned_predictions(cfg) if q["name"] == "hff6dof_hard")



def job_plan(cfg: ReproduceConfig) -> list[dict]:
    """The jobs ``cfg`` makes, in the order they run: {"name", "stage"} each, with the options a
    choice tries ("grid"), the two HFF6DoF rows a formulation choice compares ("pair") and the
    options a test prediction uses unless validation chose others ("default_options")."""
    preds = planned_predictions(cfg)
    jobs = [{"name": "dataset", "stage": "dataset"}]
    jobs += [{"name": f"train/{r['name']}", "stage": "train"} for r in planned_runs(cfg)]
    for p in preds:
        grid = candidate_grid(cfg, p) if p["role"] == "main" else [{}]
        if len(grid) > 1:
            jobs.append({"name": f"choose/{p['name']}", "stage": "choose", "grid": grid})
    for split in cfg.protocols:
        pair = [p["name"] for p in preds if p["name"] in (f"hff6dof_{split}", f"hff6dof-3d_{split}")]
        if len(pair) == 2:
            jobs.append({"name": f"choose/formulation/{split}", "stage": "choose", "pair": pair})
    for p in preds:
        default = {**candidate_grid(cfg, choice_source(cfg, p))[0], **p["options"]}
        jobs.append({"name": f"predict/{p['name']}", "stage": "predict", "default_options": default})
        jobs.append({"name": f"score/{p['name']}", "stage": "score"})
    if cfg.profile.enabled:
        jobs.append({"name": "profile", "stage": "profile"})
    return jobs


def validated_epochs(cfg: ReproduceConfig, epochs: int) -> list[int]:
    if cfg.select.epochs != "best" or epochs < 2:
        return [epochs]
    every = cfg.select.every
    return sorted(set(range(every, epochs + 1, every)) | {epochs})


def part_counts(cfg: ReproduceConfig) -> dict:
    """{split: {"train-val", "val", "test"}} image counts of the config's data, from the split rules
    (simulated scenes) or the given dataset, without building anything."""
    out = {p: {"train-val": 0, "val": 0, "test": 0} for p in cfg.protocols}
    if cfg.dataset:
        for p in cfg.protocols:
            for part in out[p]:
                out[p][part] = len(part_images(cfg.dataset, p, part))
        return out
    d = cfg.data
    for s in d.scenes:
        sid = scene_number(normalize_scene_id(s))
        for im in range(d.n_arms * d.steps):
            for p in cfg.protocols:
                part = part_of(p, sid, im, d.steps, d.n_arms, with_val=True)
                if part is not None:
                    out[p][{"train": "train-val", VAL_PART: "val"}.get(part, part)] += 1
    return out


def plan(cfg: ReproduceConfig) -> dict:
    """What ``cfg`` asks for, counted without running anything: {"frames" (simulated RGB-D pairs,
    both phases), "parts" (:func:`part_counts`), "runs": [{"name", "method", "split", "images",
    "steps", "epochs", "val_predictions", "val_images", "test_images"}]}. Validation predictions are
    an upper bound (figures shared between the choices are counted once each)."""
    parts = part_counts(cfg)
    preds = {p["run"]: p for p in planned_predictions(cfg)}
    runs = []
    for r in planned_runs(cfg):
        n = parts[r["split"]]["train-val"]
        bs = min(cfg.train.batch_size, max(1, n))
        spe = max(1, n // bs)
        steps = r["epochs"] * spe
        if cfg.train.max_steps:
            steps = min(steps, cfg.train.max_steps)
        p = preds[r["name"]]
        marks = validated_epochs(cfg, r["epochs"])
        n_val = (len(marks) if len(marks) > 1 and steps > spe else 0)
        grid = candidate_grid(cfg, p) if p["role"] == "main" else [{}]
        n_val += len(grid) if len(grid) > 1 else 0
        if p["method"] == "hff6dof" and p["role"] == "main" and cfg.ablations.voting_3d:
            n_val += 1  # the formulation's figure (usually shared with the choices above)
        vi = parts[r["split"]]["val"]
        runs.append({"name": r["name"], "method": r["method"], "split": r["split"], "images": n, "steps": steps,
                     "epochs": r["epochs"], "val_predictions": n_val,
                     "val_images": min(vi, cfg.select.max_images) if cfg.select.max_images else vi,
                     "test_images": parts[r["split"]]["test"]})
    d = cfg.data
    frames = 0 if cfg.dataset else 2 * len(d.scenes) * d.n_arms * d.steps
    return {"frames": frames, "parts": parts, "runs": runs}


def estimate(cfg: ReproduceConfig, step_s: dict, image_s: dict, frame_s: float = 0.0,
             profile_s: float = 0.0) -> dict:
    """Multiply :func:`plan` out: ``step_s`` {method: seconds per optimiser step at the config's
    image size and batch}, ``image_s`` {method: seconds per predicted image (input + network + pose
    recovery)}, ``frame_s`` seconds per simulated frame (capture + labels + dataset build),
    ``profile_s`` seconds for Table 3. Returns {"total_s", "dataset_s", "train_s", "val_s", "test_s",
    "profile_s", "per_run": [...], "plan"}."""
    pl = plan(cfg)
    per_run, tr, va, te = [], 0.0, 0.0, 0.0
    for r in pl["runs"]:
        t = r["steps"] * step_s[r["method"]]
        v = r["val_predictions"] * r["val_images"] * image_s[r["method"]]
        x = r["test_images"] * image_s[r["method"]]
        tr, va, te = tr + t, va + v, te + x
        per_run.append({**r, "train_s": round(t, 1), "val_s": round(v, 1), "test_s": round(x, 1)})
    ds = pl["frames"] * frame_s
    return {"total_s": round(ds + tr + va + te + profile_s, 1), "dataset_s": round(ds, 1), "train_s": round(tr, 1),
            "val_s": round(va, 1), "test_s": round(te, 1), "profile_s": round(profile_s, 1), "per_run": per_run,
            "plan": pl}
