"""The command line as a user meets it. The console script in a subprocess where the process itself
is tested (the help, which must start without torch; the demo end to end); elsewhere ``tdof20.cli.main``
in this process with its stdout and stderr captured (:func:`cli`): the same parsing, checks, output
and exit codes, without 3-8 s of imports (torch, open3d) for every command."""

import io
import json
import re
import shutil
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from tdof20.formats import read_models_info, read_png

EXE = [sys.executable, "-m", "tdof20.cli"]


def run(*args, cwd=None, timeout=300):
    """``tdof20 ARGS`` as a fresh process (the console script)."""
    return subprocess.run(EXE + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, timeout=timeout)


def cli(*args) -> subprocess.CompletedProcess:
    """``tdof20 ARGS`` in this process: :func:`tdof20.cli.main` (what the console script calls, with its
    one-line error handling) with ``sys.argv`` set and stdout/stderr captured; the exit code is
    its ``SystemExit``'s. An exception that escapes ``main`` (a traceback for the user) fails the test."""
    from tdof20.cli import main

    out, err, code = io.StringIO(), io.StringIO(), 0
    argv, sys.argv = sys.argv, ["tdof20", *(str(a) for a in args)]
    try:
        with redirect_stdout(out), redirect_stderr(err):
            main()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = argv
    return subprocess.CompletedProcess(["tdof20", *map(str, args)], code, out.getvalue(), err.getvalue())


def one_line_error(res, *needles):
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error:")
    for n in needles:
        assert n in lines[0], lines[0]
    assert "Traceback" not in res.stderr


def test_help_lists_only_built_commands():
    """The console script's own help (a process of its own: it starts without torch, see
    test_architecture.py)."""
    res = run("--help")
    assert res.returncode == 0
    import re
    commands = set(re.findall(r"^│ (\w+) ", res.stdout, flags=re.M))
    assert commands == {"demo", "capture", "annotate", "dataset", "objects", "sim", "train", "predict", "benchmark",
                        "reproduce", "serve", "submit"}


def test_annotate_help_shows_the_pipeline_options():
    """`tdof20 annotate --help`: the evaluate subcommand and the pipeline's own options (its command
    is hidden so that `tdof20 annotate RAW --out SCENE` reads naturally)."""
    res = cli("annotate", "--help")
    assert res.returncode == 0
    for opt in ("evaluate", "--out", "--models", "--stages", "--config", "--executor", "--ray-address",
                "--workers", "--force"):
        assert opt in res.stdout, opt
    assert "│ run " not in res.stdout


def test_error_keeps_brackets(tmp_path):
    """An error naming config tables ([sim], [turntable]) prints them: rich markup would eat them."""
    one_line_error(cli("capture", "run", tmp_path / "c.toml", "--clutter", "cabinet", "--out", tmp_path / "s"),
                   "[sim] table", "[turntable] direction")


def test_paths_with_brackets_print_whole(tmp_path):
    """A folder named like rich markup ('[sim]', '[/x]') is printed as it is, not eaten or a MarkupError."""
    out = tmp_path / "[sim]" / "[/x]" / "models"
    res = cli("objects", "export", out, "--ids", "3")
    assert res.returncode == 0, res.stderr
    assert str(out) in res.stderr.replace("\n", "") and "Traceback" not in res.stderr


@pytest.mark.parametrize("args,needle", [
    (["sim", "frames", "--scene", "single/01", "--width", "80", "--height", "60", "--angles", "nan"], "--angles"),
    (["sim", "frames", "--scene", "single/01", "--width", "80", "--height", "60", "--angles", ","], "--angles"),
    (["sim", "frames", "--scene", "single/01", "--width", "80", "--height", "60", "--seed", "-1"], "sim.seed"),
    (["capture", "run", "--sim", "--steps", "99999999999999999999", "--yes"], "turntable.steps: must be in 1..36000"),
    (["objects", "picture", "P.png", "--tile", "0"], "--tile"),
])
def test_out_of_range_numbers_are_one_line(tmp_path, args, needle):
    """Numbers a command cannot use (nan, negative seeds, zero sizes, 1e20 steps) are refused before
    any work, in one line, instead of a traceback from numpy, OpenCV or a MemoryError."""
    out = tmp_path / "o"
    args = [str(out / "p.png") if a == "P.png" else a for a in args]
    if args[0] != "objects":
        args += ["--out", str(out)]
    one_line_error(cli(*args), needle)
    assert not out.exists()


