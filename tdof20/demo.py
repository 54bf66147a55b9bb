"""``tdof20 demo``: the main job end to end on the simulator.

Today the chain is: capture (simulated sessions of both phases, with exact truth) → labels (the
simulator's oracle labels, until the annotation pipeline lands) → dataset (BOP layout, the two
protocols, an HDF5 shard) → a contact sheet. Later stages (train, predict, score) join as they land.
"""

from __future__ import annotations

import time
from pathlib import Path

from tdof20.benchmark.dataset import build_dataset, pack
from tdof20.capture import run_capture, sim_config
from tdof20.formats import write_png
from tdof20.progress import console
from tdof20.sim.truth import oracle_scene
from tdof20.viz import session_contact_sheet


def run_demo(out: str | Path, scenes: tuple[str, ...] = ("single/03", "multi/08"), steps: int = 8,
             step_deg: float = 45.0, n_arms: int = 4, width: int = 640, height: int = 480, seed: int = 0) -> dict:
    """Run the demo into ``out``; returns the paths it wrote and the time each stage took."""
    out = Path(out)
    timings: dict[str, float] = {}
    console.rule("[bold]tdof20 demo")
    labelled = []
    t0 = time.perf_counter()
    for scene in scenes:
        cfg = sim_config(scene, steps=steps, step_deg=step_deg, n_arms=n_arms, width=width, height=height, seed=seed)
        session = out / "raw" / scene.replace("/", "_")
        run_capture(cfg, session, yes=True,
                    resume_command=f"tdof20 demo --out {out} (the same options)")
        labelled.append((scene, session))
    timings["capture"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene_dirs = [oracle_scene(s, out / "labels" / name.replace("/", "_")) for name, s in labelled]
    timings["labels"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    root = out / "dataset"
    st = build_dataset(scene_dirs, root)
    shard = pack(root, "hard", "test", out / "shards" / "hard_test.h5")
    timings["dataset"] = time.perf_counter() - t0
    sheet = out / "contact_sheet.png"
    write_png(sheet, session_contact_sheet(labelled[-1][1], n_frames=min(6, n_arms * steps)))
    n = 2 * len(scenes) * n_arms * steps
    console.print(f"capture (simulated): {n} RGB-D frames of {', '.join(scenes)} in {timings['capture']:.1f} s -> {out / 'raw'}")
    console.print(f"labels (simulator truth): {len(scene_dirs)} scenes in {timings['labels']:.1f} s -> {out / 'labels'}")
    console.print(f"dataset: {st['images']} images, hard split {st['splits']['hard_train']} train / "
                  f"{st['splits']['hard_test']} test, shard {shard} ({timings['dataset']:.1f} s)")
    console.print(f"contact sheet: {sheet}")
    return {"sessions": [s for _, s in labelled], "dataset": root, "shard": shard, "contact_sheet": sheet,
            "timings": timings}
