"""The house's shape (docs/architecture.md): layers importing only downwards, no import cycles, a
fast torch-free ``tdof20 --help``, and scoring unchanged by moves (a byte-for-byte golden file)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_layers_import_only_downwards():
    """import-linter's contract in pyproject.toml ([tool.importlinter]): a lower layer never imports a
    higher one, at the top of a module or inside a function."""
    exe = Path(sys.executable).with_name("lint-imports")
    res = subprocess.run([str(exe), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "broken" in res.stdout and "0 broken" in res.stdout


def _cycles() -> list[list[str]]:
    import grimp

    g = grimp.build_graph("tdof20", cache_dir=None)
    edges = {m: set(g.find_modules_directly_imported_by(m)) for m in g.modules}
    # a package's __init__ may import its own submodules (re-exports): that is not a cycle of concepts
    for m in edges:
        edges[m] = {i for i in edges[m] if not i.startswith(m + ".")}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    assert _cycles() == []


def test_help_imports_no_torch_nor_open3d():
    code = ("import sys\nfrom typer.testing import CliRunner\nfrom tdof20.cli import app\n"
            "r = CliRunner().invoke(app, ['--help'])\nassert r.exit_code == 0, r.output\n"
            "heavy = [m for m in ('torch', 'open3d', 'ray', 'depthai') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_scores_of_a_fixed_results_file_are_unchanged(tmp_path):
    """tests/golden/score_bop_standard.json was written by tests/golden/make_golden.py with the code
    before the architecture move (issue 21), and written again only for a deliberate change of a
    figure (issue 22: VSD renders at pixel centres, as bop_toolkit; ar_vsd 0.28583 -> 0.28306, the
    other metrics unchanged): the same dataset and results scored today give the same JSON, byte for
    byte. A change that moves a figure on purpose rewrites it and says so in its commit."""
    sys.path.insert(0, str(ROOT))
    from tests.golden.make_golden import make_inputs

    ds, results = make_inputs(tmp_path)
    out = tmp_path / "score.json"
    res = subprocess.run([sys.executable, "-m", "tdof20", "benchmark", "score", str(results), "--dataset", str(ds),
                          "--split", "test", "--json", str(out)], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    golden = ROOT / "tests" / "golden" / "score_bop_standard.json"
    assert json.loads(out.read_text())["all"]["n"] == 36
    assert out.read_bytes() == golden.read_bytes()
