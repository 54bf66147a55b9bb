"""The pages of issue 32 part 6 in a real browser (headless Chromium, Debian's, driven by
Playwright), on the rich dataset (1,800 hard test targets, so figures are shown): the status page's
queue position and ETA, the leaderboard's phases (validation, test on the public part, the final
one on the held-back part: shut until the operator reveals it), the method's paper and code links,
the per-condition table, the CSV and JSON exports, and the version each score is on (an older one
said, then scored again); ``tdof20 submit`` prints the queue position. With TDOF20_SCREENSHOTS=DIR set, DIR/server_queue.png,
DIR/server_phases.png (the test phase), DIR/server_final.png (the revealed final leaderboard) and
DIR/server_conditions.png (a results page's per-condition table) are saved (docs/img/ holds them)."""

from __future__ import annotations

import csv
import io
import json
import os
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tdof20.server.cli import app
from tdof20.server.client import submit
from tdof20.server.config import ServerConfig
from tdof20.server.worker import run_worker
from tests.test_server_support import LiveServer, build_rich_dataset, rich_results_csv

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed "
                                                              "(/usr/bin/chromium; apt-get install chromium)")
PAPER, CODE = "https://arxiv.org/abs/2401.00001", "https://github.com/alice/mynet"


def test_queue_phases_conditions_exports_and_versions(tmp_path):
    from playwright.sync_api import expect, sync_playwright

    root = tmp_path / "ds"
    gt = build_rich_dataset(root)
    data = tmp_path / "data"
    files = {}
    for name, kw in {"mynet": {"bad": 0.1}, "baseline": {"bad": 0.45, "seed": 1}, "third": {"seed": 2},
                     "val": {"split": "val"}}.items():
        files[name] = tmp_path / f"{name}.csv"
        files[name].write_bytes(rich_results_csv(gt, **kw))
    cfg = ServerConfig(dataset=root, data=data)
    run = CliRunner().invoke
    shots = Path(os.environ["TDOF20_SCREENSHOTS"]) if os.environ.get("TDOF20_SCREENSHOTS") else None

    def shot(page, name: str) -> None:
        if shots is not None:
            shots.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(shots / name), full_page=True)

    with LiveServer(root, data) as live:
        r = run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), "--data", str(data)])
        assert r.exit_code == 0 and "held back 300 of 600" in r.output, r.output
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=ARGS, headless=True)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 900}, accept_downloads=True)
                page.set_default_timeout(30_000)
                page.goto(live.url + "/signin")
                page.fill("input[name=name]", "alice")
                page.fill("input[name=token]", live.tokens["alice"])
                page.click("button.primary")
                page.wait_for_url("**/mine")

                # ------------------------------------------------ the queue: position, then an ETA
                uid0 = submit(files["baseline"], live.url, live.tokens["alice"], "Baseline", "hard", public=True,
                              authors="B. Ob", hardware="Xeon 8 cores")["uid"]
                page.click("text=Submit")
                page.set_input_files("input[name=file]", str(files["mynet"]))
                page.select_option("select[name=split]", "hard")
                page.fill("input[name=method]", "MyNet")
                page.fill("input[name=authors]", "A. Lice")
                page.fill("input[name=hardware]", "RTX 4090")
                page.fill("input[name=training_data]", "hard train (real)")
                page.fill("input[name=paper]", PAPER)
                page.fill("input[name=code]", CODE)
                page.check("input[name=public]")
                page.click("button.primary")
                page.wait_for_url("**/s/*")
                uid1 = page.url.rsplit("/", 1)[1]
                queue = page.locator("#queue")
                expect(queue).to_contain_text("2")
                expect(queue).to_contain_text("in the queue")
                expect(queue).to_contain_text("1 submission ahead of it")
                expect(queue).to_contain_text("no scoring finished yet, so no estimate")
                assert run_worker(cfg, once=True) == 2  # (the page refreshes itself while queued)
                expect(page.locator("#status")).to_have_text("done", timeout=60_000)
                expect(page.locator("#version")).to_contain_text("current")
                expect(page.locator("#held-note")).to_contain_text("public part")
                expect(page.locator(f'a[href="{PAPER}"]')).to_be_visible()
                # the per-condition table: 900 public targets, every bin shown at its step
                table = page.locator("#conditions")
                expect(table).to_contain_text("occlusion > 50 %")
                expect(table).to_contain_text("not symmetric")
                assert table.locator("td.miss").count() == 0
                assert page.locator(".plots img").count() == 1  # the shown values' bars
                shot(page, "server_conditions.png")
                r = run(app, ["submit", str(files["third"]), "--server", live.url, "--token", live.tokens["alice"],
                              "--method", "Third", "--split", "hard"])  # the command says where it stands
                assert r.exit_code == 0, r.output
                lines = r.output.strip().splitlines()
                uid2 = lines[0].split()[1].rstrip(":")
                assert lines[1].startswith("position 1 in the queue (0 ahead, 1 worker(s)); expected in about "), lines
                page.goto(f"{live.url}/s/{uid2}")
                expect(page.locator("#queue")).to_contain_text("expected result")
                expect(page.locator("#queue")).to_contain_text("(median of the last 2)")
                assert page.locator("#queue .qbig b").nth(1).inner_text().startswith("~")
                api = json.loads(page.context.request.get(f"{live.url}/api/submissions/{uid2}", headers={
                    "Authorization": f"Bearer {live.tokens['alice']}"}).text())
                assert api["queue"]["position"] == 1 and api["queue"]["eta_s"] is not None
                shot(page, "server_queue.png")
                page.goto(live.url + "/mine")
                expect(page.locator("#mine tbody tr").first).to_contain_text("#1")

                # ------------------------------------------------ the leaderboard's phases
                page.goto(live.url + "/?split=hard")
                tabs = page.locator("#phases a")
                expect(tabs).to_have_text(["Validation phase", "Test phase (public part)",
                                           "Final (held-back part) · not revealed"])
                expect(tabs.nth(1)).to_have_class("on")
                rows = page.locator("table.board tbody tr")
                expect(rows).to_have_count(2)
                expect(rows.nth(0)).to_contain_text("MyNet")  # ranked by the public part's shown mean
                expect(rows.nth(0).locator(f'a[href="{CODE}"]')).to_have_text("code")
                expect(rows.nth(0)).to_contain_text("RTX 4090")
                expect(rows.nth(0)).to_contain_text("hard train (real)")
                expect(rows.nth(0).locator(".badge")).to_have_text("current")
                shot(page, "server_phases.png")
                with page.expect_download() as dl:
                    page.click("#export-csv")
                text = Path(dl.value.path()).read_text()
                table = list(csv.DictReader(io.StringIO(text)))
                assert [t["method"] for t in table] == ["MyNet", "Baseline"] and table[0]["paper"] == PAPER
                assert "score (add_s, %, test)" in text.splitlines()[0] and float(table[0]["score (add_s, %, test)"])
                page.click("#export-json")
                board = json.loads(page.locator("body").inner_text())
                assert [b["method"] for b in board] == ["MyNet", "Baseline"] and board[0]["code"] == CODE
                page.goto(live.url + "/?split=hard")
                page.click("#phases a:has-text('Final')")
                expect(page.locator("#not-revealed")).to_be_visible()
                assert page.locator("table.board").count() == 0
                assert run(app, ["serve", "reveal", "--split", "hard", "--data", str(data)]).exit_code == 0
                page.reload()
                expect(page.locator("#phase-note")).to_contain_text("Revealed by the server's operators")
                expect(page.locator("table.board tbody tr")).to_have_count(2)
                shot(page, "server_final.png")
                page.goto(f"{live.url}/s/{uid1}")
                expect(page.locator("#private")).to_be_visible()

                # ------------------------------------------------ the validation phase
                uid3 = submit(files["val"], live.url, live.tokens["bob"], "Tuned", "simple", part="val",
                              public=True)["uid"]
                assert run_worker(cfg, once=True) == 2  # (the third one too)
                page.goto(live.url + "/?split=simple")
                page.click("#phases a:has-text('Validation phase')")
                expect(page.locator("table.board tbody tr")).to_contain_text("Tuned")
                expect(page.locator("#derivable")).to_have_count(0)  # public labels: nothing to hide
                page.click("text=Tuned")
                expect(page.locator("#per-image")).to_be_visible()
                expect(page.locator("#per-condition")).to_be_visible()
                assert uid3 in page.url

                # ------------------------------------------------ versions: an older one, rescored
                con = sqlite3.connect(data / "server.db")
                with con:
                    con.execute("UPDATE submissions SET scorer_version = '0.0.9+deadbeef' WHERE uid = ?", (uid0,))
                con.close()
                page.goto(live.url + "/?split=hard")
                row = page.locator("table.board tbody tr", has_text="Baseline")
                expect(row.locator(".badge")).to_have_text("older version")
                r = run(app, ["serve", "rescore", "--dataset", str(root), "--data", str(data)])
                assert r.exit_code == 0 and "queued again 1 submission(s)" in r.output and uid0 in r.output
                page.reload()
                expect(row).to_contain_text("rescoring")  # its score stays shown meanwhile
                assert run_worker(cfg, once=True) == 1
                page.reload()
                expect(row.locator(".badge")).to_have_text("current")
            finally:
                browser.close()
