"""``tdof20 ARGS`` run in the test's own process, for the CLI tests whose subject is not the
subprocess (each ``python -m tdof20.cli`` costs ~2-3 s of imports)."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest

from tdof20.cli import main


def run_here(capfd, monkeypatch, *args) -> SimpleNamespace:
    """``tdof20 ARGS`` through the console script's entry point (:func:`tdof20.cli.main`, with its
    one-line error handling): its exit code and what it printed, captured at the file-descriptor
    level (as a subprocess's pipes would hold it, workers' output included), with ``returncode``,
    ``stdout`` and ``stderr`` as :func:`subprocess.run` gives them. ``capfd`` and ``monkeypatch``:
    the calling test's fixtures."""
    capfd.readouterr()
    monkeypatch.setattr(sys, "argv", ["tdof20", *map(str, args)])
    with pytest.raises(SystemExit) as e:
        main()
    out = capfd.readouterr()
    code = e.value.code
    return SimpleNamespace(returncode=code if isinstance(code, int) else (0 if code is None else 1),
                           stdout=out.out, stderr=out.err)
