"""The paper's tables from score dicts and profile records (``tdof20 reproduce``'s last stage).

Pure functions: nothing here trains, predicts or scores. The inputs are

- :class:`Entry` — one scored result: a column title (``label``), the registry's method name, the
  protocol ('simple' | 'hard'), the dict :func:`tdof20.scoring.scoring.score` returns (optionally
  with ``"curves"``, see :func:`curves_from_evaluation`) and whether ground-truth masks picked the
  object pixels (``oracle_masks``);
- profile records of :func:`tdof20.methods.profile.profile_method` (Table 3).

and the outputs are plain structures (``protocol_table`` ...) rendered as Markdown, CSV and JSON by
:func:`write_tables`::

    Table 1   ADD(S) accuracy (%), rows = objects by name (asymmetric ones bold and marked *, as the
              paper bolds them), then the mean over objects; columns = methods x {simple, hard}
    Table 2   the same for the 2D projection accuracy (%)
    Table 3   parameters, multiply-adds at 480x640, FPS (network and pose recovery apart) on this
              device, beside the paper's figures
    ablation  fused stages 1..5 on hard (ADD(S), 2D projection); segmentation head on / off
    agreement the paper's stated figures beside ours, and a computed yes / no per claim

Conventions: the best value of a row is bold per protocol (the paper compares methods, never
simple against hard); a result made with ground-truth masks carries "(oracle masks)" wherever it
appears and never takes the bold (it is not a valid submission); a cell without a result is "—".
How each agreement claim is judged is in :data:`tdof20.experiments.agreement.CLAIMS` (and
docs/reproduce.md); :class:`Entry` lives in :mod:`tdof20.experiments.entries`.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.experiments.agreement import (CLAIMS, PAPER, TOLERANCE, agreement, agreement_csv,  # noqa: F401
                                          agreement_markdown)
from tdof20.experiments.entries import MISSING, ORACLE, SPLITS, Entry, csv_text, over_seeds, pct, pm, signed  # noqa: F401
from tdof20.formats.io import atomic_write_bytes, write_json
from tdof20.objects import get_object
from tdof20.scoring.report import accuracy_curve, counted
from tdof20.scoring.scoring import PROJ_PLOT_MAX

KEY_TITLES = {"add_s": "ADD(S)", "proj2d": "2D projection"}
TABLE_TITLES = {
    "add_s": "Table 1 — ADD(S) accuracy (%): mean model-point distance < 10 % of the diameter (closest point "
             "for symmetric objects)",
    "proj2d": "Table 2 — 2D projection accuracy (%): mean reprojection distance < {px} px",
}


def proj_px_of(entries: Sequence[Entry]) -> str:
    """The 2D projection threshold the entries' scores name ("proj_px", in pixels), "5" (the
    paper's) where none names one; several different ones joined with " / "."""
    px = list(dict.fromkeys(e.scores.get("proj_px") for e in entries if e.scores.get("proj_px") is not None))
    return " / ".join(f"{float(v):g}" for v in px) or "5"


# --------------------------------------------------------------------------------------------
# objects


def catalog_objects(obj_ids: Sequence[int]) -> dict[int, tuple[str, bool]]:
    """obj_id -> (name, asymmetric?) from the catalog for ids 1..20; 'obj_NNNNNN' (symmetry unknown:
    not marked) otherwise."""
    out = {}
    for o in sorted({int(i) for i in obj_ids}):
        if 1 <= o <= 20:
            ob = get_object(o)
            out[o] = (ob.name, not bool(ob.symmetric))
        else:
            out[o] = (f"obj_{o:06d}", False)
    return out


def models_info_objects(models_info: Mapping, names: Mapping[int, str] | None = None) -> dict[int, tuple[str, bool]]:
    """obj_id -> (name, asymmetric?) from a BOP models_info (symmetric = any symmetries given);
    names from ``names`` or the catalog for ids 1..20."""
    cat = catalog_objects([int(k) for k in models_info])
    out = {}
    for k, e in models_info.items():
        o = int(k)
        sym = bool(e.get("symmetries_continuous")) or bool(e.get("symmetries_discrete"))
        out[o] = ((names or {}).get(o) or cat[o][0], not sym)
    return out