def test_empty_ids_and_a_folder_for_a_png_are_one_line(tmp_path):
    one_line_error(cli("objects", "export", tmp_path / "m", "--ids", ""), "--ids names no object")
    assert not (tmp_path / "m").exists()
    (tmp_path / "d").mkdir()
    one_line_error(cli("objects", "picture", tmp_path / "d", "--tile", "16"), str(tmp_path / "d"), "names a folder")
    assert list((tmp_path / "d").iterdir()) == [] and not list(tmp_path.glob(".*.tmp"))


def test_unreachable_hand_eye_is_one_line(tmp_path):
    """A simulated hand-eye 3 m off the flange: the arm has no joint solution; one line, not a traceback."""
    from tdof20.sim.rig import DEFAULT_T_TCP_CAM

    T = np.array(DEFAULT_T_TCP_CAM, float)
    T[0, 3] += 3000.0
    cfg = tmp_path / "he.toml"
    cfg.write_text('[session]\nscene_id = "multi/08"\n[hand_eye]\nT_tcp_cam = ['
                   + ", ".join(f"{x:g}" for x in T.reshape(-1)) + "]\n")
    one_line_error(cli("capture", "plan", cfg), str(cfg), "hand_eye.T_tcp_cam", "cannot place the camera")


def test_help_keeps_defaults_in_brackets():
    """rich markup would eat a bracketed default such as [cosine] as a style tag: they are escaped."""
    train, predict = cli("train", "--help").stdout, cli("predict", "--help").stdout
    for text in ("[cosine]", "[filled]", "[method]"):
        assert text in train, text
    assert "[the run's]" in predict


def test_method_options_are_set_with_set_not_with_method_flags(tmp_path):
    """HFF6DoF's options are no flags of train/predict: --set KEY=VALUE sets any method's, checked by
    its config (one line naming the key) before any work."""
    for cmd in ("train", "predict"):
        text = cli(cmd, "--help").stdout
        assert "--set" in text and not any(f in text for f in ("--fuse-stages", "--seg-head", "--masks", "--voting"))
    args = ("--dataset", tmp_path / "none", "--split", "simple", "--out", tmp_path / "run")
    one_line_error(cli("train", "hff6dof", *args, "--set", "fuse_stage=2"), "--set", "unknown option 'fuse_stage'")
    one_line_error(cli("train", "pvnet", *args, "--set", "fuse_stages=2"), "--set", "fuse_stages")
    one_line_error(cli("train", "hff6dof", *args, "--set", "fuse_stages=9"), "--set", "fuse_stages must be in 1..5")
    one_line_error(cli("train", "hff6dof", *args, "--set", "fuse_stages"), "--set", "key=value")
    res = cli("train", "hff6dof", *args, "--fuse-stages", "2")
    assert res.returncode != 0 and "No such option" in res.stderr


def test_objects_list_and_export(tmp_path):
    res = cli("objects", "list")
    assert res.returncode == 0 and "cube_136" in res.stdout and "whisky_cup_270" in res.stdout
    assert "capacity" in res.stdout
    res = cli("objects", "export", tmp_path / "models", "--ids", "3,15")
    assert res.returncode == 0, res.stderr
    info = read_models_info(tmp_path / "models")
    assert sorted(info) == [3, 15]
    assert sorted(p.name for p in (tmp_path / "models").glob("*.ply")) == ["obj_000003.ply", "obj_000015.ply"]


def test_bad_ids_and_scenes_are_one_line_errors(tmp_path):
    one_line_error(cli("objects", "export", tmp_path / "m", "--ids", "3,25"), "25")
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())
    one_line_error(cli("objects", "export", tmp_path / "m", "--ids", "x"), "--ids")
    one_line_error(cli("capture", "run", "--sim", "--scene", "multi/21", "--out", tmp_path / "s"), "multi/21")
    one_line_error(cli("capture", "run", "--sim", "--scene", "multi/20", "--out", tmp_path / "s"), "multi/20")
    one_line_error(cli("capture", "run", "--sim", "--steps", "0", "--out", tmp_path / "s"), "turntable.steps")


@pytest.fixture(scope="module")
def cli_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "s"
    res = cli("capture", "run", "--sim", "--scene", "single/05", "--steps", "2", "--step-deg", "90",
              "--arm-positions", "1", "--width", "96", "--height", "72", "--out", out, "--yes")
    assert res.returncode == 0, res.stderr
    res = cli("sim", "sheet", out)
    assert res.returncode == 0, res.stderr
    return out


