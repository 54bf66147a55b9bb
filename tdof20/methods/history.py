"""A training's loss history drawn: loss curves (the total and every part the method's loss
reports) and the learning rate, as RUN/loss.png."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

#: history keys that are not losses
NOT_LOSSES = ("step", "epoch", "lr")

#: at most this many bins of steps are drawn per curve (the figure is 800 pixels wide): a longer
#: history's raw curve is drawn as each bin's lowest and highest value, its moving average at the
#: bins' ends, so a 100,000-step run costs what a 2,000-step one does and looks the same
MAX_BINS = 1000


def _moving_average(y: np.ndarray, w: int) -> np.ndarray:
    """Mean of each ``w`` consecutive values (len(y) - w + 1 of them; np.convolve's 'valid'), in
    O(n) by a cumulative sum rather than O(n w)."""
    c = np.concatenate([[0.0], np.cumsum(y)])
    return (c[w:] - c[:-w]) / w


def _envelope(x: np.ndarray, y: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) with at most 2 ``bins`` points: each bin's first step with its lowest value and its
    last step with its highest (NaN where a bin holds none), the band a line through every point
    would fill at the figure's resolution; (x, y) themselves when they are short enough."""
    if len(x) <= 2 * bins:
        return x, y
    starts = np.linspace(0, len(x), bins, endpoint=False).astype(int)
    ends = np.append(starts[1:], len(x)) - 1
    lo, hi = np.fmin.reduceat(y, starts), np.fmax.reduceat(y, starts)  # fmin/fmax skip NaN
    return np.column_stack([x[starts], x[ends]]).ravel(), np.column_stack([lo, hi]).ravel()


def _every(x: np.ndarray, bins: int) -> np.ndarray:
    """About ``bins`` evenly spread indices of ``x`` (all where it is shorter), the last included."""
    if len(x) <= bins:
        return np.arange(len(x))
    return np.unique(np.append(np.linspace(0, len(x) - 1, bins).astype(int), len(x) - 1))


_FIGURE: list = []  # (figure, loss axes, learning-rate axes), made on the first call
_LOCK = threading.Lock()  # one picture at a time in the shared figure


def _figure():
    """The figure loss.png is drawn in: made once per process and reused (its axes, ticks and
    text objects are most of a small picture's cost), each call replacing the curves."""
    if not _FIGURE:
        # heavy: imported when a picture is first drawn
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(8, 4.5), dpi=100)
        FigureCanvasAgg(fig)
        fig.subplots_adjust(left=0.085, right=0.885, bottom=0.115, top=0.925)
        ax = fig.add_subplot()
        ax.set_yscale("log")
        ax.set_xlabel("optimiser step")
        ax.set_ylabel("loss")
        ax.grid(alpha=0.3, which="both")
        ax2 = ax.twinx()
        ax2.set_ylabel("learning rate")
        _FIGURE.extend([fig, ax, ax2])
    return _FIGURE


def plot_losses(history: list[dict], path: Path, title: str = "training") -> Path:
    """Loss curves (total and every part the method's loss reports, per step, with a moving
    average over a fiftieth of the history) and the learning rate, as a PNG (written to a
    temporary file, then renamed: a reader never sees half a picture).

    Drawn with matplotlib's Agg canvas on one figure per process (no pyplot), with fixed margins
    (tight_layout laid the figure out, and so drew every tick label, twice); long histories are
    thinned to :data:`MAX_BINS` bins of steps (:func:`_envelope`)."""
    steps = np.array([h["step"] for h in history], dtype=float)
    w = max(1, len(history) // 50)
    keys = ["loss"] + sorted({k for h in history for k in h} - {"loss", *NOT_LOSSES})
    names = {"loss": "total", "seg": "segmentation", "vec": "vector field (L1)"}
    with _LOCK:
        fig, ax, ax2 = _figure()
        for line in [*ax.lines, *ax2.lines]:
            line.remove()
        for i, key in enumerate(keys):
            y = np.array([h.get(key, np.nan) for h in history], dtype=float)
            y = np.where(y > 0, y, np.nan)  # a log axis: parts that are 0 or negative are not drawn
            if not np.isfinite(y).any():
                continue
            colour = "black" if key == "loss" else f"C{i - 1}"
            ax.plot(*_envelope(steps, y, MAX_BINS), color=colour, alpha=0.25, lw=0.8)
            if len(y) >= w:
                ys = _moving_average(np.nan_to_num(y, nan=np.nanmean(y)), w)
                keep = _every(ys, 2 * MAX_BINS)
                ax.plot(steps[w - 1:][keep], ys[keep], color=colour, lw=1.6, label=names.get(key, key))
        lr = np.array([h["lr"] for h in history], dtype=float)
        keep = _every(lr, 2 * MAX_BINS)  # a schedule: smooth, its points at the bins' ends draw it
        ax2.plot(steps[keep], lr[keep], color="tab:green", lw=1, ls="--", label="learning rate")
        for a in (ax, ax2):
            a.relim()
            a.autoscale_view()
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
        ax.set_title(title)
        tmp = path.with_name(f".{path.stem}.tmp.png")
        try:
            fig.savefig(tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    return path
