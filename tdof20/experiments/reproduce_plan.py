"""What a ``tdof20 reproduce`` config asks for, without running anything: its trainings, its
predictions (the result rows, once per seed), the jobs with what each needs first, and what they
cost (counted, and multiplied out from measured unit times: ``benchmarks/methods_profile.py
--estimate PRESET``).

    runs = planned_runs(cfg)           # [{"name", "method", "split", "options", "seed", "images", "batch"}]
    jobs = job_plan(cfg)               # [{"name": "train/pvnet_simple_s0", "stage": "train", "needs": [...]}, ...]
    counts = plan(cfg)                 # frames, images per part, steps and images seen per run

Every training run sees ``train.images`` images (optimiser steps x its method's batch), the
budget of every compared row; the segmentation ablation's row without HFF6DoF's head is two
trainings, the segmentation network (:data:`~tdof20.experiments.reproduce_config.SEGNET`, its
``segnet_images``) and HFF6DoF without the head (the rest), which together see as many.
"""

from __future__ import annotations

import itertools

from tdof20.dataset.naming import normalize_scene_id, scene_number
from tdof20.dataset.splits import VAL_PART, part_of
from tdof20.dataset.validation import part_images
from tdof20.experiments.reproduce_config import LABELS, SEGNET, ReproduceConfig, candidate_table, row_label

#: the row label of the segmentation ablation's row without HFF6DoF's head, per mask source
NOSEG_LABELS = {"segnet": "HFF6DoF without segmentation head (masks of a separate segmentation network)",
                "gt": "HFF6DoF without segmentation head"}


def _seeded(name: str, seed: int) -> str:
    return f"{name}_s{seed}"


def planned_runs(cfg: ReproduceConfig) -> list[dict]:
    """Every training, seed by seed (all of seed 0 first: a complete table comes early):
    {"name", "method", "split", "options", "seed", "images" (the run's budget, images seen),
    "batch", "row" (the seed-free name)}; the main runs, HFF6DoF's 3D-voting row, the ablations'."""
    out = []
    b = cfg.train.images
    ab = cfg.ablations
    for seed in cfg.train.seeds:
        rows = [(f"{m}_{p}", m, p, {}, b) for m in cfg.methods for p in cfg.protocols]
        if "hff6dof" in cfg.methods and ab.voting_3d:  # the paper's pose recovery, its own targets
            rows += [(f"hff6dof-3d_{p}", "hff6dof", p, {"vector_origin": "observed"}, b) for p in cfg.protocols]
        rows += [(f"hff6dof_fuse{k}_hard", "hff6dof", "hard", {"fuse_stages": k}, b)
                 for k in ab.fuse_stages if k != 3]  # 3 is the main hard run
        if ab.segmentation:
            if ab.segmentation_masks == "segnet":
                s = cfg.segnet_images()
                rows += [(f"{SEGNET}_hard", SEGNET, "hard", {}, s),
                         ("hff6dof_noseg_hard", "hff6dof", "hard", {"seg_head": False}, b - s)]
            else:
                rows.append(("hff6dof_noseg_hard", "hff6dof", "hard", {"seg_head": False}, b))
        for row, m, p, opts, images in rows:
            batch = cfg.train.batch_size if m == SEGNET else cfg.batch_of(m)
            out.append({"name": _seeded(row, seed), "method": m, "split": p, "options": opts, "seed": seed,
                        "images": images, "batch": batch, "row": row})
    return out


def noseg_options(cfg: ReproduceConfig, seed: int) -> dict:
    """The prediction options of the row without HFF6DoF's head: the separate segmentation
    network's masks (its run folder relative to the reproduce folder), or ground-truth masks (an
    oracle row)."""
    if cfg.ablations.segmentation_masks == "segnet":
        return {"masks": "segnet", "seg_run": f"runs/{_seeded(f'{SEGNET}_hard', seed)}"}
    return {"masks": "gt"}


