"""The command line's output where a person or a program reads it: piped or redirected output is not
wrapped, ``--json`` for machines, help without ``<bool>``, progress for long jobs, errors that name
the option typed. The real console script in a subprocess, stdout and stderr piped."""

import json
import os
import re
import subprocess
import sys

import pytest

EXE = [sys.executable, "-m", "tdof20.cli"]


def run(*args, columns=None, timeout=300):
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "TERMINAL_WIDTH")}
    if columns is not None:
        env["COLUMNS"] = str(columns)
    return subprocess.run(EXE + [str(a) for a in args], capture_output=True, text=True, env=env, timeout=timeout)


def test_piped_objects_list_is_not_wrapped():
    """`tdof20 objects list > f`: whole headers (not "capaci…"), one line per object."""
    res = run("objects", "list")
    assert res.returncode == 0, res.stderr
    assert "…" not in res.stdout
    header = [ln for ln in res.stdout.splitlines() if "capacity ml" in ln]
    assert len(header) == 1 and all(h in header[0] for h in ("size x*y*z", "diameter", "symmetry", "faces"))
    rows = [ln for ln in res.stdout.splitlines() if re.match(r"^│\s+\d+ │", ln)]
    assert len(rows) == 20, res.stdout
    assert "cube glass (square section, rounded edges)" in res.stdout  # a long kind stays on its row


def test_objects_list_json():
    res = run("objects", "list", "--json")
    assert res.returncode == 0, res.stderr
    objs = json.loads(res.stdout)
    assert [o["id"] for o in objs] == list(range(1, 21))
    cube = objs[0]
    assert cube["name"] == "cube_136" and len(cube["size_mm"]) == 3 and cube["symmetry"] == "discrete 4-fold"
    assert round(cube["capacity_ml"]) == 136 and cube["faces"] > 0


@pytest.mark.parametrize("columns", [None, 200])
@pytest.mark.parametrize("cmd", [(), ("objects", "list"), ("demo",), ("annotate",)])
def test_help_shows_no_bool_for_flags(cmd, columns):
    """Flags (--help, --json, --train/--no-train) take no value: the help shows no `<bool>`."""
    res = run(*cmd, "--help", columns=columns)
    assert res.returncode == 0, res.stderr
    assert "--help" in res.stdout and "<bool>" not in res.stdout, res.stdout
    if cmd == ("demo",):
        assert re.search(r"--train\s+--no-train\s+train, predict", res.stdout), res.stdout
        assert "<int>" in res.stdout  # options with a value keep their type


def test_unknown_scene_names_the_option(tmp_path):
    for args in (("sim", "frames", "--scene", "single/nosuch", "--out", tmp_path / "f"),
                 ("capture", "plan", "--sim", "--scene", "multi/99")):
        res = run(*args)
        assert res.returncode == 2
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: --scene:"), res.stderr
        assert "session.scene_id" not in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "f").exists()


@pytest.mark.timeout(600)
def test_profile_all_prints_a_line_per_method():
    """`benchmark profile all` takes minutes on a CPU: a line per method on stderr as it goes; the
    JSON on stdout stays JSON."""
    res = run("benchmark", "profile", "all", "--json", "--height", "32", "--width", "32", "--repeats", "1",
              "--device", "cpu", timeout=600)
    assert res.returncode == 0, res.stderr
    table = json.loads(res.stdout)
    names = [p["method"] for p in table]
    assert len(names) >= 2
    for i, name in enumerate(names, 1):
        assert f"profiling {name} ({i}/{len(names)}) ..." in res.stderr, res.stderr
        assert re.search(rf"profiled {name} in \d+\.\d s", res.stderr), res.stderr


def _piped(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 0, res.stderr
    return res


def test_piped_log_lines_stay_whole():
    """A log line piped stays one line (not "visible IoU \\n0.992" at 80 columns)."""
    res = _piped("from tdof20.progress import console\n"
                 "console.print('annotate: ' + ', '.join(f'visible IoU {0.992 + i / 1000:.3f}' for i in range(12)))\n"
                 "console.print('x ' * 100)\n")
    err = res.stderr.splitlines()
    assert len(err) == 2 and err[0].count("visible IoU") == 12 and err[1].strip() == ("x " * 100).strip(), err


def test_piped_rules_are_as_wide_as_their_title():
    """The demo's stage headers piped: as wide as the title (80 at least), not as an unwrapped console."""
    res = _piped("from tdof20.progress import rule\n"
                 "rule('[bold]demo 1/6: capture[/bold] — 1 simulated session', align='left')\n"
                 "rule('x' * 100)\n")
    err = res.stderr.splitlines()
    assert len(err) == 2 and err[0].startswith("demo 1/6: capture — 1 simulated session ─") and len(err[0]) == 80
    assert len(err[1]) == 106 and "x" * 100 in err[1]


@pytest.mark.parametrize("columns", [160, 250])
def test_help_descriptions_do_not_break_mid_sentence(columns):
    """A docstring's line breaks are not kept in the help: at a width that holds the sentence, the
    sentence is on one line (it broke after "results CSV with" and "predict and" at any width)."""
    res = run("--help", columns=columns)
    assert res.returncode == 0, res.stderr
    assert "writes the results CSV with per-image times" in res.stdout
    res = run("predict", "--help", columns=columns)
    assert "writes the results CSV with per-image times" in res.stdout
