"""Label accuracy under a real sensor (issue 34): `tdof20 annotate` on simulated sessions whose
camera reads depth off in scale (`--depth-bias`), alone and with hand-eye error, against the
simulator's truth; the depth-scale estimate beside each row.

    python benchmarks/annotate_real_errors.py --out /tmp/real_errors [--uncorrected]

Each case: 4 arm positions x 12 steps of 30 deg at 240x180 unless the case says otherwise (the
table in docs/annotate.md, "A depth camera off in scale"). `--uncorrected` adds each case with
`register.depth_scale_correct = false` (what annotation gave before it measured the scale).
A case already annotated under --out is read back, not run again."""
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

# (name, scene, arm positions, depth bias, hand-eye error mm, deg)
CASES = [("b102", "multi/08", 4, 1.02, 0.0, 0.0),
         ("b100_he", "multi/08", 4, 1.00, 2.0, 0.5),
         ("b103_he", "multi/08", 4, 1.03, 2.0, 0.5),
         ("b097", "multi/08", 4, 0.97, 0.0, 0.0),
         ("b102_2arms", "multi/08", 2, 1.02, 0.0, 0.0),
         ("b102_single", "single/handle_cup_440", 4, 1.02, 0.0, 0.0)]


def _row(name: str, scene_dir: Path, bias: float, lab: str, variant: str) -> str:
    ev = read_json(scene_dir / "work" / "evaluation.json")
    ds = read_json(scene_dir / "work" / "registration.json").get("depth_scale") or {}
    est = (f"{ds['measured']:.4f} ± {ds['ci95']:.4f}" if ds.get("arms") else "not estimated")
    a = ev["all"]
    return (f"| {name} ({variant}) | {bias:g} | {lab} | {est} | {a['surface_mm']['median']:.3f} | "
            f"{a['iou_visib']['median']:.3f} | {a['motion_trans_mm']['median']:.3f} | {ev['n_labelled_frames']} | "
            f"{len(ev['wrong_labels'])} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--uncorrected", action="store_true", help="also run each case without the correction")
    a = ap.parse_args()
    cfg = AnnotateConfig(label=LabelConfig(workers=1))
    variants = [("corrected", cfg)]
    if a.uncorrected:
        variants.append(("uncorrected", dataclasses.replace(cfg, register=dataclasses.replace(
            cfg.register, depth_scale_correct=False))))
    print("| case | depth bias | lab | estimate ± 95 % | surface mm (median) | visible IoU (median) | "
          "motion mm (median) | frames labelled | wrong labels |")
    print("| --- | ---: | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for name, scene, arms, bias, he_mm, he_deg in CASES:
        raw = a.out / name / "raw"
        if not (raw / "truth").exists():
            run_capture(sim_config(scene, steps=12, step_deg=30.0, n_arms=arms, width=240, height=180, seed=1,
                                   depth_bias=bias, hand_eye_error_mm=he_mm, hand_eye_error_deg=he_deg),
                        raw, yes=True, show_progress=False)
        lab = f"hand-eye {he_mm:g} mm / {he_deg:g} deg" if he_mm or he_deg else "-"
        for variant, c in variants:
            out = a.out / name / variant
            try:
                if not (out / "work" / "evaluation.json").exists():
                    annotate(raw, out, models_dir=raw / "truth" / "models", cfg=c, progress=False)
                print(_row(name, out, bias, lab, variant), flush=True)
            except TdofError as e:
                print(f"| {name} ({variant}) | {bias:g} | {lab} | refused: {e} | | | | | |", flush=True)


if __name__ == "__main__":
    main()
