"""Assemble annotated scenes into one BOP dataset with the paper's two protocols, in tdof20's layout
(:class:`tdof20.dataset.layouts.tdof20.Tdof20Reader` reads it back):

    ROOT/dataset_info.json        {"name", "scenes": {"<scene_id>": "single/cube_136", ...}, "splits": ...}
    ROOT/camera.json              BOP camera file (cx, cy, fx, fy, width, height, depth_scale)
    ROOT/models/                  obj_000001.ply ... + models_info.json (one model per object)
    ROOT/models_eval/             when the scenes bring one
    ROOT/scenes/{scene_id:06d}/   the BOP scene (rgb, depth, depth_opaque, depth_restored, masks, JSON)
    ROOT/splits/{simple,hard}_{train,test}.json    {"<scene_id>": [im_id, ...]}
    ROOT/test_targets_{simple,hard}.json           BOP targets [{"scene_id","im_id","obj_id","inst_count"}]

An annotated scene is a BOP scene folder with ``scene_info.json`` ({"scene_id": "multi/08",
"n_arms", "steps", ...}) and ``models/`` — what ``tdof20 annotate`` writes (and
``tdof20 sim label`` from the simulator's truth); :mod:`tdof20.dataset.scene_input` reads and
checks them. See docs/dataset.md.

``dataset build --layout L`` is :func:`build_dataset_in_layout`: the writer of each layout that
can be written (:data:`WRITERS`: this module's for tdof20's layout, :mod:`tdof20.dataset.build_bop`'s
for the standard BOP one) checks its options and builds. A built dataset's parts, counts and
shards (:func:`split_images`, :func:`stats`, :func:`pack`) are in :mod:`tdof20.dataset.stats`,
re-exported here.

A build checks every input (scene files, every image's PNG header, models) before it writes, and
writes ``ROOT/.build.json`` (the scene list under way) first and ``dataset_info.json`` last, so an
interrupted build is finished by running it again. An existing dataset is only rebuilt from its own
scene list, or grown with ``add=True`` (``dataset build --add``).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path

from tdof20.dataset.build_bop import build_bop_dataset, write_bop_layout
from tdof20.dataset.layouts import BopReader, Tdof20Reader
from tdof20.dataset.layouts.base import TARGET_MIN_VISIB
from tdof20.dataset.scene_input import (BUILD_MARKER, copy_file, copy_scene, plan_models, read_scenes, scene_folders,
                                        scene_list)
from tdof20.dataset.splits import PARTS, SPLIT_RULES, SPLITS, part_of, scene_name, scene_number
from tdof20.dataset.stats import pack, split_images, stats
from tdof20.errors import TdofError
from tdof20.formats import read_json, read_scene, write_json
from tdof20.progress import progress


def _dataset_scenes(out: Path) -> dict[int, str] | None:
    """{scene_id: name} of the dataset in ``out`` (None when ``out`` holds none)."""
    path = out / "dataset_info.json"
    if not path.exists():
        return None
    info = read_json(path)
    if not isinstance(info, dict) or not isinstance(info.get("scenes"), dict) or not isinstance(info.get("layout"), dict):
        raise TdofError("not a tdof20 dataset_info.json (needs 'scenes' and 'layout'); choose another --out", path)
    try:
        return {int(k): str(v) for k, v in info["scenes"].items()}
    except ValueError:
        raise TdofError("not a tdof20 dataset_info.json (scene keys must be integer ids)", path) from None


def build_dataset(scene_dirs: list[str | Path], out: str | Path, show_progress: bool = True,
                  add: bool = False) -> dict:
    """Gather annotated scenes into the dataset ``out``; returns its stats (see :func:`stats`).

    ``out`` must be empty or new, or hold the dataset of exactly these scenes (built again from
    them: a resume, or new labels). ``add=True`` adds the scenes to the dataset in ``out``
    (scenes, models, models_info, splits, targets and dataset_info stay consistent). Everything
    given is checked before anything is written: a refusal leaves ``out`` as it was."""
    out = Path(out)
    dirs = scene_folders(scene_dirs, out)

    # read and check every input
    new, sizes, _ = read_scenes(dirs)

    # what is in --out, and what this build makes of it
    existing = _dataset_scenes(out)
    marker = out / BUILD_MARKER
    pending = read_json(marker) if marker.exists() else None
    target = {sid: info["scene_id"] for sid, (info, _) in new.items()}
    if add and existing is not None:
        target.update(existing)
    if pending is not None:
        if not isinstance(pending, dict) or sorted(pending.get("scenes", [])) != sorted(target):
            raise TdofError(f"an unfinished build of other scenes is here ({BUILD_MARKER}): run that build again to "
                            "finish it, or choose another --out", out)
        if add and existing is not None:  # an interrupted --add: scenes it listed already are its own
            existing = {k: v for k, v in existing.items() if k not in new}
    elif existing is not None and add:
        again = sorted(set(new) & set(existing))
        if again:
            raise TdofError(f"{scene_list(again)} {'is' if len(again) == 1 else 'are'} already in the dataset: --add adds "
                            "new scenes only (to rebuild with new labels, give the full scene list without --add)", out)
    elif existing is not None and set(existing) != set(new):
        dropped = sorted(set(existing) - set(new))
        raise TdofError(f"holds the dataset of {scene_list(existing)}; building {scene_list(new)} here would "
                        + (f"drop {scene_list(dropped)}" if dropped else "redefine it")
                        + ": add scenes with --add, rebuild it with its full scene list, or choose another --out", out)
    elif existing is None and add:
        raise TdofError("--add needs an existing dataset (no dataset_info.json here): build it without --add first",
                        out)
    elif existing is None and pending is None and out.exists() and any(out.iterdir()):
        raise TdofError("folder is not empty and holds no dataset; choose another --out", out)
    keep = add and existing is not None  # the dataset's scenes and models stay; the new ones join them

    # one image size for the whole dataset (shards and camera.json need it)
    if keep:
        cam = read_json(out / "camera.json")
        if not isinstance(cam, dict) or not all(isinstance(cam.get(k), int) for k in ("width", "height")):
            raise TdofError("needs integer 'width' and 'height' (the dataset's image size)", out / "camera.json")
        ref_size, ref_what = (cam["height"], cam["width"]), f"the dataset {out} (camera.json)"
    else:
        first = min(new)
        ref_size, ref_what = sizes[first], f"{new[first][0]['scene_id']} ({new[first][1]})"
    for sid, hw in sizes.items():
        if hw != ref_size:
            raise TdofError(f"its images are {hw[1]}x{hw[0]} (width x height), those of {ref_what} are "
                            f"{ref_size[1]}x{ref_size[0]}: a dataset has one image size", new[sid][1])

    # models: one per object across all scenes (and the dataset's own when adding)
    sources = [d for _, (_, d) in sorted(new.items())]
    models, model_copies = plan_models(sources, "models", out, keep)
    evals, eval_copies = plan_models(sources, "models_eval", out, keep)
    if evals and set(evals) != set(models):
        raise TdofError(f"models_eval/ covers objects {sorted(evals)} but models/ has {sorted(models)}: give every "
                        "scene a models_eval/ with its objects, or none", sources[0])

    # write: the marker first, dataset_info.json last (a rerun of the same build finishes an interrupted one)
    out.mkdir(parents=True, exist_ok=True)
    write_json(marker, {"scenes": sorted(target)})
    for src, dst in model_copies + eval_copies:
        copy_file(src, dst)
    with progress(show_progress) as bar:
        task = bar.add_task("copying scenes", total=len(new))
        for sid, (info, d) in sorted(new.items()):
            copy_scene(d, out / "scenes" / f"{sid:06d}")
            bar.advance(task)
    write_json(out / "models" / "models_info.json", {str(k): v for k, v in sorted(models.items())})
    if evals:
        write_json(out / "models_eval" / "models_info.json", {str(k): v for k, v in sorted(evals.items())})
    if keep:
        info_all = read_json(out / "dataset_info.json")
    else:
        first = read_scene(out / "scenes" / f"{min(new):06d}")
        im0 = first.im_ids()[0]
        K = first.K(im0)
        h, w = ref_size
        write_json(out / "camera.json", {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                                         "fy": float(K[1, 1]), "width": int(w), "height": int(h),
                                         "depth_scale": float(first.depth_scale(im0))})
        info_all = {"name": "tdof20", "format": "bop", "scenes": {}, "layout": {}}
    for sid, (info, _) in new.items():
        info_all["scenes"][str(sid)] = scene_name(scene_number(info["scene_id"]))  # aliases -> names
        info_all["layout"][str(sid)] = {"n_arms": info["n_arms"], "steps": info["steps"]}
    order = sorted(info_all["scenes"], key=int)
    info_all["scenes"] = {k: info_all["scenes"][k] for k in order}
    info_all["layout"] = {k: info_all["layout"][k] for k in order}
    info_all["splits"] = dict(SPLIT_RULES)
    info_all["target_min_visib_fract"] = TARGET_MIN_VISIB
    write_splits(out, info_all)
    write_json(out / "dataset_info.json", info_all)
    marker.unlink()
    return stats(out)


def write_splits(root: Path, info: dict | None = None) -> None:
    """splits/{split}_{part}.json and test_targets_{split}.json from the scenes in ``root``
    (those ``info`` lists: default, ROOT/dataset_info.json)."""
    root = Path(root)
    info = read_json(root / "dataset_info.json") if info is None else info
    members = {(s, p): defaultdict(list) for s in SPLITS for p in PARTS}
    targets = {s: [] for s in SPLITS}
    for sid_s, arcs in info["layout"].items():
        sid = int(sid_s)
        scene = read_scene(root / "scenes" / f"{sid:06d}")
        for im_id in scene.im_ids():
            for split in SPLITS:
                part = part_of(split, sid, im_id, arcs["steps"], arcs["n_arms"])
                if part is None:
                    continue
                members[(split, part)][str(sid)].append(im_id)
                if part == "test":
                    counts = Counter(g["obj_id"] for g, gi in zip(scene.gt[im_id], scene.gt_info.get(im_id, []))
                                     if gi["visib_fract"] >= TARGET_MIN_VISIB)
                    targets[split] += [{"scene_id": sid, "im_id": im_id, "obj_id": int(o), "inst_count": int(n)}
                                       for o, n in sorted(counts.items())]
    for (split, part), m in members.items():
        write_json(root / "splits" / f"{split}_{part}.json", {k: sorted(v) for k, v in sorted(m.items(), key=lambda x: int(x[0]))})
    for split, t in targets.items():
        write_json(root / f"test_targets_{split}.json", t, indent=None)


def write_tdof20_layout(scene_dirs: list[str | Path], out: str | Path, *, split: str | None = None,
                        add: bool = False, show_progress: bool = True) -> dict:
    """``dataset build`` (``--layout tdof20``): both protocols, so no ``--split``; then :func:`build_dataset`."""
    if split is not None:
        raise TdofError("--split is for --layout bop (a tdof20-layout dataset holds both protocols)")
    return build_dataset(scene_dirs, out, show_progress=show_progress, add=add)


#: the layouts ``dataset build --layout`` writes: layout name -> writer (its options checked, then the build)
WRITERS = {Tdof20Reader.layout: write_tdof20_layout, BopReader.layout: write_bop_layout}


_REJECTED = "rejected by the reviewer"   # the skip reason of a frame the reviewer rejected (annotate's journal)


def unresolved_flags(scene_dir: str | Path) -> list[dict]:
    """What ``tdof20 annotate`` left for a person in the scene folder (``work/summary.json``'s
    ``unresolved_flags``: frames not labelled that the reviewer did not reject, objects that
    failed). A scene without an annotate summary (simulator truth, an import) has none."""
    path = Path(scene_dir) / "work" / "summary.json"
    if not path.exists():
        return []
    s = read_json(path)
    if not isinstance(s, dict):
        raise TdofError("not an annotate summary (a JSON object)", path)
    if isinstance(s.get("unresolved_flags"), list):
        return s["unresolved_flags"]
    # a summary written before the review tool: its skipped frames and failed objects
    skipped = (s.get("label") or {}).get("skipped") or []
    return ([{"arm": k.get("arm"), "step": k.get("step"), "reason": str(k.get("reason", ""))} for k in skipped
             if not str(k.get("reason", "")).startswith(_REJECTED)]
            + [{"obj_id": f.get("obj_id"), "reason": f.get("reason")} for f in s.get("failed_objects") or []])


def check_flags(scenes: list[str | Path]) -> None:
    """Refuse (one line) the first scene with unresolved flags (:func:`unresolved_flags`)."""
    for d in scenes:
        flags = unresolved_flags(d)
        if flags:
            f = flags[0]
            what = f"object {f['obj_id']}" if "obj_id" in f else f"arm {f.get('arm')} step {f.get('step')}"
            reason = str(f.get("reason", ""))
            raise TdofError(f"{len(flags)} unresolved flag(s), e.g. {what}: {reason[:160]}; review the scene "
                            f"(tdof20 annotate review {d}: correct, accept or reject, relabel) or give "
                            f"--allow-flagged to build with its frames as they are", Path(d) / "work" / "summary.json")


def build_dataset_in_layout(layout: str, scenes: list[str | Path], out: str | Path, *, split: str | None = None,
                            add: bool = False, show_progress: bool = True, allow_flagged: bool = False) -> dict:
    """``tdof20 dataset build SCENES... --out OUT [--layout L] [--split S] [--add] [--allow-flagged]``:
    write the annotated ``scenes`` as a dataset in ``layout`` (a name of :data:`WRITERS`) and
    return its :func:`stats`. One-line errors for an unknown layout and for options the layout
    does not take; a scene with unresolved flags (:func:`unresolved_flags`: frames the annotation
    could not label, failed objects, not resolved by a reviewer) is refused unless
    ``allow_flagged`` (then only its labelled frames go in, as always)."""
    writer = WRITERS.get(layout)
    if writer is None:
        raise TdofError(f"--layout must be {' or '.join(WRITERS)}, got '{layout}'")
    if not allow_flagged:
        check_flags([d for d in scenes if Path(d).is_dir()])
    return writer(scenes, out, split=split, add=add, show_progress=show_progress)


__all__ = ["BUILD_MARKER", "SPLIT_RULES", "TARGET_MIN_VISIB", "WRITERS", "build_bop_dataset", "build_dataset",
           "build_dataset_in_layout", "check_flags", "pack", "split_images", "stats", "unresolved_flags",
           "write_bop_layout", "write_splits", "write_tdof20_layout"]
