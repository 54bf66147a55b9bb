"""Score pose-estimation results against a tdof20 (BOP) dataset: exact accuracies, fast.

``score(results, dataset_root, split=None, targets=None, metrics=None, proj_px=None) -> dict`` gives, per object, averaged
over objects ("mean") and pooled over targets ("all")::

    n          number of targets (in "mean": the number of objects averaged)
    add        ADD accuracy       mean distance of corresponding model points < 10% of the diameter
    adds       ADD-S accuracy     mean closest-point distance < 10% of the diameter
    add_s      ADD(S) accuracy    ADD-S for symmetric objects, ADD otherwise (the paper's ADD)
    proj2d     2D projection accuracy, mean reprojection distance < 5 px at 640 pixels wide (5 * width / 640
               px; ``proj_px`` sets it); the summary's "proj_px" is the threshold used
    auc_adds   AUC of ADD-S over 0-100 mm: mean over targets of max(0, 1 - e / 100 mm)
    auc_add_s  the same for ADD(S)
    ar_vsd     BOP19 average recall of VSD (10 taus 0.05-0.5 x 10 thresholds 0.05-0.5, delta 15 mm)
    ar_mssd    BOP19 average recall of MSSD (thresholds 0.05-0.5 of the diameter)
    ar_mspd    BOP19 average recall of MSPD (thresholds 5-50 px, errors scaled by 640 / image width)
    ar         (ar_vsd + ar_mssd + ar_mspd) / 3

and "scenes": the same pooled per scene. Which keys appear follows ``metrics``
(:func:`tdof20.scoring.scorer.resolve_metrics`): by default all but VSD and AR, and those two when every test image has
a depth image. The BOP metrics are matched as BOP19 does (:func:`tdof20.scoring.bop19.bop_matches`): per target the
top ``inst_count`` estimates, greedily by score, each take the unmatched one of the
``inst_count`` most visible ground-truth instances with the smallest error below the threshold.

The parts, one concept each: :mod:`~tdof20.scoring.evaluation` (thresholds, keys, the per-object
errors and their summary), :mod:`~tdof20.scoring.dataset_view` (the dataset and its targets as
scoring reads them), :mod:`~tdof20.scoring.scorer` (matching and the metrics, exactly and fast),
:mod:`~tdof20.scoring.bop19` (VSD, MSSD, MSPD and BOP19's matching) and
:mod:`~tdof20.scoring.report` (tables and plots). This module is the public entry point: :func:`score`
and the ``benchmark score`` command, and the names of those modules that callers import from here.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tdof20.errors import TdofError
from tdof20.formats.io import atomic_write_bytes, check_output_dir, check_output_file, read_json, write_json
from tdof20.scoring import report
from tdof20.scoring.dataset_view import DatasetView, Targets, load_targets, require_targets, targets_path
from tdof20.scoring.evaluation import (ADD_THRESHOLD, ALL_KEYS, AUC_MAX, BOP_KEYS, KEYS, METRIC_KEYS, METRICS,
                                       PROJ_PLOT_MAX, PROJ_THRESHOLD, VISIB_MIN, Evaluation, ObjectEval)
from tdof20.scoring.scorer import check_proj_px, evaluate, parse_metrics, resolve_metrics, vsd_unavailable


def score(results: Any, dataset_root: str | Path, split: str | None = None,
          targets: str | Path | None = None, metrics: Any = None, proj_px: float | None = None) -> dict[str, Any]:
    """Score ``results`` (a BOP results CSV path, a :class:`Results`, or a list of
    (scene_id, im_id, obj_id, score, R, t, time) rows) on the dataset at ``dataset_root`` with the
    targets of ``split`` ('simple' | 'hard': ROOT/test_targets_{split}.json) or the ``targets``
    file. ``metrics``: None (the default set) or names of :data:`METRICS`. ``proj_px``: the 2D
    projection threshold in pixels (default 5 px at 640 pixels wide, scaled with the image width;
    the summary's "proj_px" says which was used). Returns
    {"objects": {"<obj_id>": {...}}, "mean": {...}, "all": {...}, "scenes": {"<scene_id>": {...}}}
    (see the module docstring); accuracies, AUCs and average recalls are fractions in [0, 1]."""
    return evaluate(results, dataset_root, split, targets, metrics=metrics, proj_px=proj_px).summary()


def run_info(results_csv: str | Path) -> dict | None:
    """What ``tdof20 predict`` wrote beside a results file (``<stem>_info.json``: method, its config,
    input, depth mode, masks, timings), or None for results from elsewhere. ``oracle_masks`` is
    added: True when the poses were recovered on ground-truth masks (``masks == "gt"``), which
    every score made from them must say."""
    p = Path(results_csv)
    side = p.with_name(p.stem + "_info.json")
    if not side.is_file():
        return None
    info = read_json(side)
    if not isinstance(info, dict):
        raise TdofError(f"must hold a JSON object, got {type(info).__name__}", side)
    keep = ("method", "input", "depth_mode", "masks", "method_config", "run", "split")
    out = {k: info[k] for k in keep if k in info}
    out["oracle_masks"] = info.get("masks") == "gt"
    return out


def run_line(name: str, info: dict) -> str:
    """One line naming how a results file was made (for the scorer's output)."""
    cfg = json.dumps(info.get("method_config", {}), sort_keys=True)
    oracle = "  ORACLE MASKS (ground-truth segmentation)" if info.get("oracle_masks") else ""
    return (f"{name}: method {info.get('method', '?')} ({info.get('input', '?')}), depth {info.get('depth_mode', '?')}, "
            f"masks {info.get('masks', '-')}{oracle}, config {cfg}")


def score_command(results: list[Path], dataset: Path, split: str | None, targets: Path | None,
                  json_out: Path | None, plots: Path | None, metrics: str | None = None,
                  proj_px: float | None = None) -> str:
    """``tdof20 benchmark score RESULTS.csv... --dataset ROOT (--split S | --targets F) [--json OUT]
    [--plots DIR] [--metrics add,proj,vsd,mssd,mspd,ar] [--proj-px PX]``: score each results file, write the JSON
    (one file: its summary; several: {"<method>": summary, ...}) and the plots plus ``report.md``
    (Markdown tables) in DIR, and return the text to print: Tables 1-3 (those computed), every
    metric per method and per scene, warnings and timings."""
    if not results:
        raise TdofError("give at least one results file")
    parse_metrics(metrics)  # a bad --metrics or --proj-px is refused before anything is read
    proj_px = check_proj_px(proj_px)
    if json_out is not None:
        check_output_file(json_out, "--json", "JSON file")
    if plots is not None:
        check_output_dir(plots, "--plots", "folder for the plots and report.md")
    ds = DatasetView(dataset, split)
    tpath = targets_path(ds.root, split, targets, ds)
    evals = [evaluate(r, ds.root, split, targets, dataset=ds, metrics=metrics, proj_px=proj_px) for r in results]
    names = report.method_names(evals)
    n_targets = max((e.summary()["all"]["n"] for e in evals), default=0)
    head = f"dataset {ds.root}  targets {tpath.name} ({n_targets} target instances)"
    parts = [head, "", report.report_text(evals)]
    notes = []
    if any("proj2d" in e.keys for e in evals):
        how = "--proj-px" if proj_px is not None else "5 px at 640 pixels wide, scaled with the image width"
        notes.append(f"2D projection threshold: {report.proj_px_text(evals)} px ({how}; \"proj_px\" in the JSON)")
    infos = [run_info(r) for r in results]
    for name, info in zip(names, infos):
        if info is not None:
            notes.append(run_line(name, info))
    for name, ev in zip(names, evals):
        for w in ev.warnings:
            notes.append(f"{'note' if w.startswith('VSD not computed') else 'warning'}: {name}: {w}")
        t = ev.timings
        bop = f", BOP metrics {t['bop']:.2f} s" if "bop" in t else ""
        notes.append(f"{name}: {ev.n_rows} rows scored in {t['total']:.2f} s (read {t['read']:.2f} s, "
                     f"metrics {t['metrics']:.2f} s{bop})")
    if json_out is not None:
        summaries = [dict(e.summary(), **({"run": i} if i is not None else {})) for e, i in zip(evals, infos)]
        content = summaries[0] if len(evals) == 1 else dict(zip(names, summaries))
        write_json(json_out, content)
        notes.append(f"wrote {json_out}")
    if plots is not None:
        paths = report.write_plots(evals, plots)
        md = Path(plots) / "report.md"
        runs = "".join(f"- {run_line(n, i)}\n" for n, i in zip(names, infos) if i is not None)
        atomic_write_bytes(md, (f"{head}\n\n" + (runs + "\n" if runs else "") + report.report_markdown(evals)).encode())
        notes.append("wrote " + ", ".join(str(p) for p in paths + [md]))
    return "\n".join(parts + [""] + notes)


__all__ = ["ADD_THRESHOLD", "ALL_KEYS", "AUC_MAX", "BOP_KEYS", "DatasetView", "Evaluation", "KEYS", "METRICS",
           "METRIC_KEYS", "ObjectEval", "PROJ_PLOT_MAX", "PROJ_THRESHOLD", "Targets", "VISIB_MIN", "evaluate",
           "load_targets", "parse_metrics", "require_targets", "resolve_metrics", "run_info", "run_line", "score",
           "score_command", "targets_path", "vsd_unavailable"]
