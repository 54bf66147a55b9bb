"""The command line as a user meets it: the real console script in a subprocess."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tdof20.formats import read_models_info, read_png

EXE = [sys.executable, "-m", "tdof20.cli"]


def run(*args, cwd=None):
    return subprocess.run(EXE + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, timeout=300)


def one_line_error(res, *needles):
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error:")
    for n in needles:
        assert n in lines[0], lines[0]
    assert "Traceback" not in res.stderr


def test_help_lists_only_built_commands():
    res = run("--help")
    assert res.returncode == 0
    import re
    commands = set(re.findall(r"^│ (\w+) ", res.stdout, flags=re.M))
    assert commands == {"demo", "capture", "dataset", "objects", "sim"}


def test_objects_list_and_export(tmp_path):
    res = run("objects", "list")
    assert res.returncode == 0 and "wine_glass" in res.stdout and "teapot" in res.stdout
    res = run("objects", "export", tmp_path / "models", "--ids", "3,15")
    assert res.returncode == 0, res.stderr
    info = read_models_info(tmp_path / "models")
    assert sorted(info) == [3, 15]
    assert sorted(p.name for p in (tmp_path / "models").glob("*.ply")) == ["obj_000003.ply", "obj_000015.ply"]


def test_bad_ids_and_scenes_are_one_line_errors(tmp_path):
    one_line_error(run("objects", "export", tmp_path / "m", "--ids", "3,25"), "25")
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())
    one_line_error(run("objects", "export", tmp_path / "m", "--ids", "x"), "--ids")
    one_line_error(run("capture", "run", "--sim", "--scene", "multi/21", "--out", tmp_path / "s"), "multi/21")
    one_line_error(run("capture", "run", "--sim", "--steps", "0", "--out", tmp_path / "s"), "turntable.steps")


@pytest.fixture(scope="module")
def cli_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "s"
    res = run("capture", "run", "--sim", "--scene", "single/05", "--steps", "2", "--step-deg", "90",
              "--arm-positions", "1", "--width", "96", "--height", "72", "--out", out, "--yes")
    assert res.returncode == 0, res.stderr
    res = run("sim", "sheet", out)
    assert res.returncode == 0, res.stderr
    return out


def test_sim_session_and_sheet(cli_session, tmp_path):
    sheet = read_png(cli_session / "contact_sheet.png", "rgb")
    assert sheet.shape[0] > 50 and sheet.std() > 10
    res = run("sim", "sheet", cli_session, "--out", tmp_path / "sheet.png", "--frames", "1")
    assert res.returncode == 0 and (tmp_path / "sheet.png").exists()


def test_corrupt_inputs_are_one_line_errors_and_nothing_is_damaged(cli_session, tmp_path):
    s = tmp_path / "s"
    shutil.copytree(cli_session, s)
    png = s / "opaque/arm0/rgb/000000.png"
    png.write_bytes(png.read_bytes()[:200])  # truncated PNG
    before = {p: p.read_bytes() for p in s.rglob("*") if p.is_file()}
    one_line_error(run("sim", "sheet", s, "--out", tmp_path / "x.png"), "000000.png")
    assert {p: p.read_bytes() for p in s.rglob("*") if p.is_file()} == before
    # malformed session.json
    d = json.loads((s / "session.json").read_text())
    d["camera"]["K"] = d["camera"]["K"][:8]
    (s / "session.json").write_text(json.dumps(d))
    one_line_error(run("sim", "sheet", s), "session.json", "K")
    (s / "session.json").write_text("{not json")
    one_line_error(run("sim", "sheet", s), "session.json")


def test_session_into_another_sessions_folder_is_refused(cli_session):
    before = (cli_session / "session.json").read_bytes()
    res = run("capture", "run", "--sim", "--scene", "single/06", "--steps", "2", "--step-deg", "90",
              "--arm-positions", "1", "--width", "96", "--height", "72", "--out", cli_session, "--yes")
    one_line_error(res, "different session")
    assert (cli_session / "session.json").read_bytes() == before


def test_sim_frames(tmp_path):
    res = run("sim", "frames", "--scene", "multi/02", "--angles", "0,45", "--width", "80", "--height", "60",
              "--out", tmp_path)
    assert res.returncode == 0, res.stderr
    assert len(list(tmp_path.glob("*_rgb.png"))) == 4
    d = read_png(next(tmp_path.glob("*transparent_depth.png")), "depth")
    assert d.dtype == np.uint16 and (d > 0).any()
    one_line_error(run("sim", "frames", "--arm", "9", "--out", tmp_path), "--arm")


def test_demo_runs_end_to_end(tmp_path):
    res = run("demo", "--out", tmp_path / "demo", "--steps", "2", "--arm-positions", "2", "--width", "96",
              "--height", "72")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "demo" / "contact_sheet.png").exists()
    assert "contact sheet" in res.stderr + res.stdout


def test_dataset_commands(tmp_path):
    raw = tmp_path / "raw"
    assert run("capture", "run", "--sim", "--scene", "multi/02", "--steps", "2", "--step-deg", "90",
               "--arm-positions", "1", "--width", "64", "--height", "48", "--out", raw, "--yes").returncode == 0
    assert run("sim", "label", raw, "--out", tmp_path / "lab").returncode == 0
    res = run("dataset", "build", tmp_path / "lab", "--out", tmp_path / "root")
    assert res.returncode == 0, res.stderr
    res = run("dataset", "stats", tmp_path / "root", "--json")
    assert json.loads(res.stdout)["splits"]["hard_test"] == 2
    res = run("dataset", "pack", tmp_path / "root", "--split", "hard", "--part", "test", "--out", tmp_path / "t.h5")
    assert res.returncode == 0 and (tmp_path / "t.h5").exists()
    one_line_error(run("dataset", "pack", tmp_path / "root", "--split", "medium", "--part", "test",
                       "--out", tmp_path / "u.h5"), "medium")
    one_line_error(run("dataset", "stats", tmp_path / "nothing"), "dataset_info.json")