def _object_ids(entries: Sequence[Entry]) -> list[int]:
    return sorted({int(k) for e in entries for k, v in e.scores["objects"].items() if v.get("n", 1) > 0})


# --------------------------------------------------------------------------------------------
# Tables 1 and 2


def _best(values: Sequence[float | None], eligible: Sequence[bool]) -> list[bool]:
    """Bold flags: the maximum of the eligible values (ties at the top all bold), when at least two
    compete and they are not all equal."""
    cand = [v for v, ok in zip(values, eligible) if ok and v is not None]
    if len(cand) < 2 or max(cand) - min(cand) < 1e-12:  # one result, or all alike: nobody is best
        return [False] * len(values)
    top = max(cand)
    return [bool(ok and v is not None and abs(v - top) < 1e-12) for v, ok in zip(values, eligible)]


def columns(entries: Sequence[Entry]) -> list[tuple[str, str]]:
    """(label, split) columns: labels in order of first appearance, each with simple then hard."""
    labels: list[str] = []
    for e in entries:
        if e.label not in labels:
            labels.append(e.label)
    return [(lab, s) for lab in labels for s in SPLITS]


def protocol_table(entries: Sequence[Entry], key: str = "add_s",
                   objects: Mapping[int, tuple[str, bool]] | None = None) -> dict:
    """Table 1 (``key`` 'add_s') or 2 ('proj2d') as a plain dict:
    {"key", "title", "columns": [{"label", "split", "method", "oracle_masks", "present", "seeds",
    "proj_px"}], "rows": [{"obj_id", "name", "asymmetric", "values", "spreads", "bold"}] (objects by
    id, then the mean row with obj_id None), "notes"}. Values are fractions or None (no result /
    object not tested), the mean over the row's seeds; spreads their half-range (None with one
    seed); bold = the best mean per row within each protocol, among results without oracle masks."""
    if key not in KEY_TITLES:
        raise TdofError(f"unknown table key '{key}' (known: {', '.join(KEY_TITLES)})")
    by = {}
    for e in entries:
        if (e.label, e.split) in by:
            raise TdofError(f"two results for '{e.label}' on {e.split}")
        by[(e.label, e.split)] = e
    cols = columns(entries)
    ids = _object_ids(entries)
    objs = dict(catalog_objects(ids))
    objs.update({int(k): v for k, v in (objects or {}).items()})
    col_info = []
    for lab, s in cols:
        e = by.get((lab, s))
        col_info.append({"label": lab, "split": s, "method": None if e is None else e.method,
                         "oracle_masks": bool(e is not None and e.oracle_masks), "present": e is not None,
                         "seeds": None if e is None else len(e.seeds),
                         "proj_px": None if e is None else e.scores.get("proj_px")})

    def row(obj_id):
        vals = [None if (lab, s) not in by else by[(lab, s)].value(key, obj_id) for lab, s in cols]
        spreads = [None if (lab, s) not in by else by[(lab, s)].spread(key, obj_id) for lab, s in cols]
        bold = [False] * len(cols)
        for s in SPLITS:
            idx = [i for i, (_, sp) in enumerate(cols) if sp == s]
            flags = _best([vals[i] for i in idx], [not col_info[i]["oracle_masks"] for i in idx])
            for i, f in zip(idx, flags):
                bold[i] = f
        return vals, spreads, bold

    rows = []
    for o in ids:
        vals, spreads, bold = row(o)
        name, asym = objs.get(o, (f"obj_{o:06d}", False))
        rows.append({"obj_id": o, "name": name, "asymmetric": bool(asym), "values": vals, "spreads": spreads,
                     "bold": bold})
    vals, spreads, bold = row(None)
    n_obj = max((int(e.scores["mean"].get("n", 0)) for e in entries), default=0)
    rows.append({"obj_id": None, "name": f"mean ({counted(n_obj, 'object')})", "asymmetric": False,
                 "values": vals, "spreads": spreads, "bold": bold})
    notes = ["Bold object names (marked *) are asymmetric: their ADD(S) is the stricter ADD; the others are "
             "symmetric (ADD-S). Bold values: the best of each row within each protocol.",
             f"{MISSING}: no result for that method and protocol, or the object is not in its test part."]
    n_seeds = sorted({c["seeds"] for c in col_info if c["seeds"]})
    if n_seeds and n_seeds[-1] > 1:
        notes.append(f"Each value: the mean over the row's {' or '.join(map(str, n_seeds))} seeds ± half their range "
                     "(max − min over 2); a difference smaller than the two rows' half-ranges together is not one "
                     "the seeds support.")
    if key == "proj2d":
        px = proj_px_of(entries)
        notes.append(f"2D projection threshold: {px} px" + (" (the paper's 5 px at 640 pixels wide, scaled with the "
                                                            "image width)" if any(c["proj_px"] is not None
                                                                                  for c in col_info) else "") + ".")
    if any(c["oracle_masks"] for c in col_info):
        notes.append(f"({ORACLE}): ground-truth masks picked each object's pixels — an oracle segmentation, not a "
                     "valid submission; such results never take the bold and stay outside every claim.")
    notes += [f"{e.title}: {e.note}" for e in entries if e.note]
    title = TABLE_TITLES[key].format(px=proj_px_of(entries)) if key == "proj2d" else TABLE_TITLES[key]
    return {"key": key, "title": title, "columns": col_info, "rows": rows, "notes": notes}


