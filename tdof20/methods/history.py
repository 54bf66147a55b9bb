"""A training's loss history drawn: loss curves (the total and every part the method's loss
reports) and the learning rate, as RUN/loss.png."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: history keys that are not losses
NOT_LOSSES = ("step", "epoch", "lr")


def plot_losses(history: list[dict], path: Path, title: str = "training") -> Path:
    """Loss curves (total and every part the method's loss reports, per step, with a moving
    average) and the learning rate, as a PNG."""
    import matplotlib  # the Agg backend is chosen before pyplot loads (as the tables and reports do)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([h["step"] for h in history])
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    w = max(1, len(history) // 50)
    keys = ["loss"] + sorted({k for h in history for k in h} - {"loss", *NOT_LOSSES})
    names = {"loss": "total", "seg": "segmentation", "vec": "vector field (L1)"}
    for i, key in enumerate(keys):
        y = np.array([h.get(key, np.nan) for h in history], dtype=float)
        y = np.where(y > 0, y, np.nan)  # a log axis: parts that are 0 or negative are not drawn
        if not np.isfinite(y).any():
            continue
        colour = "black" if key == "loss" else f"C{i - 1}"
        ax.plot(steps, y, color=colour, alpha=0.25, lw=0.8)
        if len(y) >= w:
            ys = np.convolve(np.nan_to_num(y, nan=np.nanmean(y)), np.ones(w) / w, mode="valid")
            ax.plot(steps[w - 1:], ys, color=colour, lw=1.6, label=names.get(key, key))
    ax.set_yscale("log")
    ax.set_xlabel("optimiser step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3, which="both")
    ax2 = ax.twinx()
    ax2.plot(steps, [h["lr"] for h in history], color="tab:green", lw=1, ls="--", label="learning rate")
    ax2.set_ylabel("learning rate")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path
