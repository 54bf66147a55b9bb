"""Reports of scored results: the paper's Tables 1-2 (text and Markdown) and accuracy curves.

Layout as in the paper: one row per object (catalog name for ids 1-20; asymmetric objects marked
``*`` in text and **bold** in Markdown, since their ADD(S) is the stricter ADD), one column per
method, then the mean over objects and the accuracy pooled over all targets. Table 1 is ADD(S)
accuracy (< 10% of the diameter), Table 2 the 2D projection accuracy (< 5 px), Table 3 the BOP
average recall AR (the mean of AR_VSD, AR_MSSD and AR_MSPD); with several methods the best value
of each row is bold in Markdown. :func:`metrics_table` lists every metric computed for one
method, :func:`scenes_table` the same per scene. Tables of metrics not computed are left out.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from tdof20.scoring import metrics as M
from tdof20.scoring.evaluation import ADD_THRESHOLD, AUC_MAX, PROJ_THRESHOLD, Evaluation, format_px

TABLES = {
    "add_s": f"Table 1 - ADD(S) accuracy (%): mean model-point distance < {ADD_THRESHOLD:.0%} of the diameter "
             f"(closest point for symmetric objects)",
    "proj2d": "Table 2 - 2D projection accuracy (%): mean reprojection distance < {px} px",
    "ar": "Table 3 - BOP average recall AR (%): the mean of AR_VSD, AR_MSSD and AR_MSPD (BOP19)",
}
METRIC_LABELS = {"add": "ADD", "adds": "ADD-S", "add_s": "ADD(S)", "proj2d": "2D proj", "auc_adds": "AUC ADD-S",
                 "auc_add_s": "AUC ADD(S)", "ar_vsd": "AR VSD", "ar_mssd": "AR MSSD", "ar_mspd": "AR MSPD",
                 "ar": "AR"}


def proj_px_text(evals: Sequence[Evaluation]) -> str:
    """The 2D projection threshold(s) the evaluations used, as text ("0.75", "5", "2.5-5")."""
    pxs = list(dict.fromkeys(format_px(getattr(e, "proj_px", None)) for e in evals
                             if getattr(e, "proj_px", None) is not None))
    return "/".join(pxs) if pxs else f"{PROJ_THRESHOLD:g}"


def title_of(evals: Sequence[Evaluation], key: str) -> str:
    """The table title of ``key`` (Table 2 names the 2D projection threshold used)."""
    t = TABLES.get(key, METRIC_LABELS.get(key, key))
    return t.format(px=proj_px_text(evals)) if key == "proj2d" else t


def counted(n: int, word: str) -> str:
    """``n`` and ``word``, plural unless n is 1: "1 object", "3 objects"."""
    return f"{n} {word}" + ("" if n == 1 else "s")


def _keys(ev: Evaluation) -> list[str]:
    """The metric keys computed for ``ev``, in report order."""
    return [k for k in getattr(ev, "keys", ("n",) + tuple(METRIC_LABELS))[1:] if k in METRIC_LABELS]


def object_name(obj_id: int, evals: Sequence[Evaluation] = ()) -> str:
    """The dataset's name of the object (the evaluations' ``object_labels``: a BOP dataset's
    'obj_000005' or its names file), else the catalog name of ids 1-20 (tdof20.objects), else 'obj_<id>'."""
    for e in evals:
        name = (getattr(e, "object_labels", None) or {}).get(int(obj_id))
        if name:
            return name
    if 1 <= obj_id <= 20:
        from tdof20.objects import get_object

        return get_object(obj_id).name
    return f"obj_{obj_id:06d}"


def method_names(evals: Sequence[Evaluation]) -> list[str]:
    """Column titles: each method's name, made unique with a counter where two are alike."""
    names, seen = [], {}
    for e in evals:
        n = e.method
        seen[n] = seen.get(n, 0) + 1
        names.append(n if seen[n] == 1 else f"{n}#{seen[n]}")
    return names


def _rows(evals: Sequence[Evaluation], key: str):
    """[(label, asymmetric?, [value per method or None])] for objects, mean and all."""
    sums = [e.summary() for e in evals]
    ids = sorted({int(k) for s in sums for k in s["objects"]})
    sym = {}
    for e in evals:
        for k, o in e.objects.items():
            sym[k] = o.symmetric
    rows = []
    for i in ids:
        vals = [s["objects"].get(str(i), {}).get(key) for s in sums]
        rows.append((f"{i:>2} {object_name(i, evals)}", not sym.get(i, True), vals))  # text pads ids; markdown strips
    n_obj = max((s["mean"]["n"] for s in sums), default=0)
    n_all = max((s["all"]["n"] for s in sums), default=0)
    rows.append((f"mean ({counted(n_obj, 'object')})", False, [s["mean"][key] for s in sums]))
    rows.append((f"all ({counted(n_all, 'target')})", False, [s["all"][key] for s in sums]))
    return rows, len(ids)


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def table_text(evals: Sequence[Evaluation], key: str = "add_s", title: str | None = None) -> str:
    """Fixed-width text table of ``key`` (a summary key) for one or more methods."""
    rows, _ = _rows(evals, key)
    names = method_names(evals)
    labels = [f"{lab} *" if asym else lab for lab, asym, _ in rows]
    w0 = max([len("object")] + [len(x) for x in labels])
    ws = [max(7, len(n)) for n in names]
    out = [title or title_of(evals, key)]
    out.append("object".ljust(w0) + "".join("  " + n.rjust(w) for n, w in zip(names, ws)))
    out.append("-" * (w0 + sum(w + 2 for w in ws)))
    for k, (lab, (_, _, vals)) in enumerate(zip(labels, rows)):
        if k == len(rows) - 2:
            out.append("-" * (w0 + sum(w + 2 for w in ws)))
        out.append(lab.ljust(w0) + "".join("  " + _pct(v).rjust(w) for v, w in zip(vals, ws)))
    if key in ("add_s", "proj2d"):
        out.append("* asymmetric object: ADD(S) is ADD; the others are symmetric: ADD(S) is ADD-S")
    else:
        out.append("* asymmetric object (MSSD, MSPD: the symmetries of models_info.json, discretised as BOP does)")
    return "\n".join(out)