def _md_cell(v, bold: bool, spread: float | None = None) -> str:
    t = pct(v)
    t = f"**{t}**" if bold and v is not None else t
    return t + (f" ± {100 * spread:.2f}" if spread is not None and v is not None else "")


def _col_title(c: Mapping) -> str:
    return f"{c['label']} · {c['split']}" + (f" ({ORACLE})" if c["oracle_masks"] else "")


def protocol_markdown(table: Mapping) -> str:
    """Markdown of :func:`protocol_table`'s dict."""
    cols = table["columns"]
    out = [f"**{table['title']}**", "", "| object | " + " | ".join(_col_title(c) for c in cols) + " |",
           "| --- |" + " ---: |" * len(cols)]
    for r in table["rows"]:
        name = f"**{r['name']}** \\*" if r["asymmetric"] else r["name"]
        sp = r.get("spreads") or [None] * len(r["values"])
        out.append(f"| {name} | " + " | ".join(_md_cell(v, b, d) for v, b, d in zip(r["values"], r["bold"], sp))
                   + " |")
    return "\n".join(out + [""] + table["notes"])


def _num(v: float | None, scale: float = 100.0, digits: int = 4) -> float | None:
    return None if v is None else round(scale * float(v), digits)


def protocol_csv(table: Mapping) -> str:
    """CSV: obj_id, object, asymmetric, one column per method/protocol (percent, the mean over its
    seeds; empty = no result), and where any row has several seeds one "± half-range" column after
    each; the mean row last (obj_id empty)."""
    cols = table["columns"]
    spread = any(d is not None for r in table["rows"] for d in (r.get("spreads") or []))
    head = ["obj_id", "object", "asymmetric"]
    for c in cols:
        t = f"{c['label']}/{c['split']}" + (f" ({ORACLE})" if c["oracle_masks"] else "")
        head += [t, f"{t} ±"] if spread else [t]
    rows = [head]
    for r in table["rows"]:
        vals = []
        for v, d in zip(r["values"], r.get("spreads") or [None] * len(r["values"])):
            vals += [_num(v), _num(d)] if spread else [_num(v)]
        rows.append([r["obj_id"], r["name"], int(r["asymmetric"])] + vals)
    return csv_text(rows)


# --------------------------------------------------------------------------------------------
# Table 3


def _paper_of(p: Mapping) -> dict:
    paper = dict(p.get("paper") or {})
    m = str(p.get("method", ""))
    if m in PAPER["macs_G"]:
        paper.setdefault("macs_G", PAPER["macs_G"][m])
    if m == "hff6dof":
        paper.setdefault("parameters_M", PAPER["hff6dof_parameters_M"])
        paper.setdefault("fps", PAPER["hff6dof_fps"])
    return paper