def test_sim_session_and_sheet(cli_session, tmp_path):
    sheet = read_png(cli_session / "contact_sheet.png", "rgb")
    assert sheet.shape[0] > 50 and sheet.std() > 10
    res = cli("sim", "sheet", cli_session, "--out", tmp_path / "sheet.png", "--frames", "1")
    assert res.returncode == 0 and (tmp_path / "sheet.png").exists()


def test_corrupt_inputs_are_one_line_errors_and_nothing_is_damaged(cli_session, tmp_path):
    s = tmp_path / "s"
    shutil.copytree(cli_session, s)
    png = s / "opaque/arm0/rgb/000000.png"
    png.write_bytes(png.read_bytes()[:200])  # truncated PNG
    before = {p: p.read_bytes() for p in s.rglob("*") if p.is_file()}
    one_line_error(cli("sim", "sheet", s, "--out", tmp_path / "x.png"), "000000.png")
    assert {p: p.read_bytes() for p in s.rglob("*") if p.is_file()} == before
    # malformed session.json
    d = json.loads((s / "session.json").read_text())
    d["camera"]["K"] = d["camera"]["K"][:8]
    (s / "session.json").write_text(json.dumps(d))
    one_line_error(cli("sim", "sheet", s), "session.json", "K")
    (s / "session.json").write_text("{not json")
    one_line_error(cli("sim", "sheet", s), "session.json")


def test_session_into_another_sessions_folder_is_refused(cli_session):
    before = (cli_session / "session.json").read_bytes()
    res = cli("capture", "run", "--sim", "--scene", "single/06", "--steps", "2", "--step-deg", "90",
              "--arm-positions", "1", "--width", "96", "--height", "72", "--out", cli_session, "--yes")
    one_line_error(res, "different session")
    assert (cli_session / "session.json").read_bytes() == before


def test_sim_frames(tmp_path):
    res = cli("sim", "frames", "--scene", "multi/02", "--angles", "0,45", "--width", "80", "--height", "60",
              "--out", tmp_path)
    assert res.returncode == 0, res.stderr
    assert len(list(tmp_path.glob("*_rgb.png"))) == 4
    d = read_png(next(tmp_path.glob("*transparent_depth.png")), "depth")
    assert d.dtype == np.uint16 and (d > 0).any()
    one_line_error(cli("sim", "frames", "--arm", "9", "--out", tmp_path), "--arm")


