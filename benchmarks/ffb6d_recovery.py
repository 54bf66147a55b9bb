"""FFB6D's pose recovery (MeanShift voting + least squares) at 480x640: ms per image for 1, 3 and 5
objects on a synthetic vote set (tdof20.methods.ffb6d_pose.example_votes: 12,800 points, 60 % of them on
the objects, 2 mm noise, 30 % outlier votes), with the pose errors and MeanShift's work.

    python benchmarks/ffb6d_recovery.py [--objects 1,3,5] [--repeats 3] [--threads 1] [--device cpu|cuda]
        [--outliers 0.3] [--noise 2.0] [--impl PATH] [--max-iter N] [--max-votes N]

``--impl PATH`` times the ``recover_poses`` of another copy of ffb6d_pose.py (or of an older
ffb6d.py, where it lived before: ``git show REV:tdof20/methods/ffb6d.py > /tmp/old.py``) with the
same positional arguments.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
import time

import numpy as np
import torch

from tdof20.methods import ffb6d, ffb6d_pose
from tdof20.methods.base import MethodMeta


def rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def load_impl(path: str | None):
    if not path:
        return ffb6d_pose.recover_poses
    spec = importlib.util.spec_from_file_location("ffb6d_impl", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod                                        # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod.recover_poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="1,3,5")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n-points", type=int, default=12800)
    ap.add_argument("--outliers", type=float, default=0.3, help="share of outlier votes")
    ap.add_argument("--noise", type=float, default=2.0, help="Gaussian noise of the clean votes, mm")
    ap.add_argument("--impl", default=None, help="another ffb6d_pose.py (or older ffb6d.py) whose recover_poses to time")
    ap.add_argument("--max-iter", type=int, default=None, help="default: FFB6DConfig's meanshift_iters")
    ap.add_argument("--max-votes", type=int, default=None, help="default: FFB6DConfig's max_votes")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    cfg = ffb6d.FFB6DConfig()
    max_iter = cfg.meanshift_iters if a.max_iter is None else a.max_iter
    max_votes = cfg.max_votes if a.max_votes is None else a.max_votes
    rec = load_impl(a.impl)
    print(f"device {dev}, {torch.get_num_threads()} thread(s), {a.n_points} points, impl {a.impl or 'tdof20'}, "
          f"max_iter {max_iter}, max_votes {max_votes}, {a.outliers:.0%} outlier votes, noise {a.noise} mm")
    for n_obj in [int(v) for v in a.objects.split(",")]:
        meta = MethodMeta.from_catalog(tuple(range(1, n_obj + 1)), image_size=(480, 640))
        v = ffb6d_pose.example_votes(meta, a.n_points, outliers=a.outliers, noise_mm=a.noise, seed=n_obj)
        args = [v[k].to(dev) for k in ("points", "classes", "ctr_ofs", "kp_ofs", "model_kps")]
        times, rows = [], []
        for r in range(a.repeats + 1):                                  # the first run warms up
            if dev.type == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            rows = rec(*args, 40.0, max_iter, max_votes, 10, torch.Generator().manual_seed(0))
            if dev.type == "cuda":
                torch.cuda.synchronize()
            if r:
                times.append(time.perf_counter() - t0)
        stats: dict = {}
        if rec is ffb6d_pose.recover_poses:
            rec(*args, 40.0, max_iter, max_votes, 10, torch.Generator().manual_seed(0), stats=stats)
        t_err = max(float(np.linalg.norm(t - v["poses"][c][1])) for _, c, _, _, t in rows)
        r_err = max(rot_err_deg(R, v["poses"][c][0]) for _, c, _, R, _ in rows)
        work = ""
        if stats:
            work = (f"  kernel entries {stats['ctr']['kernel_evals'] + stats['kp']['kernel_evals']:,}"
                    f"  iterations seeds/winner ctr {stats['ctr']['seed_iters']}/{stats['ctr']['refine_iters']}"
                    f" kp {stats['kp']['seed_iters']}/{stats['kp']['refine_iters']}")
        print(f"{n_obj} object(s): {1000 * np.median(times):8.1f} ms/image (median of {a.repeats}), "
              f"{len(rows)} poses, max error {t_err:.2f} mm / {r_err:.3f} deg{work}", flush=True)


if __name__ == "__main__":
    main()
