"""``tdof20 demo``: the main job end to end on the simulator.

capture (simulated sessions of both phases, with exact truth) → labels → dataset (BOP layout, the
two protocols) → a short HFF6DoF training on the TDoF20-simple train part → predict its test part →
score (ADD(S), 2D projection, AUC) → a report (``OUT/report.md``) with the contact sheet, the loss
curves and the accuracy curves. Every stage resumes: run the demo again on the same ``--out`` and
finished stages are reused.

Labels come from the simulator's exact truth (``tdof20 sim label``): the annotation pipeline
(``tdof20 annotate``) replaces them once it runs end to end.
"""

from __future__ import annotations

import time
from pathlib import Path

from tdof20.benchmark.dataset import build_dataset
from tdof20.capture import run_capture, sim_config
from tdof20.formats import atomic_write_bytes, read_json, write_json, write_png
from tdof20.progress import console
from tdof20.sim.truth import oracle_scene
from tdof20.viz import session_contact_sheet


def _done(path: Path) -> bool:
    return path.exists()


def run_demo(out: str | Path, scenes: tuple[str, ...] = ("single/03", "multi/08"), steps: int = 24,
             step_deg: float = 15.0, n_arms: int = 4, width: int = 640, height: int = 480, seed: int = 0,
             train: bool = True, image_size: tuple[int, int] = (96, 128), epochs: int = 6, batch_size: int = 8,
             lr: float = 2e-3, device: str = "auto") -> dict:
    """Run the demo into ``out``; returns the paths it wrote and the time each stage took.

    ``train=False`` stops after the dataset. ``image_size``, ``epochs``, ``batch_size``, ``lr``:
    the short HFF6DoF training (CPU-sized by default: a few minutes on 2 cores)."""
    out = Path(out)
    timings: dict[str, float] = {}
    console.rule("[bold]tdof20 demo")

    # capture ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    sessions = []
    for scene in scenes:
        cfg = sim_config(scene, steps=steps, step_deg=step_deg, n_arms=n_arms, width=width, height=height, seed=seed)
        session = out / "raw" / scene.replace("/", "_")
        run_capture(cfg, session, yes=True, resume_command=f"tdof20 demo --out {out} (the same options)")
        sessions.append((scene, session))
    timings["capture"] = time.perf_counter() - t0
    n_frames = 2 * len(scenes) * n_arms * steps
    console.print(f"capture (simulated): {n_frames} RGB-D frames of {', '.join(scenes)} in "
                  f"{timings['capture']:.1f} s -> {out / 'raw'}")

    # labels -------------------------------------------------------------------------------
    t0 = time.perf_counter()
    scene_dirs = []
    for name, s in sessions:
        d = out / "labels" / name.replace("/", "_")
        scene_dirs.append(d if _done(d / "scene_info.json") else oracle_scene(s, d))
    timings["labels"] = time.perf_counter() - t0
    console.print(f"labels (simulator truth): {len(scene_dirs)} scenes in {timings['labels']:.1f} s -> {out / 'labels'}")

    # dataset ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    root = out / "dataset"
    if _done(root / "dataset_info.json"):
        from tdof20.benchmark.dataset import stats
        st = stats(root)
    else:
        st = build_dataset(scene_dirs, root)
    timings["dataset"] = time.perf_counter() - t0
    sp = st["splits"]
    console.print(f"dataset: {st['images']} images; simple {sp['simple_train']} train / {sp['simple_test']} test, "
                  f"hard {sp['hard_train']} train / {sp['hard_test']} test -> {root}")
    sheet = out / "contact_sheet.png"
    write_png(sheet, session_contact_sheet(sessions[-1][1], n_frames=min(6, n_arms * steps)))
    result = {"sessions": [s for _, s in sessions], "dataset": root, "contact_sheet": sheet, "timings": timings}
    if not train:
        console.print(f"contact sheet: {sheet}")
        return result

    # train, predict, score ----------------------------------------------------------------
    from tdof20.benchmark.scoring import score_command
    from tdof20.methods.predict import predict
    from tdof20.methods.train import train as train_hff

    run = out / "runs" / "hff6dof_simple"
    t0 = time.perf_counter()
    train_hff(root, "simple", run, image_size=image_size, batch_size=batch_size, epochs=epochs, lr=lr,
              device=device, num_workers=1, seed=seed)
    timings["train"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    results = out / "results" / "hff6dof_simple.csv"
    predict(run, root, "simple", results, device=device, num_workers=1, seed=seed)
    timings["predict"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    report_dir = out / "report"
    scores_json = report_dir / "scores.json"
    text = score_command([results], root, "simple", None, scores_json, report_dir)
    timings["score"] = time.perf_counter() - t0
    scores = read_json(scores_json)
    info = read_json(results.with_name(results.stem + "_info.json"))
    write_json(out / "timings.json", {k: round(v, 2) for k, v in timings.items()})
    report = out / "report.md"
    md = [f"# tdof20 demo — {', '.join(scenes)}", "",
          f"Simulated capture: {len(scenes)} scenes, {n_arms} arm positions × {steps} turntable steps of "
          f"{step_deg}°, {width}×{height}, both phases ({n_frames} RGB-D frames).", "",
          f"Dataset: {st['images']} images; TDoF20-simple {sp['simple_train']} train / {sp['simple_test']} test.", "",
          f"HFF6DoF trained {epochs} epochs at {image_size[0]}×{image_size[1]} on the simple train part "
          f"({timings['train']:.0f} s); prediction {info['network_ms_per_image']:.0f} ms network + "
          f"{info['pose_ms_per_image']:.0f} ms pose recovery per image on {info['device']}.", "",
          "| metric (TDoF20-simple test, mean over objects) | value |", "| --- | ---: |",
          f"| ADD(S) < 10 % diameter | {100 * scores['mean']['add_s']:.1f} % |",
          f"| 2D projection < 5 px | {100 * scores['mean']['proj2d']:.1f} % |",
          f"| AUC of ADD(S) (0–100 mm) | {100 * scores['mean']['auc_add_s']:.1f} % |", "",
          "Stage times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()), "",
          "![contact sheet](contact_sheet.png)", "", "![loss curves](runs/hff6dof_simple/loss.png)", "",
          "Scores per object: report/report.md; accuracy curves: report/*.png; results: results/hff6dof_simple.csv.",
          ""]
    atomic_write_bytes(report, "\n".join(md).encode())
    console.print(text, highlight=False)
    console.print(f"report: {report}")
    result.update(run=run, results=results, scores=scores, report=report)
    return result
