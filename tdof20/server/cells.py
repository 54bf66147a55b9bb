"""What a worker adds to a test result besides the scorer's summary: the cells of each condition
(occlusion level, distance, symmetric or not), the summary of the public part and of the held-back
(private) part of the test images, and the versions the result was computed with.

All of it comes from the scorer's own per-target arrays (:class:`~tdof20.scoring.evaluation.ObjectEval`:
its errors, decisions and BOP matches), never from a second scoring: :func:`instance_images`
gives each target instance's image, in the order the scorer keeps them (per object: the targets
with one estimate and one ground-truth instance, then those with several, then those without an
estimate, each in the order of the targets file), and checks it against the scorer's own per-instance
scene ids; when they disagree (a scorer that orders differently) nothing is added rather than a
wrong cell. Each cell is pooled over its instances like the scorer's per-scene cells, and the
disclosure rule (:mod:`tdof20.server.disclosure`) treats it by its target count like any other.

Conditions (the bins are fixed or come from public labels, never from test labels):

- occlusion: the instance's ``visib_fract`` (scene_gt_info.json): under 10 % hidden, 10-50 %,
  over 50 % (a BOP target is at least 10 % visible);
- distance: the camera-to-object distance |t| of the ground truth, in thirds cut at the terciles of
  the train images' distances (public labels), rounded to 10 mm;
- symmetry: the object's model symmetric (ADD-S counts) or not.

An instance of a target with several instances of one object gets the conditions of the
instances the scorer matches against in the order BOP's rule lists them (the scorer's matching
pairs them up inside the image; TDoF20's images hold each object once).
"""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

import tdof20
from tdof20.dataset.layouts import open_dataset
from tdof20.dataset.results import read_results
from tdof20.formats.io import read_json
from tdof20.scoring.dataset_view import DatasetView
from tdof20.scoring.evaluation import Evaluation

OCCLUSION = (("occlusion < 10 %", 0.9, 1.01), ("occlusion 10-50 %", 0.5, 0.9), ("occlusion > 50 %", -1.0, 0.5))
SYMMETRY = ("symmetric", "not symmetric")


def instance_images(ev: Evaluation, ds: DatasetView, targets: list[dict], results: Path) -> dict | None:
    """Per object id: (scene_id, im_id, ground-truth index) of each of its instances in ``ev``, in
    the scorer's order; None when that order does not match the scorer's per-instance scenes."""
    res = read_results(results)
    have = set(zip(res.scene_id.tolist(), res.im_id.tolist(), res.obj_id.tolist()))
    single: dict[int, list] = defaultdict(list)
    multi: dict[int, list] = defaultdict(list)
    missing: dict[int, list] = defaultdict(list)
    for t in targets:
        s, im, ob, cnt = int(t["scene_id"]), int(t["im_id"]), int(t["obj_id"]), int(t.get("inst_count", 1))
        gt = ds.scene(s).gt[im]
        idx = [i for i, g in enumerate(gt) if int(g[0]) == ob]
        vis = (ds.visib(s) or {}).get(im)
        ranked = sorted(idx, key=lambda i: -(vis[i] if vis is not None and i < len(vis) else 1.0))[:cnt]
        ranked += [ranked[-1] if ranked else None] * (cnt - len(ranked))
        if (s, im, ob) not in have:
            missing[ob] += [(s, im, i) for i in ranked]
        elif cnt == 1 and len(idx) == 1:
            single[ob].append((s, im, idx[0]))
        else:
            multi[ob] += [(s, im, i) for i in ranked]
    out = {}
    for ob, o in ev.objects.items():
        inst = single.get(ob, []) + multi.get(ob, []) + missing.get(ob, [])
        if len(inst) != o.n or not np.array_equal(np.array([x[0] for x in inst], np.int64), np.asarray(o.scene)):
            return None
        out[ob] = inst
    return out


def pooled(ev: Evaluation, masks: dict[int, np.ndarray]) -> dict[str, Any]:
    """One cell pooled over the instances in ``masks`` (per object), as the scorer pools a scene."""
    parts = [o.values(masks[ob]) for ob, o in ev.objects.items() if ob in masks]
    parts = [p for p in parts if p["n"] > 0]
    n = sum(p["n"] for p in parts)
    keys = list(ev.keys[1:])
    return {"n": n, **{k: (round(float(sum(p[k] * p["n"] for p in parts) / n), 10) if n else 0.0) for k in keys}}