def planned_predictions(cfg: ReproduceConfig) -> list[dict]:
    """Every prediction (one per pose training): {"name", "run", "row", "seed", "label", "method",
    "split", "options", "role", "oracle"}; role "main" (a compared row of Tables 1-2: each method,
    and HFF6DoF's 3D voting as its own row), "fuse<k>" or "noseg" (the ablations); "oracle" marks
    a row predicted with ground-truth masks (outside every claim)."""
    out = []
    for r in planned_runs(cfg):
        if r["method"] == SEGNET:
            continue
        row, split = r["row"], r["split"]
        base = {"name": r["name"], "run": r["name"], "row": row, "seed": r["seed"], "method": r["method"],
                "split": split, "oracle": False}
        if row == f"{r['method']}_{split}":
            out.append({**base, "label": row_label(cfg, r["method"]), "options": {}, "role": "main"})
        elif row == f"hff6dof-3d_{split}":
            out.append({**base, "label": LABELS["hff6dof-3d"], "options": {"voting": "3d"}, "role": "main"})
        elif "fuse_stages" in r["options"]:
            k = r["options"]["fuse_stages"]
            out.append({**base, "label": f"HFF6DoF {k} fused", "options": {}, "role": f"fuse{k}"})
        else:
            opts = noseg_options(cfg, r["seed"])
            out.append({**base, "label": NOSEG_LABELS[cfg.ablations.segmentation_masks], "options": opts,
                        "role": "noseg", "oracle": opts["masks"] == "gt"})
    return out


def candidate_grid(cfg: ReproduceConfig, p: dict) -> list[dict]:
    """The candidate option sets of a main prediction ``p`` ([candidates.<method>], the product of
    its lists in the order given; the first set is the default), without the options that do not
    act on the row (its method record's ``unused_choices``: HFF6DoF's bearing_tol only with bearing
    voting, inlier_cos only with 3D voting) nor those the row fixes. [{}] when nothing is listed."""
    table = candidate_table(cfg.candidates, p["method"], p["options"])
    keys = list(table)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(table[k] for k in keys))]


def choice_source(cfg: ReproduceConfig, p: dict) -> dict:
    """The main prediction whose chosen options ``p`` uses: itself, or for the ablations' runs
    HFF6DoF's main run on hard of the same seed (the ablations change only the fusion or the head)."""
    if p["role"] == "main":
        return p
    name = _seeded("hff6dof_hard", p["seed"])
    return next(q for q in planned_predictions(cfg) if q["name"] == name)


def job_plan(cfg: ReproduceConfig) -> list[dict]:
    """The jobs ``cfg`` makes, in the order a local run takes them: {"name", "stage", "needs" (the
    jobs that must be done first: what an executor running jobs side by side waits for)}, with the
    options a choice tries ("grid") and the options a test prediction uses unless validation chose
    others ("default_options")."""
    preds = planned_predictions(cfg)
    jobs = [{"name": "dataset", "stage": "dataset", "needs": []}]
    for r in planned_runs(cfg):
        needs = ["dataset"]
        if r["row"] == "hff6dof_noseg_hard" and cfg.ablations.segmentation_masks == "segnet":
            needs.append(f"train/{_seeded(f'{SEGNET}_hard', r['seed'])}")  # its validation uses the masks
        jobs.append({"name": f"train/{r['name']}", "stage": "train", "needs": needs})
    chooses = set()
    for p in preds:
        grid = candidate_grid(cfg, p) if p["role"] == "main" else [{}]
        if len(grid) > 1:
            jobs.append({"name": f"choose/{p['name']}", "stage": "choose", "grid": grid,
                         "needs": [f"train/{p['run']}"]})
            chooses.add(p["name"])
    for p in preds:
        src = choice_source(cfg, p)
        default = {**candidate_grid(cfg, src)[0], **p["options"]}
        needs = [f"train/{p['run']}"] + ([f"choose/{src['name']}"] if src["name"] in chooses else [])
        jobs.append({"name": f"predict/{p['name']}", "stage": "predict", "default_options": default,
                     "needs": needs})
        jobs.append({"name": f"score/{p['name']}", "stage": "score", "needs": [f"predict/{p['name']}"]})
    if cfg.profile.enabled:
        jobs.append({"name": "profile", "stage": "profile", "needs": []})
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
    ids = [scene_number(normalize_scene_id(s)) for s in d.scenes]
    for sid in ids:
        for im in range(d.n_arms * d.steps):
            for p in cfg.protocols:
                part = part_of(p, sid, im, d.steps, d.n_arms, with_val=True, scenes=ids)
                if part is not None:
                    out[p][{"train": "train-val", VAL_PART: "val"}.get(part, part)] += 1
    return out


