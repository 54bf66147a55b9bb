"""Reports of scored results: the paper's Tables 1-2 (text and Markdown) and accuracy curves.

Layout as in the paper: one row per object (catalog name for ids 1-20; asymmetric objects marked
``*`` in text and **bold** in Markdown, since their ADD(S) is the stricter ADD), one column per
method, then the mean over objects and the accuracy pooled over all targets. Table 1 is ADD(S)
accuracy (< 10% of the diameter), Table 2 the 2D projection accuracy (< 5 px); with several
methods the best value of each row is bold in Markdown. :func:`metrics_table` lists every metric
of one method.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from tdof20.benchmark.scoring import ADD_THRESHOLD, AUC_MAX, PROJ_THRESHOLD, Evaluation

TABLES = {
    "add_s": f"Table 1 - ADD(S) accuracy (%): mean model-point distance < {ADD_THRESHOLD:.0%} of the diameter "
             f"(closest point for symmetric objects)",
    "proj2d": f"Table 2 - 2D projection accuracy (%): mean reprojection distance < {PROJ_THRESHOLD:g} px",
}
METRIC_LABELS = {"add": "ADD", "adds": "ADD-S", "add_s": "ADD(S)", "proj2d": "2D proj", "auc_adds": "AUC ADD-S",
                 "auc_add_s": "AUC ADD(S)"}


def object_name(obj_id: int) -> str:
    """The catalog name of ids 1-20 (tdof20.objects), else 'obj_<id>'."""
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
        rows.append((f"{i:>2} {object_name(i)}", not sym.get(i, True), vals))  # text pads ids; markdown strips
    n_obj = max((s["mean"]["n"] for s in sums), default=0)
    n_all = max((s["all"]["n"] for s in sums), default=0)
    rows.append((f"mean ({n_obj} objects)", False, [s["mean"][key] for s in sums]))
    rows.append((f"all ({n_all} targets)", False, [s["all"][key] for s in sums]))
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
    out = [title or TABLES.get(key, METRIC_LABELS.get(key, key))]
    out.append("object".ljust(w0) + "".join("  " + n.rjust(w) for n, w in zip(names, ws)))
    out.append("-" * (w0 + sum(w + 2 for w in ws)))
    for k, (lab, (_, _, vals)) in enumerate(zip(labels, rows)):
        if k == len(rows) - 2:
            out.append("-" * (w0 + sum(w + 2 for w in ws)))
        out.append(lab.ljust(w0) + "".join("  " + _pct(v).rjust(w) for v, w in zip(vals, ws)))
    out.append("* asymmetric object: ADD(S) is ADD; the others are symmetric: ADD(S) is ADD-S")
    return "\n".join(out)


def table_markdown(evals: Sequence[Evaluation], key: str = "add_s", title: str | None = None) -> str:
    """Markdown table of ``key``: asymmetric objects bold (as in the paper), and with several
    methods the best value of each row bold."""
    rows, _ = _rows(evals, key)
    names = method_names(evals)
    out = [f"**{title or TABLES.get(key, METRIC_LABELS.get(key, key))}**", "",
           "| object | " + " | ".join(names) + " |", "| --- |" + " ---: |" * len(names)]
    for lab, asym, vals in rows:
        finite = [v for v in vals if v is not None]
        best = max(finite) if finite and len(names) > 1 else None
        cells = [("-" if v is None else (f"**{_pct(v)}**" if best is not None and v == best else _pct(v)))
                 for v in vals]
        lab = lab.strip()
        out.append(f"| {'**' + lab + '**' if asym else lab} | " + " | ".join(cells) + " |")
    out += ["", "Bold objects are asymmetric (ADD(S) = ADD); the others are symmetric (ADD(S) = ADD-S)."]
    return "\n".join(out)


def metrics_table(ev: Evaluation, markdown: bool = False) -> str:
    """Every metric of one method: objects, mean, all (percent; n = targets)."""
    s = ev.summary()
    keys = ["add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s"]
    rows = [(f"{int(k):>2} {object_name(int(k))}", not ev.objects[int(k)].symmetric, v)
            for k, v in s["objects"].items()]
    rows.append((f"mean ({s['mean']['n']} objects)", False, s["mean"]))
    rows.append(("all", False, s["all"]))
    heads = ["n"] + [METRIC_LABELS[k] for k in keys]
    if markdown:
        out = [f"**{ev.method}: all metrics (%)**", "", "| object | " + " | ".join(heads) + " |",
               "| --- |" + " ---: |" * len(heads)]
        for lab, asym, v in rows:
            lab = lab.strip()
            n = str(v["n"]) if "mean" not in lab else "-"
            out.append(f"| {'**' + lab + '**' if asym else lab} | {n} | " + " | ".join(_pct(v[k]) for k in keys) + " |")
        return "\n".join(out)
    labels = [f"{lab} *" if asym else lab for lab, asym, _ in rows]
    w0 = max(len(x) for x in labels + ["object"])
    ws = [max(6, len(h)) for h in heads]
    out = [f"{ev.method}: all metrics (%)",
           "object".ljust(w0) + "".join("  " + h.rjust(w) for h, w in zip(heads, ws))]
    for lab, (_, _, v) in zip(labels, rows):
        n = str(v["n"]) if not lab.startswith("mean") else "-"
        out.append(lab.ljust(w0) + "  " + n.rjust(ws[0]) +
                   "".join("  " + _pct(v[k]).rjust(w) for k, w in zip(keys, ws[1:])))
    return "\n".join(out)


def report_text(evals: Sequence[Evaluation]) -> str:
    parts = [table_text(evals, "add_s"), "", table_text(evals, "proj2d")]
    for ev in evals:
        parts += ["", metrics_table(ev)]
    return "\n".join(parts)


def report_markdown(evals: Sequence[Evaluation]) -> str:
    parts = [table_markdown(evals, "add_s"), "", table_markdown(evals, "proj2d")]
    for ev in evals:
        parts += ["", metrics_table(ev, markdown=True)]
    return "\n".join(parts) + "\n"


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
    AUC), 2D projection against px (0-20). PNG files in ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tdof20.formats.io import atomic_write_bytes

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = method_names(evals)
    specs = [
        ("accuracy_add_s.png", "ADD(S) accuracy", "threshold (% of the object diameter)", np.linspace(0, 100, 401),
         lambda o: 100 * o.add_s / o.diameter, 100 * ADD_THRESHOLD),
        ("accuracy_adds_mm.png", "ADD-S accuracy (area = AUC)", "threshold (mm)", np.linspace(0, AUC_MAX, 401),
         lambda o: o.adds, None),
        ("accuracy_proj2d.png", "2D projection accuracy", "threshold (px)", np.linspace(0, 20, 401),
         lambda o: o.proj, PROJ_THRESHOLD),
    ]
    paths = []
    import io

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


__all__ = ["object_name", "method_names", "table_text", "table_markdown", "metrics_table", "report_text",
           "report_markdown", "accuracy_curve", "write_plots"]