def summary_of(ev: Evaluation, masks: dict[int, np.ndarray]) -> dict[str, Any]:
    """The scorer's summary ({"objects", "mean", "all", "scenes"}) of the instances in ``masks``."""
    keys = list(ev.keys[1:])
    objs = {}
    for ob, o in sorted(ev.objects.items()):
        m = masks.get(ob)
        if m is not None and m.any():
            objs[str(ob)] = {k: (round(v, 10) if isinstance(v, float) else v) for k, v in o.values(m).items()}
    per = [v for v in objs.values() if v["n"] > 0]
    mean = {"n": len(per), **{k: (round(float(np.mean([o[k] for o in per])), 10) if per else 0.0) for k in keys}}
    scenes = {}
    ids = sorted({int(x) for ob, o in ev.objects.items() if ob in masks for x in np.unique(o.scene[masks[ob]])})
    for sid in ids:
        scenes[str(sid)] = pooled(ev, {ob: masks[ob] & (o.scene == sid) for ob, o in ev.objects.items() if ob in masks})
    out = {"objects": objs, "mean": mean, "all": pooled(ev, masks), "scenes": scenes}
    if ev.proj_px is not None and "proj2d" in keys:
        out["proj_px"] = ev.proj_px
    return out


@lru_cache(maxsize=8)
def _distance_edges(root: str, hidden_key: str) -> tuple[float, float]:
    """The terciles (mm, rounded to 10) of the camera-to-object distances over the train images."""
    hidden = {int(s): set(ims) for s, ims in json.loads(hidden_key).items()}
    ds = DatasetView(root)
    d = []
    for s in ds.scene_ids:
        for im, gts in ds.scene(s).gt.items():
            if im not in hidden.get(int(s), set()):
                d += [float(np.linalg.norm(g[2])) for g in gts]
    if not d:
        return (500.0, 800.0)
    lo, hi = np.percentile(d, [100 / 3, 200 / 3])
    return (round(float(lo), -1), round(float(hi), -1))


def distance_edges(root: Path, hidden: dict[int, set[int]]) -> tuple[float, float]:
    key = json.dumps({str(s): sorted(v) for s, v in sorted(hidden.items())})
    return _distance_edges(str(Path(root).resolve()), key)


def condition_masks(ev: Evaluation, ds: DatasetView, inst: dict, edges: tuple[float, float]) -> dict:
    """{kind: {bin: {obj_id: mask}}} of each condition (module docstring)."""
    lo, hi = edges
    dist_bins = ((f"near (< {lo:g} mm)", -1.0, lo), (f"middle ({lo:g}-{hi:g} mm)", lo, hi),
                 (f"far (>= {hi:g} mm)", hi, float("inf")))
    occ: dict[str, dict] = {b[0]: {} for b in OCCLUSION}
    dist: dict[str, dict] = {b[0]: {} for b in dist_bins}
    sym: dict[str, dict] = {b: {} for b in SYMMETRY}
    for ob, o in ev.objects.items():
        vis, far = np.ones(o.n), np.zeros(o.n)
        for k, (s, im, i) in enumerate(inst[ob]):
            if i is None:
                continue
            v = (ds.visib(s) or {}).get(im)
            vis[k] = v[i] if v is not None and i < len(v) else 1.0
            far[k] = float(np.linalg.norm(ds.scene(s).gt[im][i][2]))
        for name, a, b in OCCLUSION:
            occ[name][ob] = (vis >= a) & (vis < b)
        for name, a, b in dist_bins:
            dist[name][ob] = (far >= a) & (far < b)
        sym[SYMMETRY[0 if o.symmetric else 1]][ob] = np.ones(o.n, bool)
    return {"occlusion": occ, "distance": dist, "symmetry": sym}


def conditions_of(ev: Evaluation, cmasks: dict, within: dict[int, np.ndarray] | None = None) -> dict:
    """{kind: {bin: cell}} pooled over the instances of each bin (and of ``within``); empty bins left out."""
    out: dict[str, dict] = {}
    for kind, bins in cmasks.items():
        cells = {}
        for name, masks in bins.items():
            m = {ob: (mk & within[ob] if within is not None else mk) for ob, mk in masks.items()}
            if any(x.any() for x in m.values()):
                cells[name] = pooled(ev, m)
        out[kind] = cells
    return out


