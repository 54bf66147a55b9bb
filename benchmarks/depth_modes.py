"""The depth question (issue 6, item 2; issue 15 parts 3-4): how should pixels without depth take
part, and which vector targets make the paper's 3D voting work? Chosen on VALIDATION, never test.

Builds a small simulated dataset (oracle labels), trains HFF6DoF briefly on the simple split's
train part minus its validation part (``train(part="train-val")``) once per run ``MODE:ORIGIN``
(input depth 'raw' with holes, 'filled', or 'restored' = the privileged upper bound; vector
targets from the 'restored' true surface points or from the 'observed' input-depth points),
predicts the validation images (``--part val``; ``--part test`` only to report a final choice)
with each pose recovery ('3d' voting from the pixels with depth + least squares; 'bearing' voting
from every object pixel + PnP), and scores ADD(S), 2D projection and the AUC against the
validation targets. It also separates the formulation from the network by voting with the
*ground-truth* vector field of each origin (an oracle: vectors perfect, no training).
Resumable (runs and datasets are kept in --out).

    python benchmarks/depth_modes.py --out /tmp/depth_modes [--epochs 25] \
        [--runs raw:restored filled:restored restored:restored filled:observed]

Prints a Markdown table and writes OUT/depth_modes.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from tdof20.dataset.build import build_dataset
from tdof20.scoring.scoring import score
from tdof20.dataset.validation import part_images, write_val_targets
from tdof20.capture import run_capture, sim_config
from tdof20.methods.data import DEPTH_MODES, SceneImages, keypoints_from_json
from tdof20.methods.hff6dof_data import VECTOR_ORIGINS, HFFTransform, keypoint_table
from tdof20.methods.hff6dof_pose import VOTING, recover_poses
from tdof20.methods.predict import predict_rows, segmentation_iou
from tdof20.methods.runs import load_run, run_classes
from tdof20.methods.train import train
from tdof20.sim.truth import oracle_scene


def make_dataset(out: Path, scenes: list[str], steps: int, step_deg: float, n_arms: int, width: int,
                 height: int) -> Path:
    root = out / "dataset"
    if (root / "dataset_info.json").exists():
        return root
    dirs = []
    for sc in scenes:
        raw = out / "raw" / sc.replace("/", "_")
        if not (raw / "truth" / "scene_gt.json").exists():
            run_capture(sim_config(sc, steps=steps, step_deg=step_deg, n_arms=n_arms, width=width, height=height),
                        raw, yes=True, show_progress=False)
        dirs.append(oracle_scene(raw, out / "labels" / sc.replace("/", "_"), show_progress=False))
    build_dataset(dirs, root, show_progress=False)
    return root


def oracle_vector_rows(run: Path, root: Path, split: str, voting: str, part: str = "val",
                       depth_mode: str | None = None, origin: str | None = None) -> list[tuple]:
    """Poses from the ground-truth vector field (of ``origin``, default the run's) and masks with
    the input depth (``depth_mode``, default the run's): the error of the formulation alone."""
    net, cfg = load_run(run, "cpu")
    classes = run_classes(cfg)  # class c -> object classes[c - 1]
    kt = keypoint_table(keypoints_from_json(cfg["keypoints"]), classes=classes)
    images = part_images(root, split, part)
    data = SceneImages(root, images, labels=True)
    origin = origin or cfg.get("method_config", {}).get("vector_origin", "restored")
    tf_in = HFFTransform(kt, cfg["image_size"], depth_mode or cfg["depth_mode"], targets=True, classes=classes,
                         vector_origin=origin)
    gen = torch.Generator().manual_seed(0)
    rows = []
    for i in range(len(data)):
        s = tf_in(data[i])
        lab = torch.where(s["mask"], s["seg"], torch.zeros_like(s["seg"]))  # the pixels with a target vector
        res = recover_poses(lab[None], s["vec"][None], s["depth"][None], s["K"][None], kt, 5,
                            generator=gen, voting=voting)[0]
        rows += [(s["scene_id"], s["im_id"], classes[r["obj_id"] - 1], r["score"], r["R"], r["t"], -1) for r in res]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenes", nargs="+", default=["single/15", "single/05", "single/12"])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--step-deg", type=float, default=2.0)
    ap.add_argument("--arms", type=int, default=4)
    ap.add_argument("--capture-size", type=int, nargs=2, default=[80, 60], metavar=("W", "H"))
    ap.add_argument("--image-size", type=int, nargs=2, default=[60, 80], metavar=("H", "W"))
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--max-steps", type=int, default=None, help="at most this many optimiser steps per run")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--runs", nargs="+", default=["raw:restored", "filled:restored", "restored:restored",
                                                 "filled:observed"],
                    help="trainings, each INPUT_DEPTH:VECTOR_ORIGIN")
    ap.add_argument("--voting", nargs="+", default=list(VOTING), choices=VOTING)
    ap.add_argument("--part", default="val", choices=["val", "test"],
                    help="where runs are compared (val; test only to report a choice made on val)")
    ap.add_argument("--seed", type=int, default=0, help="the trainings' seed (initial weights, batch order)")
    ap.add_argument("--device", default="auto")
    a = ap.parse_args()
    combos = []
    for r in a.runs:
        mode, _, origin = r.partition(":")
        if mode not in DEPTH_MODES or (origin or "restored") not in VECTOR_ORIGINS:
            ap.error(f"--runs {r}: INPUT_DEPTH ({', '.join(DEPTH_MODES)}):VECTOR_ORIGIN ({', '.join(VECTOR_ORIGINS)})")
        combos.append((mode, origin or "restored"))
    a.out.mkdir(parents=True, exist_ok=True)
    root = make_dataset(a.out, a.scenes, a.steps, a.step_deg, a.arms, *a.capture_size)
    train_part = "train-val" if a.part == "val" else "train"
    targets = write_val_targets(root, "simple") if a.part == "val" else None
    n_images = len(part_images(root, "simple", a.part))

    def scored(rows):
        return score(rows, root, targets=targets) if targets is not None else score(rows, root, split="simple")

    results: dict = {"options": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()},
                     "part": a.part, "images": n_images, "runs": {}}
    for mode, origin in combos:
        name = f"{mode}_{origin}" + (f"_seed{a.seed}" if a.seed else "")
        run = a.out / "runs" / name
        t0 = time.perf_counter()
        train(root, "simple", run, image_size=tuple(a.image_size), batch_size=a.batch_size, epochs=a.epochs,
              lr=a.lr, depth_mode=mode, method_config={"vector_origin": origin}, device=a.device, num_workers=1,
              progress=False, part=train_part, max_steps=a.max_steps, seed=a.seed)
        hist = json.loads((run / "history.json").read_text())
        entry = {"depth_mode": mode, "vector_origin": origin, "seed": a.seed,
                 "train_s": round(time.perf_counter() - t0, 1),
                 "epochs": hist["epochs"][-1] if hist["epochs"] else None,
                 "seg_iou": round(segmentation_iou(run, root, "simple", device=a.device,
                                                   images=part_images(root, "simple", a.part))["mean"], 4)}
        for voting in a.voting:
            rows, info = predict_rows(run, root, "simple", device=a.device, voting=voting, num_workers=0,
                                      progress=False, part=a.part)
            sc = scored(rows)
            oracle = scored(oracle_vector_rows(run, root, "simple", voting, a.part))
            entry[voting] = {"add_s": sc["mean"]["add_s"], "proj2d": sc["mean"]["proj2d"],
                             "auc_add_s": sc["mean"]["auc_add_s"], "pose_ms": info["pose_ms_per_image"],
                             "gt_vectors_add_s": oracle["mean"]["add_s"], "gt_vectors_proj2d": oracle["mean"]["proj2d"],
                             "gt_vectors_auc_add_s": oracle["mean"]["auc_add_s"]}
        results["runs"][name] = entry
        (a.out / "depth_modes.json").write_text(json.dumps(results, indent=2))
        print(json.dumps({name: entry}), flush=True)

    lines = [f"Simple split, {a.part} part ({n_images} images); trained on {train_part}.", "",
             "| input depth | vector origin | pose recovery | ADD(S) | 2D proj. | AUC ADD(S) | ADD(S) GT vectors "
             "| 2D proj. GT vectors | seg IoU |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, e in results["runs"].items():
        for voting in a.voting:
            v = e[voting]
            lines.append(f"| {e['depth_mode']} | {e['vector_origin']} | {voting} | {100 * v['add_s']:.1f} % | "
                         f"{100 * v['proj2d']:.1f} % | {100 * v['auc_add_s']:.1f} % | "
                         f"{100 * v['gt_vectors_add_s']:.1f} % | {100 * v['gt_vectors_proj2d']:.1f} % | "
                         f"{100 * e['seg_iou']:.1f} % |")
    print("\n".join(lines))
    results["table"] = lines
    (a.out / "depth_modes.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