def efficiency_table(profiles: Sequence[Mapping]) -> dict:
    """Table 3 from profile records: {"title", "rows": [{"method", "device", "parameters_M",
    "paper_parameters_M", "macs_G", "paper_macs_G", "network_ms", "network_fps", "pose_ms",
    "end_to_end_ms", "end_to_end_fps", "paper_fps", "input", "error"}], "notes"}."""
    rows, devices = [], []
    for p in profiles:
        paper = _paper_of(p)
        r = {"method": p.get("method"), "device": p.get("device"), "error": p.get("error"),
             "parameters_M": p.get("parameters_M"), "paper_parameters_M": paper.get("parameters_M"),
             "macs_G": p.get("macs_480x640_G"), "paper_macs_G": paper.get("macs_G"),
             "network_ms": p.get("network_ms"), "network_fps": p.get("network_fps"), "pose_ms": p.get("pose_ms"),
             "end_to_end_ms": p.get("end_to_end_ms"), "end_to_end_fps": p.get("end_to_end_fps"),
             "paper_fps": paper.get("fps"), "input": p.get("input"), "amp": p.get("amp")}
        if r["device"] and r["device"] not in devices:
            devices.append(r["device"])
        rows.append(r)
    notes = [f"Ours: measured on {', '.join(devices) or 'this device'} (untrained networks; pose recovery = end to "
             "end − network); the paper's FPS are on a " + PAPER["gpu"] + ". Multiply-adds at 480x640 "
             "(FlopCounterMode / 2), the paper's 'FLOPs' read as multiply-adds."]
    return {"title": "Table 3 — parameters, multiply-adds at 480x640 and speed", "rows": rows, "notes": notes}


def _f(v, spec: str = ".2f") -> str:
    if v is None:
        return MISSING
    if isinstance(v, float) and math.isinf(v):
        return "∞"
    return format(v, spec)


