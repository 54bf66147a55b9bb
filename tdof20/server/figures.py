"""A scored submission's figures (accuracy curves, BOP recalls), drawn when first asked for.

Why lazily: drawing them with matplotlib takes seconds per submission, which a worker spent on
every job before recording its result; the queue drains faster when the worker only keeps what
the figures are drawn from, and a results page nobody opens costs nothing.

The worker writes :data:`FIGURE_DATA` (DATA/results/<uid>/figure_data.npz): each object's
per-target errors and BOP decisions as the scorer computed them (the arrays of
:class:`~tdof20.scoring.evaluation.ObjectEval`; errors, never a pose or a label). It lies in the
store, which no endpoint serves. The first request for the results page or one of its figures
draws the PNGs with the scoring package's :func:`~tdof20.scoring.report.write_plots` — the same
figures the worker drew before, curves pooled over all targets, so they show what the page already
tells — and caches them in the same folder with :data:`FIGURES`, the list of their names and
the key of the shown summary they were drawn from (:func:`drawn_from`): a result scored again (a
new scorer or dataset version, a held-back part's public part) is drawn anew, never an old figure.

Concurrent requests: in one process drawing is serialised by a lock (pyplot is not thread-safe)
and a request that waited finds the figures drawn; across processes (several servers sharing the
store) each draws into a temp folder of its own and renames each PNG into place, then writes the
list last, so a reader sees either no list or a list whose PNGs are whole.

What a test part's figure may show: no more than its numbers (:mod:`tdof20.server.disclosure`).
Accuracy curves drawn from the per-target errors step at each target's error, and a pooled curve
with one probe estimate shows that target's error exactly, whatever the tables round to. So the
curves are drawn only for a validation part (public labels); a test part gets
:data:`SHOWN_FIGURE`, its shown per-object values as bars, drawn from the disclosed result alone
(nothing else is read), so the PNG is a function of numbers the page already prints."""

from __future__ import annotations

import hashlib
import io
import json
import os
import sys
import tempfile
import threading
import zipfile
from pathlib import Path

import numpy as np

from tdof20.formats.io import atomic_write_bytes
from tdof20.scoring import report
from tdof20.scoring.evaluation import Evaluation, ObjectEval

FIGURE_DATA = "figure_data.npz"
FIGURES = "figures.json"
SHOWN_FIGURES = "figures_shown.json"  # the list of a test part's figures (drawn from disclosed values)
SHOWN_FIGURE = "shown_per_object.png"
SHOWN_METRICS = {"add_s": "ADD(S)", "proj2d": "2D projection", "auc_add_s": "AUC ADD(S)"}
ARRAYS = ("add", "adds", "proj", "add_ok", "adds_ok", "proj_ok", "adds_exact", "scene")
_DRAW = threading.Lock()


