"""Static clutter near the turntable (issue 25): frames labelled, wrong labels and accuracy of
`tdof20 annotate` on simulated sessions with the lab's clutter presets, with and without the
moving-points test that keeps what does not turn out of the object clusters
(`reconstruct.static_max_agree = 0` turns it off).

    python benchmarks/annotate_clutter.py --out /tmp/clutter [--off]

Each case: 1 arm position x 24 steps of 15 deg at 320x240 (the table in docs/annotate.md)."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.label import LabelConfig
from tdof20.annotate.pipeline import annotate
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import read_json

CASES = [("multi/08", ("cabinet_near", "box_near"), "cw"),
         ("multi/08", ("cabinet", "monitor", "box", "wall"), "ccw"),
         ("multi/02", ("cabinet_near",), "ccw"),
         ("multi/11", ("cabinet_near", "monitor", "box_near", "wall"), "cw")]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--off", action="store_true", help="also run with the moving-points test off")
    a = ap.parse_args()
    cfg = AnnotateConfig(label=LabelConfig(workers=1))
    variants = [("on", cfg)]
    if a.off:
        variants.append(("off", dataclasses.replace(cfg, reconstruct=dataclasses.replace(cfg.reconstruct,
                                                                                          static_max_agree=0.0))))
    print("| scene | clutter | direction | test | frames labelled | wrong labels | surface mm (median) | visible IoU (median) |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: | ---: |")
    for scene, clutter, direction in CASES:
        raw = a.out / f"{scene.replace('/', '_')}_{'-'.join(clutter)}_{direction}"
        if not (raw / "session.json").exists():
            run_capture(sim_config(scene, steps=24, step_deg=15.0, n_arms=1, width=320, height=240,
                                   clutter=clutter, direction=direction), raw, yes=True, show_progress=False)
        for name, c in variants:
            out = raw.with_name(raw.name + f"_scene_{name}")
            try:
                annotate(raw, out, models_dir=raw / "truth" / "models", cfg=c, progress=False, force=True)
                ev = read_json(out / "work" / "evaluation.json")
                al = ev["all"]
                row = (f"{ev['n_labelled_frames']}/24 | {len(ev['wrong_labels'])} | {al['surface_mm']['median']:.3f} | "
                       f"{al['iou_visib']['median']:.3f}")
            except TdofError as e:
                row = f"0/24 (refused: {str(e).split(':')[-2].strip()[:60]}) | 0 | - | -"
            print(f"| {scene} | {','.join(clutter)} | {direction} | {name} | {row} |", flush=True)


if __name__ == "__main__":
    main()