def efficiency_markdown(table: Mapping) -> str:
    out = [f"**{table['title']}**", "",
           "| method | parameters M (paper) | multiply-adds G (paper) | network ms | network FPS | "
           "pose recovery ms | end-to-end FPS (paper) | input B×H×W |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in table["rows"]:
        if r.get("error"):
            out.append(f"| {r['method']} | error: {r['error']} |" + " |" * 6)
            continue
        pp = f" ({_f(r['paper_parameters_M'])})" if r["paper_parameters_M"] is not None else ""
        pmac = f" ({_f(r['paper_macs_G'])})" if r["paper_macs_G"] is not None else ""
        pf = f" ({_f(r['paper_fps'])})" if r["paper_fps"] is not None else ""
        inp = "×".join(str(v) for v in r["input"]) if r.get("input") else MISSING
        out.append(f"| {r['method']} | {_f(r['parameters_M'])}{pp} | {_f(r['macs_G'])}{pmac} | "
                   f"{_f(r['network_ms'], '.1f')} | {_f(r['network_fps'])} | {_f(r['pose_ms'], '.1f')} | "
                   f"{_f(r['end_to_end_fps'])}{pf} | {inp} |")
    return "\n".join(out + [""] + table["notes"])


def efficiency_csv(table: Mapping) -> str:
    keys = ["method", "device", "parameters_M", "paper_parameters_M", "macs_G", "paper_macs_G", "network_ms",
            "network_fps", "pose_ms", "end_to_end_ms", "end_to_end_fps", "paper_fps", "error"]
    return csv_text([keys] + [[r.get(k) for k in keys] for r in table["rows"]])


# --------------------------------------------------------------------------------------------
# ablations


def _ablation_rows(items: Sequence[tuple[str, Entry | None]]) -> list[dict]:
    rows = []
    for name, e in items:
        rows.append({"setting": name, "label": None if e is None else e.label,
                     "oracle_masks": bool(e is not None and e.oracle_masks),
                     "n": None if e is None else e.scores["mean"].get("n"),
                     "add_s": None if e is None else e.value("add_s"),
                     "proj2d": None if e is None else e.value("proj2d"),
                     "add_s_spread": None if e is None else e.spread("add_s"),
                     "proj2d_spread": None if e is None else e.spread("proj2d")})
    for k in ("add_s", "proj2d"):
        flags = _best([r[k] for r in rows], [not r["oracle_masks"] for r in rows])
        for r, f in zip(rows, flags):
            r[f"{k}_bold"] = f
    return rows


def fusion_table(by_stages: Mapping[int, Entry]) -> dict:
    """The fusion-layer ablation on TDoF20-hard: one row per number of fused stages 1..5 (missing
    ones "—"), ADD(S) and 2D projection (means over objects), best bold."""
    bad = [k for k in by_stages if int(k) not in range(1, 6)]
    if bad:
        raise TdofError(f"fused stages must be 1..5, got {bad}")
    rows = _ablation_rows([(f"{k} fused stage{'s' if k > 1 else ''}" + (" (the paper's)" if k == 3 else ""),
                            by_stages.get(k)) for k in range(1, 6)])
    for k, r in zip(range(1, 6), rows):
        r["fuse_stages"] = k
    notes = ["Only the fusion changes between rows; the decoder's skip connections come from the fused stages, so "
             "the skips change with it (1 = layer4 only, 5 = stem..layer4); the decoder's widths do not.",
             "Paper: the highest ADD of 50.50 % with three fused stages, stable after."]
    if any(r["oracle_masks"] for r in rows):
        notes.append(f"({ORACLE}): ground-truth masks picked the object pixels.")
    return {"title": "Ablation — fused stages on TDoF20-hard (HFF6DoF)", "rows": rows, "notes": notes}


def segmentation_table(on: Entry | None, off: Entry | None) -> dict:
    """The segmentation-module ablation: with the head, without it (masks of a separately trained
    segmentation network, or ground-truth masks: an oracle row), and the gain (on - off)."""
    off_name = "without segmentation head"
    if off is not None and off.oracle_masks:
        off_name += f" ({ORACLE})"
    elif off is not None:
        off_name += ", masks of a separately trained segmentation network"
    rows = _ablation_rows([("with segmentation head", on), (off_name, off)])
    gain = {k: (None if on is None or off is None or on.value(k) is None or off.value(k) is None
                else on.value(k) - off.value(k)) for k in ("add_s", "proj2d")}
    notes = ["Paper: the segmentation module adds 8.52 % ADD and 2.63 % 2D projection."]
    if off is not None and off.oracle_masks:
        notes.append(f"Without the head, ground-truth masks ({ORACLE}) pick each object's pixels: the row without "
                     "the head is given a perfect segmentation, so the gain measured is a lower bound of what the "
                     "head brings over a real alternative; an oracle row, outside every claim.")
    elif off is not None:
        b = off.scores.get("budget") or []
        seg = [x.get("segnet_images_seen") for x in b if isinstance(x, Mapping)]
        notes.append("Without the head, a segmentation network trained separately on the same split picks each "
                     "object's pixels (the paper's ablation); its training counts in the row's budget"
                     + (f" ({seg[0]} of the row's images seen)" if seg and seg[0] else "") + ", so both rows "
                     "see as many images.")
    return {"title": "Ablation — segmentation module on TDoF20-hard (HFF6DoF)", "rows": rows, "gain": gain,
            "notes": notes}


def ablation_markdown(table: Mapping) -> str:
    out = [f"**{table['title']}**", "", "| setting | n objects | ADD(S) % | 2D projection % |",
           "| --- | ---: | ---: | ---: |"]
    for r in table["rows"]:
        name = r["setting"] + (f" ({ORACLE})" if r["oracle_masks"] and ORACLE not in r["setting"] else "")
        out.append(f"| {name} | {_f(r['n'], 'd')} | {_md_cell(r['add_s'], r['add_s_bold'], r.get('add_s_spread'))} | "
                   f"{_md_cell(r['proj2d'], r['proj2d_bold'], r.get('proj2d_spread'))} |")
    if "gain" in table:
        g = table["gain"]
        out.append(f"| gain of the head | | {signed(g['add_s'])} | {signed(g['proj2d'])} |")
    return "\n".join(out + [""] + table["notes"])


def ablation_csv(table: Mapping) -> str:
    rows = [["setting", "oracle_masks", "n_objects", "add_s", "proj2d", "add_s_spread", "proj2d_spread"]]
    rows += [[r["setting"], int(r["oracle_masks"]), r["n"], _num(r["add_s"]), _num(r["proj2d"]),
              _num(r.get("add_s_spread")), _num(r.get("proj2d_spread"))] for r in table["rows"]]
    if "gain" in table:
        rows.append(["gain", "", "", _num(table["gain"]["add_s"]), _num(table["gain"]["proj2d"]), "", ""])
    return csv_text(rows)


# --------------------------------------------------------------------------------------------
# curves and plots


def curves_from_evaluation(ev, points: int = 101) -> dict:
    """Accuracy-vs-threshold curves of a :class:`~tdof20.scoring.scoring.Evaluation`, pooled over
    its targets, to store in a score dict under "curves": {"add_s": {"x": % of the diameter 0-100,
    "y": accuracy}, "proj2d": {"x": px 0-20, "y": ...}} (those computed)."""
    objs = list(ev.objects.values())
    out = {}
    if "add_s" in ev.keys and objs:
        x = np.linspace(0, 100, points)
        e = np.concatenate([100 * o.add_s / o.diameter for o in objs])
        out["add_s"] = {"x": x.round(4).tolist(), "y": accuracy_curve(e, x).round(6).tolist()}
    if "proj2d" in ev.keys and objs:
        x = np.linspace(0, PROJ_PLOT_MAX, points)
        e = np.concatenate([o.proj for o in objs])
        out["proj2d"] = {"x": x.round(4).tolist(), "y": accuracy_curve(e, x).round(6).tolist()}
    return out


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name).strip("_") or "method"


