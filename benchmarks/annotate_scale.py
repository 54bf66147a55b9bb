"""Scale-out of ``tdof20 annotate RAW... --out DIR``: two simulated scenes, 1 worker vs 2.

    python benchmarks/annotate_scale.py [--scenes multi/08,multi/08] [--arms 2] [--steps 6]
        [--step-deg 30] [--width 160] [--height 120] [--executors local,ray] [--workers 1,2] [--no-gate]
        [--work DIR] [--keep]

Captures the scenes on the simulated rig (each with its own noise seed; a scene named twice is
relabelled multi/NN+1 in its session.json, so that the two get their own scene folders), merges
their truth models into one models folder (the CAD models of the run), then annotates both in one
``annotate_many`` call (what the command does) per executor and worker count, each into a fresh
folder: ``local`` with N worker processes (N = 2: the two scenes side by side), ``ray`` on a fresh
local Ray instance of N CPUs (scenes as tasks, their arm positions and label chunks as tasks
inside them; the instance's start is in the time). Prints the wall time of each run, the ratio
1 worker / 2 workers per executor, and whether every run wrote the same label files as the first
(they must: where the work runs does not change the labels).

Default sizes run in a few minutes on 2 idle cores; --arms 4 --steps 24 --step-deg 15 --width 640 --height 480
is closer to a real session. The machine's load (os.getloadavg) is printed beside the figures:
on a shared machine the ratio says little.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LABEL_DIRS = ("rgb", "depth", "depth_opaque", "depth_restored", "mask", "mask_visib", "models")
LABEL_FILES = ("scene_gt.json", "scene_gt_info.json", "scene_camera.json")


def _label_files(scene: Path) -> dict[str, bytes]:
    out = {n: (scene / n).read_bytes() for n in LABEL_FILES if (scene / n).exists()}
    for d in LABEL_DIRS:
        if (scene / d).is_dir():
            for p in sorted((scene / d).iterdir()):
                out[f"{d}/{p.name}"] = p.read_bytes()
    return out


def _capture(work: Path, scenes: list[str], args) -> tuple[list[Path], Path]:
    from tdof20.capture import run_capture, sim_config

    raws, used = [], set()
    models = work / "models"
    models.mkdir(parents=True, exist_ok=True)
    info: dict = {}
    for seed, sid in enumerate(scenes):
        raw = work / f"raw_{seed}_{sid.replace('/', '_')}"
        t = time.perf_counter()
        run_capture(sim_config(sid, steps=args.steps, step_deg=args.step_deg, n_arms=args.arms,
                               width=args.width, height=args.height, seed=seed), raw, yes=True, show_progress=False)
        name = sid
        while name in used:   # the same scene twice: the second gets the next scene id
            kind, n = name.split("/")
            name = f"{kind}/{int(n) + 1:02d}"
        if name != sid:
            p = raw / "session.json"
            d = json.loads(p.read_text())
            d["scene_id"] = name
            p.write_text(json.dumps(d, indent=2))
        used.add(name)
        print(f"captured {sid} as {name}: {args.arms} arms x {args.steps} steps at {args.width}x{args.height} "
              f"in {time.perf_counter() - t:.1f} s")
        truth = raw / "truth" / "models"
        for f in truth.glob("obj_*.ply"):
            shutil.copy2(f, models / f.name)
        info.update(json.loads((truth / "models_info.json").read_text()))
        raws.append(raw)
    (models / "models_info.json").write_text(json.dumps(info, indent=2))
    return raws, models


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="multi/08,multi/08", help="two (or more) scene ids, comma-separated")
    ap.add_argument("--arms", type=int, default=2)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--step-deg", type=float, default=30.0)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--executors", default="local,ray")
    ap.add_argument("--workers", default="1,2", help="worker counts to compare, comma-separated")
    ap.add_argument("--no-gate", action="store_true", help="label every frame (the label gate off)")
    ap.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    args = ap.parse_args()

    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    from tdof20.annotate.batch import annotate_many, batch_text
    from tdof20.annotate.config import AnnotateConfig
    from tdof20.annotate.label import LabelConfig

    work = args.work or Path(tempfile.mkdtemp(prefix="annotate_scale_"))
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    raws, models = _capture(work, scenes, args)
    cfg = AnnotateConfig(label=LabelConfig(gate=not args.no_gate))
    results = []
    reference: dict | None = None
    for executor in [e.strip() for e in args.executors.split(",") if e.strip()]:
        for n in [int(w) for w in args.workers.split(",") if w.strip()]:
            out = work / f"out_{executor}_{n}"
            shutil.rmtree(out, ignore_errors=True)
            load = os.getloadavg()[0]
            t = time.perf_counter()
            s = annotate_many(raws, out, models, cfg=cfg.with_label_options(executor=executor, workers=n),
                              progress=False)
            wall = time.perf_counter() - t
            print(batch_text(s))
            files = {r["scene"]: _label_files(Path(r["out"])) for r in s["scenes"]}
            same = None
            if reference is None:
                reference = files
            else:
                same = files == reference
            results.append({"executor": executor, "workers": n, "wall_s": wall, "failed": s["failed"],
                            "load": load, "same": same,
                            "scene_s": [r["seconds"] for r in s["scenes"]]})
            print(f"--> {executor}, {n} worker(s): {wall:.1f} s (load {load:.1f})\n")

    print(f"{len(raws)} scenes ({', '.join(scenes)}), {args.arms} arms x {args.steps} steps at "
          f"{args.width}x{args.height}, {os.cpu_count()} cores")
    print(f"{'executor':<9} {'workers':>7} {'wall':>8} {'per scene':>18} {'load':>5}  same labels")
    for r in results:
        per = ", ".join(f"{x:.1f}" for x in r["scene_s"])
        same = "reference" if r["same"] is None else ("yes" if r["same"] else "NO")
        fail = f"  failed: {', '.join(r['failed'])}" if r["failed"] else ""
        print(f"{r['executor']:<9} {r['workers']:>7} {r['wall_s']:>7.1f}s {per:>18} {r['load']:>5.1f}  {same}{fail}")
    by = {(r["executor"], r["workers"]): r["wall_s"] for r in results}
    for executor in dict.fromkeys(r["executor"] for r in results):
        if (executor, 1) in by and (executor, 2) in by:
            print(f"{executor}: 1 worker / 2 workers = {by[(executor, 1)] / by[(executor, 2)]:.2f}x")
    if args.keep or args.work:
        print(f"kept: {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
