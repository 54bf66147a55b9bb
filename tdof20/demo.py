"""``tdof20 demo``: the main job end to end on the simulator.

Today the chain is: a simulated capture session (both phases, with exact truth) and its contact
sheet. Later stages (annotate, dataset, train, predict, score) join as they land.
"""

from __future__ import annotations

import time
from pathlib import Path

from tdof20.formats import write_png
from tdof20.progress import console
from tdof20.sim.session import SimSessionConfig, simulate_session
from tdof20.viz import session_contact_sheet


def run_demo(out: str | Path, scene: str = "multi/08", steps: int = 8, step_deg: float = 45.0, n_arms: int = 4,
             width: int = 640, height: int = 480, seed: int = 0) -> dict:
    """Run the demo into ``out``; returns the paths it wrote and the time each stage took."""
    out = Path(out)
    timings = {}
    cfg = SimSessionConfig(scene_id=scene, steps=steps, step_deg=step_deg, n_arms=n_arms, width=width,
                           height=height, seed=seed).validate()
    console.rule("[bold]tdof20 demo")
    t0 = time.perf_counter()
    session = simulate_session(cfg, out / "raw" / scene.replace("/", "_"))
    timings["capture"] = time.perf_counter() - t0
    sheet = out / "contact_sheet.png"
    write_png(sheet, session_contact_sheet(session, n_frames=min(6, n_arms * steps)))
    n = len(cfg.phases) * n_arms * steps
    console.print(f"capture (simulated): {n} RGB-D frames of {scene} in {timings['capture']:.1f} s -> {session}")
    console.print(f"contact sheet: {sheet}")
    return {"session": session, "contact_sheet": sheet, "timings": timings}