def table_markdown(evals: Sequence[Evaluation], key: str = "add_s", title: str | None = None) -> str:
    """Markdown table of ``key``: asymmetric objects bold (as in the paper), and with several
    methods the best value of each row bold."""
    rows, _ = _rows(evals, key)
    names = method_names(evals)
    out = [f"**{title or title_of(evals, key)}**", "",
           "| object | " + " | ".join(names) + " |", "| --- |" + " ---: |" * len(names)]
    for lab, asym, vals in rows:
        finite = [v for v in vals if v is not None]
        best = max(finite) if finite and len(names) > 1 else None
        cells = [("-" if v is None else (f"**{_pct(v)}**" if best is not None and v == best else _pct(v)))
                 for v in vals]
        lab = lab.strip()
        out.append(f"| {'**' + lab + '**' if asym else lab} | " + " | ".join(cells) + " |")
    out += ["", "Bold objects are asymmetric (ADD(S) = ADD); the others are symmetric (ADD(S) = ADD-S)."
            if key in ("add_s", "proj2d") else "Bold objects are asymmetric."]
    return "\n".join(out)


def _table(title: str, first: str, rows: list, keys: list[str], markdown: bool) -> str:
    """rows: [(label, bold/starred?, values dict, show n?)] -> a text or Markdown table (percent)."""
    heads = ["n"] + [METRIC_LABELS[k] for k in keys]
    if markdown:
        out = [f"**{title}**", "", f"| {first} | " + " | ".join(heads) + " |", "| --- |" + " ---: |" * len(heads)]
        for lab, asym, v, show_n in rows:
            lab = lab.strip()
            n = str(v["n"]) if show_n else "-"
            out.append(f"| {'**' + lab + '**' if asym else lab} | {n} | " + " | ".join(_pct(v[k]) for k in keys) + " |")
        return "\n".join(out)
    labels = [f"{lab} *" if asym else lab for lab, asym, _, _ in rows]
    w0 = max(len(x) for x in labels + [first])
    ws = [max(6, len(h)) for h in heads]
    out = [title, first.ljust(w0) + "".join("  " + h.rjust(w) for h, w in zip(heads, ws))]
    for lab, (_, _, v, show_n) in zip(labels, rows):
        n = str(v["n"]) if show_n else "-"
        out.append(lab.ljust(w0) + "  " + n.rjust(ws[0]) +
                   "".join("  " + _pct(v[k]).rjust(w) for k, w in zip(keys, ws[1:])))
    return "\n".join(out)


def metrics_table(ev: Evaluation, markdown: bool = False) -> str:
    """Every metric computed for one method: objects, mean, all (percent; n = targets)."""
    s = ev.summary()
    rows = [(f"{int(k):>2} {object_name(int(k), [ev])}", not ev.objects[int(k)].symmetric, v, True)
            for k, v in s["objects"].items()]
    rows.append((f"mean ({counted(s['mean']['n'], 'object')})", False, s["mean"], False))
    rows.append(("all", False, s["all"], True))
    return _table(f"{ev.method}: all metrics (%)", "object", rows, _keys(ev), markdown)


def scenes_table(ev: Evaluation, markdown: bool = False) -> str:
    """Every metric computed for one method, per scene (pooled over the scene's targets), and all."""
    s = ev.summary()
    labels = getattr(ev, "scene_labels", {}) or {}
    rows = [(f"{int(k):>2} {labels.get(int(k), '')}".rstrip(), False, v, True) for k, v in s["scenes"].items()]
    rows.append(("all", False, s["all"], True))
    return _table(f"{ev.method}: per scene (%)", "scene", rows, _keys(ev), markdown)


def _main_tables(evals: Sequence[Evaluation]) -> list[str]:
    have = set(_keys(evals[0])) if evals else set()
    return [k for k in ("add_s", "proj2d", "ar") if k in have]


def report_text(evals: Sequence[Evaluation]) -> str:
    parts: list[str] = []
    for k in _main_tables(evals):
        parts += ([""] if parts else []) + [table_text(evals, k)]
    for ev in evals:
        parts += ["", metrics_table(ev), "", scenes_table(ev)]
    return "\n".join(parts).lstrip("\n")


