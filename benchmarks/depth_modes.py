"""The depth question (issue 6, item 2): how should pixels without depth take part?

Builds a small simulated dataset (oracle labels), trains HFF6DoF briefly once per input depth mode
('raw' sensor depth with holes, 'filled' holes, 'restored' = the privileged upper bound), predicts
the simple split's test images with each pose recovery ('3d' voting from the pixels with depth +
Kabsch; 'bearing' voting from every object pixel + PnP), and scores ADD(S), 2D projection and the
AUC with the benchmark scorer. It also separates the two error sources by voting with the
*ground-truth* vector field (vectors perfect, only the depth matters). Everything is resumable
(runs and datasets are kept in --out).

    python benchmarks/depth_modes.py --out /tmp/depth_modes [--epochs 25] [--modes raw filled restored]

Prints a Markdown table and writes OUT/depth_modes.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from tdof20.benchmark.dataset import build_dataset, split_images
from tdof20.benchmark.scoring import score
from tdof20.capture import run_capture, sim_config
from tdof20.methods.data import DEPTH_MODES, HFFTransform, SceneImages, keypoint_table, keypoints_from_json
from tdof20.methods.predict import VOTING, predict_rows, recover_poses, segmentation_iou
from tdof20.methods.train import load_run, run_classes, train
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


def oracle_vector_rows(run: Path, root: Path, split: str, voting: str) -> list[tuple]:
    """Poses from the ground-truth vector field and masks with the run's input depth: the error
    that the depth alone causes."""
    net, cfg = load_run(run, "cpu")
    classes = run_classes(cfg)  # class c -> object classes[c - 1]
    kt = keypoint_table(keypoints_from_json(cfg["keypoints"]), classes=classes)
    images = split_images(root, split, "test")
    data = SceneImages(root, images, labels=True)
    tf_in = HFFTransform(kt, cfg["image_size"], cfg["depth_mode"], targets=True, classes=classes)
    gen = torch.Generator().manual_seed(0)
    rows = []
    for i in range(len(data)):
        s = tf_in(data[i])
        res = recover_poses(s["label"][None], s["vec"][None], s["depth"][None], s["K"][None], kt, 5,
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
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--modes", nargs="+", default=list(DEPTH_MODES), choices=DEPTH_MODES)
    ap.add_argument("--voting", nargs="+", default=list(VOTING), choices=VOTING)
    ap.add_argument("--device", default="auto")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    root = make_dataset(a.out, a.scenes, a.steps, a.step_deg, a.arms, *a.capture_size)
    results: dict = {"options": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()},
                     "modes": {}}
    for mode in a.modes:
        run = a.out / "runs" / mode
        t0 = time.perf_counter()
        train(root, "simple", run, image_size=tuple(a.image_size), batch_size=a.batch_size, epochs=a.epochs,
              lr=a.lr, depth_mode=mode, device=a.device, num_workers=1, progress=False)
        hist = json.loads((run / "history.json").read_text())
        entry = {"train_s": round(time.perf_counter() - t0, 1), "epochs": hist["epochs"][-1] if hist["epochs"] else None,
                 "seg_iou": round(segmentation_iou(run, root, "simple", device=a.device)["mean"], 4)}
        for voting in a.voting:
            rows, info = predict_rows(run, root, "simple", device=a.device, voting=voting, num_workers=0,
                                      progress=False)
            sc = score(rows, root, split="simple")
            oracle = score(oracle_vector_rows(run, root, "simple", voting), root, split="simple")
            entry[voting] = {"add_s": sc["mean"]["add_s"], "proj2d": sc["mean"]["proj2d"],
                             "auc_add_s": sc["mean"]["auc_add_s"], "pose_ms": info["pose_ms_per_image"],
                             "gt_vectors_add_s": oracle["mean"]["add_s"],
                             "gt_vectors_auc_add_s": oracle["mean"]["auc_add_s"]}
        results["modes"][mode] = entry
        (a.out / "depth_modes.json").write_text(json.dumps(results, indent=2))
        print(json.dumps({mode: entry}), flush=True)

    lines = ["| input depth | pose recovery | ADD(S) | 2D proj. | AUC ADD(S) | ADD(S) with GT vectors | seg IoU |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for mode, e in results["modes"].items():
        for voting in a.voting:
            v = e[voting]
            lines.append(f"| {mode} | {voting} | {100 * v['add_s']:.1f} % | {100 * v['proj2d']:.1f} % | "
                         f"{100 * v['auc_add_s']:.1f} % | {100 * v['gt_vectors_add_s']:.1f} % | "
                         f"{100 * e['seg_iou']:.1f} % |")
    print("\n".join(lines))
    results["table"] = lines
    (a.out / "depth_modes.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