def test_extras(ev: Evaluation, root: Path, split: str, results: Path, private: set[tuple[int, int]] | None,
                hidden: dict[int, set[int]], targets: list[dict] | None = None) -> dict:
    """What the worker adds to a test result (module docstring): {"conditions"} and, where the
    protocol has a held-back part (``private``: its (scene_id, im_id)), {"parts": {"public":
    {"summary", "conditions"}, "private": {...}}}; {} when the scorer's order cannot be followed.
    ``targets``: the targets ``ev`` was scored on (default: the protocol's test targets; a
    validation result gives its validation targets and gets its conditions the same way)."""
    ds = DatasetView(root)
    targets = read_json(ds.dataset.scoring_targets_path(split)) if targets is None else targets
    inst = instance_images(ev, ds, targets, results)
    if inst is None:
        return {}
    cm = condition_masks(ev, ds, inst, distance_edges(root, hidden))
    out: dict[str, Any] = {"conditions": conditions_of(ev, cm)}
    if private is not None:
        priv = {ob: np.array([(s, im) in private for s, im, _ in inst[ob]], bool) for ob in inst}
        out["parts"] = {}
        for name, m in (("public", {ob: ~v for ob, v in priv.items()}), ("private", priv)):
            out["parts"][name] = {"summary": summary_of(ev, m), "conditions": conditions_of(ev, cm, m)}
    return out


# ------------------------------------------------------------------ versions
def _digest(paths) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(str(p.name).encode())
        try:
            h.update(p.read_bytes())
        except OSError:
            h.update(b"\x00missing")
    return h.hexdigest()


def scorer_sources() -> list[Path]:
    """What a stored result is computed by: the scoring package, the results reader and this module
    (the condition cells and the parts); the disclosure rule applies when a result is shown, so it
    is not among them."""
    import tdof20.dataset.results
    import tdof20.scoring

    return (sorted(Path(tdof20.scoring.__file__).parent.rglob("*.py"))
            + [Path(tdof20.dataset.results.__file__), Path(__file__)])


@lru_cache(maxsize=1)
def scorer_version() -> str:
    """tdof20's version and a digest of :func:`scorer_sources`: any change to the scorer (a fix, a
    new rounding, a new condition bin) gives a new version. Computed once per process (a worker
    calls it as it starts), so it names the code the process imported, not what an upgrade has
    since put on disk: restart the server and its workers together after upgrading."""
    return f"{tdof20.__version__}+{_digest(scorer_sources())[:8]}"


def _stamp(p: Path) -> tuple:
    try:
        st = p.stat()
        return (str(p), st.st_mtime_ns, st.st_size)
    except OSError:
        return (str(p), None, None)


@lru_cache(maxsize=32)
def _targets_path(root: str, split: str) -> Path:
    return open_dataset(root).scoring_targets_path(split)


@lru_cache(maxsize=32)
def _dataset_files(root: str, split: str, targets_stamp: tuple) -> tuple[Path, ...]:
    ds = DatasetView(root)
    paths = [ds.dataset.scoring_targets_path(split)]
    scenes = sorted({int(t["scene_id"]) for t in read_json(paths[0])})
    for s in scenes:
        d = ds.scene_dir(s)
        paths += [d / "scene_gt.json", d / "scene_gt_info.json", d / "scene_camera.json"]
    paths += sorted((Path(root) / "models").glob("models_info.json"))
    return tuple(paths)


@lru_cache(maxsize=32)
def _dataset_digest(paths: tuple[Path, ...], stamps: tuple) -> str:
    return _digest(paths)[:8]


def dataset_version(root: Path, split: str, held_digest: str | None = None) -> str:
    """A digest of what a test score of ``split`` depends on in the dataset (its targets, its test
    scenes' labels and cameras, the models' info) and of its held-back image list, if any. Read
    again whenever one of those files changes (size or time), so a long-running server or worker
    sees the operator's change at once; otherwise a stat per file."""
    root = Path(root).resolve()
    paths = _dataset_files(str(root), split, _stamp(_targets_path(str(root), split)))
    v = _dataset_digest(paths, tuple(_stamp(p) for p in paths))
    return v + (f"/{held_digest[:6]}" if held_digest else "")


__all__ = ["OCCLUSION", "SYMMETRY", "condition_masks", "conditions_of", "dataset_version", "distance_edges",
           "instance_images", "pooled", "scorer_sources", "scorer_version", "summary_of", "test_extras"]
