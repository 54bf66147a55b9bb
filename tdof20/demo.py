"""``tdof20 demo``: the main job end to end on the simulator.

Today the chain is: capture (a simulated session of both phases, with exact truth) and its
contact sheet. Later stages (annotate, dataset, train, predict, score) join as they land.
"""

from __future__ import annotations

import time
from pathlib import Path

from tdof20.capture import run_capture, sim_config
from tdof20.formats import write_png
from tdof20.progress import console
from tdof20.viz import session_contact_sheet


def run_demo(out: str | Path, scene: str = "multi/08", steps: int = 8, step_deg: float = 45.0, n_arms: int = 4,
             width: int = 640, height: int = 480, seed: int = 0) -> dict:
    """Run the demo into ``out``; returns the paths it wrote and the time each stage took."""
    out = Path(out)
    timings = {}
    cfg = sim_config(scene, steps=steps, step_deg=step_deg, n_arms=n_arms, width=width, height=height, seed=seed)
    console.rule("[bold]tdof20 demo")
    session = out / "raw" / scene.replace("/", "_")
    t0 = time.perf_counter()
    summary = run_capture(cfg, session, yes=True,
                          resume_command=f"tdof20 demo --out {out} --scene {scene} --steps {steps} "
                                         f"--step-deg {step_deg:g} --arm-positions {n_arms} --width {width} "
                                         f"--height {height} --seed {seed}")
    timings["capture"] = time.perf_counter() - t0
    sheet = out / "contact_sheet.png"
    write_png(sheet, session_contact_sheet(session, n_frames=min(6, n_arms * steps)))
    console.print(f"capture (simulated): {summary.planned} RGB-D frames of {scene} "
                  f"({summary.captured} new) in {timings['capture']:.1f} s -> {session}")
    console.print(f"contact sheet: {sheet}")
    return {"session": session, "contact_sheet": sheet, "timings": timings}