def report_markdown(evals: Sequence[Evaluation]) -> str:
    parts: list[str] = []
    for k in _main_tables(evals):
        parts += ([""] if parts else []) + [table_markdown(evals, k)]
    for ev in evals:
        parts += ["", metrics_table(ev, markdown=True), "", scenes_table(ev, markdown=True)]
    return "\n".join(parts).lstrip("\n") + "\n"


# ---------------------------------------------------------------------------------------------
# plots
# ---------------------------------------------------------------------------------------------
def accuracy_curve(errors: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Fraction of ``errors`` strictly below each threshold."""
    e = np.sort(np.asarray(errors, dtype=np.float64))
    if len(e) == 0:
        return np.zeros(len(thresholds))
    return np.searchsorted(e, thresholds, side="left") / len(e)


def write_plots(evals: Sequence[Evaluation], out_dir: str | Path) -> list[Path]:
    """Accuracy against threshold, one line per method, pooled over all targets:
    ADD(S) against % of the diameter (0-100), ADD-S against mm (0-100: the area under it is the
    AUC), 2D projection against px (0-20), and the BOP recalls at their thresholds
    (``recall_bop.png``), each where computed. PNG files in ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tdof20.formats.io import atomic_write_bytes

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = method_names(evals)
    have = set(_keys(evals[0])) if evals else set()
    specs = []
    if "add_s" in have:
        specs += [
            ("accuracy_add_s.png", "ADD(S) accuracy", "threshold (% of the object diameter)", np.linspace(0, 100, 401),
             lambda o: 100 * o.add_s / o.diameter, 100 * ADD_THRESHOLD),
            ("accuracy_adds_mm.png", "ADD-S accuracy (area = AUC)", "threshold (mm)", np.linspace(0, AUC_MAX, 401),
             lambda o: o.adds, None)]
    if "proj2d" in have:
        px = [getattr(e, "proj_px", None) for e in evals]
        mark = px[0] if px and isinstance(px[0], float) and all(p == px[0] for p in px) else None
        specs.append(("accuracy_proj2d.png", "2D projection accuracy", "threshold (px)", np.linspace(0, 20, 401),
                      lambda o: o.proj, mark))
    paths = []
    import io

    bop = [k for k in ("vsd", "mssd", "mspd") if f"ar_{k}" in have]
    if bop:  # recall at each BOP threshold (VSD: averaged over the taus), pooled over all targets
        xs = {"vsd": M.VSD_THRESHOLDS, "mssd": M.MSSD_THRESHOLDS, "mspd": M.MSPD_THRESHOLDS}
        xl = {"vsd": "VSD threshold (recall averaged over the 10 taus)",
              "mssd": "MSSD threshold (fraction of the diameter)",
              "mspd": "MSPD threshold (px at width 640)"}
        fig, axes = plt.subplots(1, len(bop), figsize=(4.2 * len(bop), 3.6), dpi=110, squeeze=False)
        for ax, k in zip(axes[0], bop):
            for ev, name in zip(evals, names):
                oks = [o.bop[k].reshape(len(o.bop[k]), -1, len(xs[k])) for o in ev.objects.values() if k in o.bop]
                ok = np.concatenate(oks) if oks else np.zeros((0, 1, len(xs[k])), bool)
                rec = ok.mean(axis=(0, 1)) if len(ok) else np.zeros(len(xs[k]))
                ax.plot(xs[k], 100 * rec, marker="o", ms=3, label=f"{name} (AR {100 * rec.mean():.1f})")
            ax.set_ylim(0, 100)
            ax.set_xlabel(xl[k])
            ax.set_ylabel("recall (%)")
            ax.set_title(f"{k.upper()} recall (mean = AR_{k.upper()})")
            ax.grid(alpha=0.3)
            ax.legend(loc="lower right", fontsize=8)
        buf = io.BytesIO()
        fig.tight_layout()
        fig.savefig(buf, format="png")
        plt.close(fig)
        atomic_write_bytes(out / "recall_bop.png", buf.getvalue())
        paths.append(out / "recall_bop.png")

    for fname, title, xlabel, x, err, mark in specs:
        fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
        for ev, name in zip(evals, names):
            e = np.concatenate([err(o) for o in ev.objects.values()]) if ev.objects else np.zeros(0)
            ax.plot(x, 100 * accuracy_curve(e, x), label=name, lw=1.6)
        if mark is not None:
            ax.axvline(mark, color="0.5", ls="--", lw=1)
        ax.set_xlim(x[0], x[-1])
        ax.set_ylim(0, 100)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("accuracy (%)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right")
        buf = io.BytesIO()
        fig.tight_layout()
        fig.savefig(buf, format="png")
        plt.close(fig)
        atomic_write_bytes(out / fname, buf.getvalue())
        paths.append(out / fname)
    return paths


__all__ = ["object_name", "method_names", "table_text", "table_markdown", "metrics_table", "scenes_table",
           "report_text", "report_markdown", "accuracy_curve", "write_plots"]