def run_schedule(images: int, batch: int, n: int) -> dict:
    """How a budget of ``images`` images seen becomes a training on a part of ``n`` images with
    batches of ``batch``: {"batch" (the batch the training uses: at most the part), "steps",
    "steps_per_epoch", "epochs" (the last one cut short where the steps end inside it),
    "images_seen" (steps x batch: the budget, or just above where a part smaller than the batch
    leaves a smaller batch)}. The same rule as :func:`tdof20.methods.train.train` (whole batches)."""
    bs = min(batch, max(1, n))
    spe = max(1, n // bs)
    steps = -(-images // bs)
    return {"batch": bs, "steps": steps, "steps_per_epoch": spe, "epochs": -(-steps // spe),
            "images_seen": steps * bs}


def plan(cfg: ReproduceConfig) -> dict:
    """What ``cfg`` asks for, counted without running anything: {"frames" (simulated RGB-D pairs,
    both phases), "parts" (:func:`part_counts`), "runs": [{"name", "row", "seed", "method", "split",
    "images" (train-val images), "batch", "steps", "epochs", "images_seen", "val_predictions",
    "val_images", "test_images", "candidates"}]}. Validation predictions are an upper bound
    (figures shared between the choices are counted once each)."""
    parts = part_counts(cfg)
    preds = {p["run"]: p for p in planned_predictions(cfg)}
    runs = []
    for r in planned_runs(cfg):
        n = parts[r["split"]]["train-val"]
        sch = run_schedule(r["images"], r["batch"], n)
        p = preds.get(r["name"])
        marks = validated_epochs(cfg, sch["epochs"])
        n_val, grid = 0, [{}]
        if p is not None:
            n_val = len(marks) if len(marks) > 1 and sch["steps"] > sch["steps_per_epoch"] else 0
            grid = candidate_grid(cfg, p) if p["role"] == "main" else [{}]
            n_val += len(grid) if len(grid) > 1 else 0
        vi = parts[r["split"]]["val"]
        runs.append({"name": r["name"], "row": r["row"], "seed": r["seed"], "method": r["method"],
                     "split": r["split"], "images": n, "batch": sch["batch"], "steps": sch["steps"],
                     "epochs": sch["epochs"], "images_seen": sch["images_seen"], "val_predictions": n_val,
                     "val_images": min(vi, cfg.select.max_images) if cfg.select.max_images else vi,
                     "test_images": parts[r["split"]]["test"] if p is not None else 0,
                     "candidates": len(grid) if p is not None and p["role"] == "main" else 0})
    d = cfg.data
    frames = 0 if cfg.dataset else 2 * len(d.scenes) * d.n_arms * d.steps
    return {"frames": frames, "parts": parts, "runs": runs}


def budgets(cfg: ReproduceConfig) -> dict:
    """{row: images seen by its training(s)} per seed: the segmentation ablation's row without the
    head counts the segmentation network's training with its own (what a fair comparison holds
    equal: tests/test_reproduce_plans.py)."""
    out: dict = {}
    for r in plan(cfg)["runs"]:
        row = "hff6dof_noseg_hard" if r["row"] == f"{SEGNET}_hard" else r["row"]
        key = (row, r["seed"])
        out[key] = out.get(key, 0) + r["images_seen"]
    return out


def estimate(cfg: ReproduceConfig, step_s: dict, image_s: dict, frame_s: float = 0.0,
             profile_s: float = 0.0) -> dict:
    """Multiply :func:`plan` out: ``step_s`` {method: seconds per optimiser step at the config's
    image size and its batch} (the segmentation network, when not given, at the slowest given
    method's rate: an upper bound), ``image_s`` {method: seconds per predicted image (input +
    network + pose recovery)}, ``frame_s`` seconds per simulated frame (capture + labels + dataset
    build), ``profile_s`` seconds for Table 3. Returns {"total_s", "dataset_s", "train_s",
    "val_s", "test_s", "profile_s", "per_run": [...], "plan"}."""
    pl = plan(cfg)
    per_run, tr, va, te = [], 0.0, 0.0, 0.0
    slowest = max(step_s.values()) if step_s else 0.0
    for r in pl["runs"]:
        t = r["steps"] * step_s.get(r["method"], slowest)
        per_image = image_s.get(r["method"], 0.0)
        v = r["val_predictions"] * r["val_images"] * per_image
        x = r["test_images"] * per_image
        tr, va, te = tr + t, va + v, te + x
        per_run.append({**r, "train_s": round(t, 1), "val_s": round(v, 1), "test_s": round(x, 1)})
    ds = pl["frames"] * frame_s
    return {"total_s": round(ds + tr + va + te + profile_s, 1), "dataset_s": round(ds, 1), "train_s": round(tr, 1),
            "val_s": round(va, 1), "test_s": round(te, 1), "profile_s": round(profile_s, 1), "per_run": per_run,
            "plan": pl}


__all__ = ["NOSEG_LABELS", "budgets", "candidate_grid", "choice_source", "estimate", "job_plan", "noseg_options",
           "part_counts", "plan", "planned_predictions", "planned_runs", "run_schedule", "validated_epochs"]