def plot_accuracy(entries: Sequence[Entry], path: str | Path,
                  objects: Mapping[int, tuple[str, bool]] | None = None) -> Path:
    """One method's accuracy plot (PNG, matplotlib Agg): ADD(S) accuracy against the threshold (% of
    the diameter) and 2D projection against px, one line per protocol, where the score dicts hold
    "curves"; otherwise bars per object (ADD(S) and 2D projection, one bar per protocol)."""
    import matplotlib  # the Agg backend is chosen before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not entries:
        raise TdofError("nothing to plot")
    title = entries[0].label
    curves = all("curves" in e.scores and e.scores["curves"] for e in entries)
    if curves:
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=100)
        px = entries[0].scores.get("proj_px")
        for ax, key, xl, mark in ((axes[0], "add_s", "threshold (% of the object diameter)", 10.0),
                                  (axes[1], "proj2d", "threshold (px)", 5.0 if px is None else float(px))):
            for e in entries:
                c = e.scores["curves"].get(key)
                if c:
                    ax.plot(c["x"], 100 * np.asarray(c["y"]), lw=1.6,
                            label=e.split + (f" ({ORACLE})" if e.oracle_masks else ""))
            ax.axvline(mark, color="0.5", ls="--", lw=1)
            ax.set_ylim(0, 100)
            ax.set_xlabel(xl)
            ax.set_ylabel("accuracy (%)")
            ax.set_title(f"{title}: {KEY_TITLES[key]}")
            ax.grid(alpha=0.3)
            ax.legend(loc="lower right", fontsize=8)
    else:
        ids = _object_ids(entries)
        objs = dict(catalog_objects(ids))
        objs.update({int(k): v for k, v in (objects or {}).items()})
        fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 0.45 * len(ids) + 2), 6.4), dpi=100, squeeze=False)
        w = 0.8 / max(1, len(entries))
        x = np.arange(len(ids))
        for ax, key in zip(axes[:, 0], ("add_s", "proj2d")):
            for k, e in enumerate(entries):
                v = [e.value(key, o) for o in ids]
                ax.bar(x + (k - (len(entries) - 1) / 2) * w, [100 * (a or 0.0) for a in v], w,
                       label=e.split + (f" ({ORACLE})" if e.oracle_masks else ""))
            ax.set_xticks(x, [objs.get(o, (str(o), False))[0] + (" *" if objs.get(o, ("", False))[1] else "")
                              for o in ids], rotation=60, ha="right", fontsize=7)
            ax.set_ylim(0, 100)
            ax.set_ylabel(f"{KEY_TITLES[key]} (%)")
            ax.grid(alpha=0.3, axis="y")
            ax.legend(fontsize=8)
        axes[0, 0].set_title(f"{title}: accuracy per object (* asymmetric)")
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buf.getvalue())
    return path