@pytest.mark.timeout(900)  # the whole demo at tiny sizes: ~80 s idle, several times that beside other tests
def test_demo_runs_end_to_end_and_the_method_commands_on_its_output(tmp_path):
    demo = tmp_path / "demo"
    # the smallest session registration handles: 2 arm positions x 12 steps of 5 deg
    opts = ["--scenes", "single/juice_cup_340", "--steps", "12", "--step-deg", "5", "--arm-positions", "2",
            "--width", "160", "--height", "120", "--image-size", "48x64", "--epochs", "1", "--device", "cpu"]
    res = run("demo", "--out", demo, *opts, timeout=840)  # the console script, end to end (the test's limit: 900 s)
    assert res.returncode == 0, res.stderr
    for f in ("demo.json", "models/models_info.json", "models/obj_000012.ply",
              "raw/single_juice_cup_340/session.json", "scenes/single_juice_cup_340/scene_gt.json",
              "scenes/single_juice_cup_340/qa/report.html", "scenes/single_juice_cup_340/work/summary.json",
              "contact_sheet.png", "report.md", "timings.json",
              "runs/hff6dof_simple/loss.png", "runs/hff6dof_simple/last.pt", "results/hff6dof_simple.csv",
              "runs/pvnet_simple/loss.png", "runs/pvnet_simple/last.pt", "results/pvnet_simple.csv",
              "report/scores.json", "report/accuracy_add_s.png"):
        assert (demo / f).exists(), f
    out = res.stderr + res.stdout
    for stage in ("1/6: capture", "2/6: annotate", "3/6: dataset", "4/6: train", "5/6: predict", "6/6: score"):
        assert stage in out, stage
    assert "report:" in out
    # the labels come from the annotation pipeline, and it got them right
    summary = json.loads((demo / "scenes/single_juice_cup_340/work/summary.json").read_text())
    assert all(e["status"] == "ran" for e in summary["stages"].values())
    ev = summary["evaluation"]["all"]
    assert ev["surface_mm"]["median"] < 2.0 and ev["iou_visib"]["median"] > 0.9
    assert len(json.loads((demo / "dataset/scenes/000012/scene_gt.json").read_text())) == 24
    report = (demo / "report.md").read_text()
    assert "ADD(S)" in report and "Annotation" in report and "visible-mask IoU" in report
    assert f"{ev['iou_visib']['median']:.3f}" in report and f"{ev['surface_mm']['median']:.2f} mm" in report
    # HFF6DoF and PVNet side by side: one scorer call, both in the table, each with its run line
    scores = json.loads((demo / "report/scores.json").read_text())
    assert set(scores) == {"hff6dof_simple", "pvnet_simple"}
    for name, s in scores.items():
        assert s["all"]["n"] > 0 and 0.0 <= s["mean"]["add_s"] <= 1.0 and s["run"]["method"] == name.split("_")[0]
    assert "| TDoF20-simple test, mean over objects | HFF6DoF (3D voting + LSQ) | PVNet |" in report
    # HFF6DoF ran the paper's pose recovery, from observed-origin vectors (the report says so)
    assert scores["hff6dof_simple"]["run"]["method_config"]["voting"] == "3d"
    assert scores["hff6dof_simple"]["run"]["method_config"]["vector_origin"] == "observed" and "voting 3d" in report
    assert "- hff6dof_simple: method hff6dof (rgbd)" in report and "- pvnet_simple: method pvnet (rgb)" in report
    assert "runs/pvnet_simple/loss.png" in report
    timings = json.loads((demo / "timings.json").read_text())
    assert set(timings) == {"capture", "annotate", "dataset", "train/hff6dof", "train/pvnet", "predict/hff6dof",
                            "predict/pvnet", "score", "total"}
    # a rerun resumes: every stage is reused
    mtime = (demo / "runs/hff6dof_simple/last.pt").stat().st_mtime
    res = cli("demo", "--out", demo, *opts)
    assert res.returncode == 0, res.stderr
    out = res.stderr + res.stdout
    assert out.count("up to date") == 6 and len(re.findall(r"has its \d+ steps already", out)) == 2
    assert out.count("newer than the run") == 2
    assert (demo / "runs/hff6dof_simple/last.pt").stat().st_mtime == mtime
    # ... and says so once per stage, without a time of this run for what it did not do
    assert re.search(r"capture: 48 RGB-D frames reused \(\d+\.\d s when it ran\)", out), out
    assert re.search(r"annotate: 1 scene reused \(", out) and re.search(r"dataset: \d+ images reused \(", out), out
    assert "RGB-D frames in" not in out and "capture: reused" not in out
    # the total is this run's wall time, not the reused stages' sum
    rerun = json.loads((demo / "timings.json").read_text())
    assert rerun["capture"] == timings["capture"] and rerun["total"] < sum(v for k, v in rerun.items() if k != "total")
    assert f"this run {rerun['total']:.1f} s (reused: capture, annotate, dataset, train/hff6dof, train/pvnet" in out
    assert "1 objects" not in out and "mean (1 object)" in out
    # other data options on the same folder are refused
    # the alias single/12 is the same scene: the data options are compared, not the spelling
    one_line_error(cli("demo", "--out", demo, "--scenes", "single/12", "--steps", "13"), "demo.json", "steps 12 (now 13)")
    one_line_error(cli("demo", "--out", tmp_path / "d2", "--scenes", "multi/08"), "single-object")
    one_line_error(cli("demo", "--out", tmp_path / "d3", "--scenes", "single/99"), "single/99")
    one_line_error(cli("demo", "--out", tmp_path / "d4", "--step-deg", "60"), "--step-deg")
    from tdof20.experiments.demo import run_demo
    from tdof20.errors import TdofError  # an unknown method: one line naming the known ones, nothing written
    with pytest.raises(TdofError, match=r"unknown method 'posecnn' \(known: hff6dof, pvnet"):
        run_demo(tmp_path / "d5", methods=("hff6dof", "posecnn"))
    one_line_error(cli("demo", "--out", tmp_path / "d6", "--methods", "posecnn"), "posecnn", "hff6dof")
    assert not (tmp_path / "d6").exists()
    assert not (tmp_path / "d5").exists()
    root, run_dir = demo / "dataset", demo / "runs/hff6dof_simple"
    # train resumes and extends the demo's run (with its options); predict and score the other way of voting
    res = cli("train", "hff6dof", "--dataset", root, "--split", "simple", "--out", run_dir, "--image-size", "48x64",
              "--epochs", "2", "--batch-size", "4", "--device", "cpu", "--workers", "0", "--set", "vector_origin=observed")
    assert res.returncode == 0, res.stderr
    assert json.loads((run_dir / "history.json").read_text())["epochs"][-1]["epoch"] == 2
    res = cli("predict", run_dir, "--dataset", root, "--split", "simple", "--out", tmp_path / "r3d.csv",
              "--set", "voting=bearing", "--device", "cpu", "--workers", "0")
    assert res.returncode == 0, res.stderr
    res = cli("benchmark", "score", tmp_path / "r3d.csv", demo / "results/hff6dof_simple.csv", "--dataset", root,
              "--split", "simple", "--json", tmp_path / "s.json")
    assert res.returncode == 0, res.stderr
    assert "Table 1" in res.stdout and set(json.loads((tmp_path / "s.json").read_text())) == {"r3d", "hff6dof_simple"}
    # mistakes are one line
    one_line_error(cli("train", "hff6dof", "--dataset", root, "--split", "simple", "--out", run_dir,
                       "--image-size", "64x96", "--device", "cpu", "--set", "vector_origin=observed"),
                   "image_size", "config.json")
    one_line_error(cli("train", "hff6dof", "--dataset", root, "--split", "simple", "--out", run_dir,
                       "--image-size", "48x64", "--device", "cpu"), "vector_origin = observed, now restored")
    one_line_error(cli("train", "hff6dof", "--dataset", root, "--split", "simple", "--out", tmp_path / "r",
                       "--image-size", "big"), "--image-size")
    one_line_error(cli("predict", tmp_path, "--dataset", root, "--split", "simple", "--out", tmp_path / "x.csv"),
                   "not an HFF6DoF run")
    one_line_error(cli("predict", run_dir, "--dataset", root, "--split", "easy", "--out", tmp_path / "x.csv"), "easy")
    one_line_error(cli("benchmark", "score", tmp_path / "none.csv", "--dataset", root, "--split", "simple"), "none.csv")