def save_figure_data(ev: Evaluation, folder: Path) -> Path:
    """Keep what ``ev``'s figures are drawn from in ``folder`` (atomically; replaces an older one)."""
    arrays: dict[str, np.ndarray] = {}
    objects = []
    for oid, o in ev.objects.items():
        objects.append({"obj_id": int(oid), "diameter": float(o.diameter), "symmetric": bool(o.symmetric),
                        "auc_se": float(o.auc_se), "keys": list(o.keys), "bop": sorted(o.bop)})
        for name in ARRAYS:
            arrays[f"o{int(oid)}_{name}"] = np.asarray(getattr(o, name))
        for k, v in o.bop.items():
            arrays[f"o{int(oid)}_bop_{k}"] = np.asarray(v)
    meta = {"keys": list(ev.keys), "proj_px": ev.proj_px, "objects": objects,
            "object_labels": {str(k): v for k, v in (ev.object_labels or {}).items()}}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    path = Path(folder) / FIGURE_DATA
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_figure_data(path: Path, method: str) -> Evaluation:
    """The :class:`Evaluation` (without warnings and timings) that :func:`save_figure_data` kept."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(z["meta"].tobytes())
        objects = {}
        for m in meta["objects"]:
            oid = m["obj_id"]
            a = {name: z[f"o{oid}_{name}"] for name in ARRAYS}
            objects[oid] = ObjectEval(oid, m["diameter"], m["symmetric"], a["add"], a["adds"], a["proj"], a["add_ok"],
                                      a["adds_ok"], a["proj_ok"], a["adds_exact"], auc_se=m["auc_se"], scene=a["scene"],
                                      bop={k: z[f"o{oid}_bop_{k}"] for k in m["bop"]}, keys=tuple(m["keys"]))
    # a '$' would start matplotlib's mathtext in the legend (and an odd one fail the drawing): escaped
    return Evaluation(method.replace("$", r"\$"), objects, [], {}, keys=tuple(meta["keys"]),
                      object_labels={int(k): v for k, v in meta["object_labels"].items()}, proj_px=meta["proj_px"])


def drawn_from(result: dict | None) -> str:
    """The key of what a submission's figures are drawn from: its shown summary (a result scored
    again, on a new scorer or dataset version or on a held-back part's public part, draws anew)."""
    summary = (result or {}).get("summary")
    return hashlib.sha256(json.dumps(summary, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _listed(folder: Path, listing: str = FIGURES, key: str | None = None) -> list[str] | None:
    """The names in the figure list when it was drawn from ``key`` and every PNG it names is there
    (a list from before keys, or of another key, is drawn again)."""
    try:
        got = json.loads((folder / listing).read_text())
    except (OSError, ValueError):
        return None
    names = got.get("names") if isinstance(got, dict) and got.get("key") == key else None
    if isinstance(names, list) and all(isinstance(n, str) and (folder / n).is_file() for n in names):
        return names
    return None


def _list(folder: Path, listing: str, names: list[str], key: str) -> None:
    atomic_write_bytes(folder / listing, json.dumps({"key": key, "names": names}).encode())


def figures(folder: Path, method: str, result: dict) -> list[str]:
    """The names of a scored submission's figures in ``folder`` (its results folder), drawing them
    first where they are not there yet. ``result`` is the result as shown
    (:func:`tdof20.server.disclosure.disclose`): a validation part's figures are the accuracy
    curves; any other's (a test part, or a result that does not say) the shown values' bars
    (:func:`shown_figures`). A validation result scored by a worker that drew its figures itself
    (tdof20 before lazy figures) lists them in ``result["plots"]``. [] when there is nothing to draw
    from or the drawing failed (logged; the page shows its tables without figures)."""
    folder = Path(folder)
    if ((result or {}).get("disclosure") or {}).get("part") != "val":
        return shown_figures(folder, method, result or {})
    key = drawn_from(result)
    names = _listed(folder, FIGURES, key)
    if names is not None:
        return names
    data = folder / FIGURE_DATA
    if not data.is_file():
        return [n for n in result.get("plots", []) if (folder / n).is_file()]
    with _DRAW:
        names = _listed(folder, FIGURES, key)  # drawn while this request waited
        if names is not None:
            return names
        try:
            ev = load_figure_data(data, method)
            with tempfile.TemporaryDirectory(prefix=".drawing-", dir=folder) as tmp:
                names = [p.name for p in report.write_plots([ev], tmp)]
                for n in names:
                    os.replace(Path(tmp) / n, folder / n)
            _list(folder, FIGURES, names, key)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
            print(f"server: figures of {folder.name}: {type(e).__name__}: {e}", file=sys.stderr)
            return []
    return names


def _draw_shown(method: str, summary: dict) -> bytes | None:
    """The PNG of the shown per-object values (None when no object's cell is shown)."""
    objs = [(o, c) for o, c in (summary.get("objects") or {}).items() if c.get("step") is not None]
    keys = [k for k in SHOWN_METRICS if any(c.get(k) is not None for _, c in objs)]
    if not objs or not keys:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 0.9 + 0.42 * len(objs) * len(keys) ** 0.5), dpi=110)
    h = 0.8 / len(keys)
    for j, k in enumerate(keys):
        ys = [i + (j - (len(keys) - 1) / 2) * h for i in range(len(objs))]
        vals = [100 * (c.get(k) or 0.0) for _, c in objs]
        err = [50 * c["step"] for _, c in objs]  # half a step each way: what the rounding leaves open
        ax.barh(ys, vals, height=h * 0.9, xerr=err, label=SHOWN_METRICS[k], capsize=2)
    ax.set_yticks(range(len(objs)), [summary.get("names", {}).get(o, o) for o, _ in objs])
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("accuracy (%), as shown: each to its step (bars: +- half a step)")
    ax.set_title(method[:60].replace("$", r"\$") + " - per object (test part)")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(loc="lower right", fontsize=8)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def shown_figures(folder: Path, method: str, result: dict) -> list[str]:
    """A test part's figures in ``folder``: :data:`SHOWN_FIGURE`, drawn (once, cached under
    :data:`SHOWN_FIGURES`) from ``result`` as disclosed and nothing else; [] when it shows no object."""
    folder = Path(folder)
    key = drawn_from(result)
    names = _listed(folder, SHOWN_FIGURES, key)
    if names is not None:
        return names
    summary = dict((result or {}).get("summary") or {})
    summary["names"] = (result or {}).get("object_names") or {}
    with _DRAW:
        names = _listed(folder, SHOWN_FIGURES, key)
        if names is not None:
            return names
        try:
            png = _draw_shown(method, summary)
            names = [] if png is None else [SHOWN_FIGURE]
            if png is not None:
                atomic_write_bytes(folder / SHOWN_FIGURE, png)
            if png is None:
                (folder / SHOWN_FIGURE).unlink(missing_ok=True)  # (one drawn from an earlier result)
            if folder.is_dir():
                _list(folder, SHOWN_FIGURES, names, key)
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"server: figures of {folder.name}: {type(e).__name__}: {e}", file=sys.stderr)
            return []
    return names


__all__ = ["FIGURES", "FIGURE_DATA", "SHOWN_FIGURE", "SHOWN_FIGURES", "drawn_from", "figures", "load_figure_data",
           "save_figure_data", "shown_figures"]