# --------------------------------------------------------------------------------------------
# everything


def choices_markdown(rows: Sequence[Mapping]) -> str:
    """The choices made on validation ({"result", "choice", "chosen", "validation"} each) as a
    Markdown section."""
    out = ["**Chosen on validation** (the validation part of each protocol's train part; mean ADD(S) / "
           "2D projection accuracy over objects; the test part played no part in any choice)", ""]
    if not rows:
        return "\n".join(out + ["Nothing to choose: one checkpoint per training and no candidate options."])
    out += ["| result | choice | chosen on validation | validation ADD(S) / 2D projection |", "| --- | --- | --- | --- |"]
    out += [f"| {r['result']} | {r['choice']} | {r['chosen']} | {r['validation']} |" for r in rows]
    return "\n".join(out)


def choices_csv(rows: Sequence[Mapping]) -> str:
    return csv_text([["result", "choice", "chosen", "validation"]]
                 + [[r["result"], r["choice"], r["chosen"], r["validation"]] for r in rows])


VALIDATION_COLUMNS = ["result", "protocol", "seeds", "add_s", "add_s_spread", "proj2d", "proj2d_spread",
                      "per_seed_add_s", "options_as_tested"]


def validation_markdown(rows: Sequence[Mapping]) -> str:
    """The validation figures of each result (:func:`~tdof20.experiments.reproduce_report.validation_summary`'s
    rows) as a Markdown section: what every choice was made on, beside the test tables."""
    out = ["**On validation** (each result's kept checkpoint with the options its test prediction uses, on "
           "the validation part; mean ADD(S) and 2D projection accuracy over objects, mean over the seeds "
           "± half their range)", ""]
    if not rows:
        return "\n".join(out + ["No training done yet."])
    out += ["| result | protocol | ADD(S) % | 2D projection % | ADD(S) per seed % |", "| --- | --- | ---: | ---: | --- |"]
    for r in rows:
        mark = "" if r["same_options"] else " †"
        seeds = ", ".join(f"s{k} {pct(v, 1)}" for k, v in r["per_seed"].items())
        out.append(f"| {r['label']}{mark} | {r['split']} | {pm(r['add_s'], r['add_s_spread'])} | "
                   f"{pm(r['proj2d'], r['proj2d_spread'])} | {seeds} |")
    if any(not r["same_options"] for r in rows):
        out += ["", "† validated with the first candidate set; its test prediction takes the options chosen for "
                "HFF6DoF's main hard run."]
    if all(r["add_s"] is None for r in rows):
        out += ["", "Nothing was validated (select.epochs = \"last\" and no candidate options)."]
    return "\n".join(out)


def validation_csv(rows: Sequence[Mapping]) -> str:
    return csv_text([VALIDATION_COLUMNS] + [
        [r["label"], r["split"], " ".join(map(str, r["seeds"])), r["add_s"], r["add_s_spread"], r["proj2d"],
         r["proj2d_spread"], " ".join(f"{k}:{v}" for k, v in r["per_seed"].items()), r["same_options"]]
        for r in rows])


