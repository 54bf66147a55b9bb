"""A real browser (headless Chromium, Debian's, driven by Playwright): a researcher signs in,
uploads a results file through the form, watches it go from queued to scored while a worker runs,
and finds it on the leaderboard. With TDOF20_SCREENSHOTS=DIR set, the leaderboard and the results
page are saved as DIR/server_leaderboard.png and DIR/server_results.png (docs/img/ holds them)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests.test_server_support import CLI, LiveServer, dataset, results_csv  # noqa: F401

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed "
                                                              "(/usr/bin/chromium; apt-get install chromium)")


def test_sign_in_upload_watch_it_scored_and_ranked(dataset, tmp_path):
    from playwright.sync_api import expect, sync_playwright

    root, gt = dataset
    data = tmp_path / "data"
    csv = tmp_path / "mynet_hard.csv"
    csv.write_bytes(results_csv(gt, "hard", shift_mm=4.0))
    shots = os.environ.get("TDOF20_SCREENSHOTS")
    with LiveServer(root, data) as live:
        worker = subprocess.Popen(CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--poll",
                                         "0.3"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=ARGS, headless=True)
                try:
                    page = browser.new_page(viewport={"width": 1280, "height": 900})
                    page.set_default_timeout(30_000)
                    page.goto(live.url + "/signin")
                    page.fill("input[name=name]", "alice")
                    page.fill("input[name=token]", live.tokens["alice"])
                    page.click("button.primary")
                    page.wait_for_url("**/mine")
                    expect(page.locator("header")).to_contain_text("signed in as alice")
                    page.click("text=Submit")
                    page.set_input_files("input[name=file]", str(csv))
                    page.select_option("select[name=split]", "hard")
                    page.fill("input[name=method]", "MyNet")
                    page.fill("input[name=authors]", "A. Lice, B. Ob")
                    page.fill("input[name=hardware]", "RTX 4090")
                    page.fill("input[name=time_per_image]", "31 ms")
                    page.fill("input[name=training_data]", "hard train (real)")
                    page.check("input[name=public]")
                    page.click("button.primary")
                    page.wait_for_url("**/s/*")
                    status = page.locator("#status")
                    assert status.inner_text() in ("queued", "scoring")
                    # the page refreshes itself while queued or scoring; the worker scores it
                    expect(page.locator("#status")).to_have_text("done", timeout=180_000)
                    expect(page.locator("h2", has_text="Per object")).to_be_visible()
                    # a test part on 9 targets: every cell withheld, the rule said, no curve drawn
                    expect(page.locator("#disclosure")).to_be_visible()
                    assert page.locator("td.miss", has_text="withheld").count() >= 1
                    assert page.locator(".plots img").count() == 0
                    assert page.locator("#per-image").count() == 0  # a test submission: aggregates only
                    results_url = page.url
                    page.click("text=Leaderboard")
                    page.select_option("select[name=split]", "hard")
                    page.click("form.controls button")
                    row = page.locator("tbody tr", has_text="MyNet")
                    expect(row).to_contain_text("A. Lice, B. Ob")
                    expect(row).to_contain_text("RTX 4090")
                    if shots:
                        out = Path(shots)
                        out.mkdir(parents=True, exist_ok=True)
                        page.screenshot(path=str(out / "server_leaderboard.png"), full_page=True)
                        page.goto(results_url)
                        page.wait_for_load_state("networkidle")
                        page.screenshot(path=str(out / "server_results.png"), full_page=True)
                finally:
                    browser.close()
        finally:
            worker.terminate()
            worker.wait(20)
