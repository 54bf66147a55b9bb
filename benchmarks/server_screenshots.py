"""Screenshots of the benchmark server's pages for docs/server.md, taken in headless Chromium.

    python benchmarks/server_screenshots.py [--images 180] [--out docs/img]

Builds a small synthetic dataset (benchmarks/server_workload.py: the hard protocol's 6 test
scenes, 20 objects), starts ``tdof20 serve`` on loopback, submits five synthetic methods (ground
truth perturbed at different scales; their names say they are demos) as two users, scores them
with a worker, and saves the leaderboard (hard, ADD(S)) and the second method's results page as
OUT/server_leaderboard.png and OUT/server_results.png. Needs /usr/bin/chromium and playwright.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from server_workload import make, results

from tdof20.server.client import submit
from tdof20.server.config import ServerConfig
from tdof20.server.worker import run_worker
from tests.test_server_support import LiveServer

METHODS = [  # name, rotation (deg), translation (mm), missing, authors, hardware, time, training data, description
    ("demo-RGBD-refine", 2.0, 4.0, 0.01, "A. Lice, B. Ob", "RTX 4090", "48 ms", "hard train + synthetic",
     "RGB-D keypoints with an ICP refinement on the restored depth"),
    ("demo-keypoints-PnP", 4.0, 9.0, 0.03, "C. Arol", "RTX 3090", "22 ms", "hard train",
     "per-pixel keypoint voting and RANSAC PnP on RGB only"),
    ("demo-dense-fusion", 6.0, 14.0, 0.03, "D. Ave", "A100", "35 ms", "hard train",
     "dense colour-geometry fusion, no refinement"),
    ("demo-template", 12.0, 25.0, 0.08, "E. Ve", "Xeon 8 cores", "410 ms", "CAD models only",
     "template matching on edge maps"),
    ("demo-centre-only", 30.0, 40.0, 0.1, "F. Rank", "i7 laptop", "5 ms", "hard train",
     "object centres from masks, mean orientation (a floor)"),
]
CHROMIUM = "/usr/bin/chromium"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=180)
    ap.add_argument("--out", type=Path, default=Path("docs/img"))
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="tdof20-shots-") as tmp:
        root, data = Path(tmp) / "ds", Path(tmp) / "data"
        make(root, a.images)
        with LiveServer(root, data, "--daily-limit", "100") as live:
            uids = []
            for i, (name, rot, trans, miss, authors, hw, tpi, train, desc) in enumerate(METHODS):
                csv = Path(tmp) / f"{name}.csv"
                csv.write_bytes(results(root, rot, trans, miss, seed=i))
                uids.append(submit(csv, live.url, live.tokens[("alice", "bob")[i % 2]], name, "hard", desc, authors,
                                   hw, tpi, train, public=True)["uid"])
            run_worker(ServerConfig(dataset=root, data=data), once=True)
            a.out.mkdir(parents=True, exist_ok=True)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                             args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"])
                page = browser.new_page(viewport={"width": 1400, "height": 800}, device_scale_factor=1)
                page.goto(live.url + "/signin")
                page.fill("input[name=name]", "alice")
                page.fill("input[name=token]", live.tokens["alice"])
                page.click("button.primary")
                page.goto(live.url + "/?split=hard&metric=add_s")
                page.screenshot(path=str(a.out / "server_leaderboard.png"), full_page=True)
                page.goto(f"{live.url}/s/{uids[1]}")
                page.wait_for_load_state("networkidle")
                page.screenshot(path=str(a.out / "server_results.png"), full_page=True)
                browser.close()
    print(f"wrote {a.out / 'server_leaderboard.png'} and {a.out / 'server_results.png'}")


if __name__ == "__main__":
    main()