def write_tables(out_dir: str | Path, entries: Sequence[Entry], profiles: Sequence[Mapping] = (),
                 fusion: Mapping[int, Entry] | None = None, seg_on: Entry | None = None,
                 seg_off: Entry | None = None, objects: Mapping[int, tuple[str, bool]] | None = None,
                 header: Sequence[str] = (), plots: bool = True,
                 choices: Sequence[Mapping] | None = None,
                 validation: Sequence[Mapping] | None = None) -> dict[str, Path]:
    """Render every table into ``out_dir``: tables.md, tables.json, table1_add_s.csv,
    table2_proj2d.csv, table3_efficiency.csv, ablation_fusion.csv, ablation_segmentation.csv,
    agreement.csv, choices.csv (with ``choices``: what was chosen on validation, rendered after
    the header), validation.csv (with ``validation``: each result's validation figures) and
    plots/accuracy_<label>.png per method (atomic writes). Tables without any input are left out
    (a note says so). Returns {name: path}."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    md = [*header] + ([""] if header else [])
    data: dict[str, Any] = {}

    def put(name: str, text: str) -> None:
        atomic_write_bytes(out / name, text.encode())
        paths[name] = out / name

    if choices is not None:
        data["choices"] = [dict(r) for r in choices]
        md += [choices_markdown(choices), ""]
        put("choices.csv", choices_csv(choices))
    if validation is not None:
        data["validation"] = [dict(r) for r in validation]
        md += [validation_markdown(validation), ""]
        put("validation.csv", validation_csv(validation))

    if entries:
        for key, name in (("add_s", "table1_add_s.csv"), ("proj2d", "table2_proj2d.csv")):
            t = protocol_table(entries, key, objects)
            data[f"table{1 if key == 'add_s' else 2}"] = t
            md += [protocol_markdown(t), ""]
            put(name, protocol_csv(t))
    else:
        md += ["Tables 1 and 2: no scored results.", ""]
    if profiles:
        t3 = efficiency_table(profiles)
        data["table3"] = t3
        md += [efficiency_markdown(t3), ""]
        put("table3_efficiency.csv", efficiency_csv(t3))
    else:
        md += ["Table 3: not profiled.", ""]
    if fusion:
        ft = fusion_table(fusion)
        data["ablation_fusion"] = ft
        md += [ablation_markdown(ft), ""]
        put("ablation_fusion.csv", ablation_csv(ft))
    else:
        md += ["Fusion ablation: not run.", ""]
    if seg_on is not None or seg_off is not None:
        st = segmentation_table(seg_on, seg_off)
        data["ablation_segmentation"] = st
        md += [ablation_markdown(st), ""]
        put("ablation_segmentation.csv", ablation_csv(st))
    else:
        md += ["Segmentation ablation: not run.", ""]
    claims = agreement(entries, profiles, fusion, seg_on, seg_off)
    data["agreement"] = claims
    hff = [e for e in entries if e.method == "hff6dof" and e.extra.get("primary")]
    md += [agreement_markdown(claims, hff[0].label if hff else None), ""]
    put("agreement.csv", agreement_csv(claims))
    if plots and entries:
        md += ["**Accuracy plots**", ""]
        for label in dict.fromkeys(e.label for e in entries):
            group = [e for e in entries if e.label == label]
            p = plot_accuracy(group, out / "plots" / f"accuracy_{_safe(label)}.png", objects)
            paths[f"plots/{p.name}"] = p
            md.append(f"![{label}](plots/{p.name})")
        md.append("")
    put("tables.md", "\n".join(md))
    write_json(out / "tables.json", data)
    paths["tables.json"] = out / "tables.json"
    return paths


__all__ = ["CLAIMS", "Entry", "over_seeds", "proj_px_of", "MISSING", "ORACLE", "PAPER", "TOLERANCE", "ablation_csv", "ablation_markdown",
           "agreement", "agreement_csv", "agreement_markdown", "catalog_objects", "choices_csv", "choices_markdown",
           "columns", "curves_from_evaluation",
           "efficiency_csv", "efficiency_markdown", "efficiency_table", "fusion_table", "models_info_objects",
           "plot_accuracy", "protocol_csv", "protocol_markdown", "protocol_table", "segmentation_table",
           "validation_csv", "validation_markdown", "write_tables"]