def test_benchmark_profile(tmp_path):
    res = cli("benchmark", "profile", "hff6dof", "--json", "--device", "cpu", "--height", "64", "--width", "96",
              "--repeats", "1")
    assert res.returncode == 0, res.stderr
    p = json.loads(res.stdout)
    assert p["method"] == "hff6dof" and p["parameters"] == 56_758_992 and abs(p["macs_480x640_G"] - 84.27) < 0.01
    assert p["network_ms"] > 0 and p["end_to_end_ms"] > 0 and p["untrained"] and isinstance(p["poses"], int)
    res = cli("benchmark", "profile", "hff6dof", "--device", "cpu", "--height", "64", "--width", "96", "--runs", "1")
    assert "multiply-adds" in res.stdout and "FPS" in res.stdout
    one_line_error(cli("benchmark", "profile", "posecnn"), "posecnn", "hff6dof")


def test_dataset_commands(tmp_path):
    raw = tmp_path / "raw"
    assert cli("capture", "run", "--sim", "--scene", "multi/02", "--steps", "2", "--step-deg", "90",
               "--arm-positions", "1", "--width", "64", "--height", "48", "--out", raw, "--yes").returncode == 0
    assert cli("sim", "label", raw, "--out", tmp_path / "lab").returncode == 0
    res = cli("dataset", "build", tmp_path / "lab", "--out", tmp_path / "root")
    assert res.returncode == 0, res.stderr
    res = cli("dataset", "stats", tmp_path / "root", "--json")
    assert json.loads(res.stdout)["splits"]["hard_test"] == 2
    res = cli("dataset", "pack", tmp_path / "root", "--split", "hard", "--part", "test", "--out", tmp_path / "t.h5")
    assert res.returncode == 0 and (tmp_path / "t.h5").exists()
    one_line_error(cli("dataset", "pack", tmp_path / "root", "--split", "medium", "--part", "test",
                       "--out", tmp_path / "u.h5"), "medium")
    one_line_error(cli("dataset", "stats", tmp_path / "nothing"), str(tmp_path / "nothing"), "no such dataset folder")


def test_a_failed_jobs_progress_bar_is_cleared_before_its_error(capsys):
    """A job that fails leaves its one-line error, not a half-done bar above it; a finished job's
    bar stays (a file or pipe sees its last state)."""
    from tdof20.progress import progress

    with pytest.raises(RuntimeError):
        with progress(True, unit="img") as bar:
            t = bar.add_task("packing", total=10)
            bar.advance(t, 3)
            raise RuntimeError("a truncated image")
    assert "packing" not in capsys.readouterr().err
    with progress(True, unit="img") as bar:
        t = bar.add_task("packing", total=2)
        bar.advance(t, 2)
    assert "packing" in capsys.readouterr().err
