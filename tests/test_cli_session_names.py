"""``tdof20 annotate RAW --out SCENE`` when the raw session folder is named like one of annotate's
subcommands (``review``, ``evaluate``): the folder is the session, since no subcommand takes --out."""

import json

import pytest
from typer.testing import CliRunner

from tdof20.cli import app


@pytest.mark.parametrize("name", ["review", "evaluate"])
def test_a_session_folder_named_like_a_subcommand_is_annotated(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    (tmp_path / name).mkdir()
    (tmp_path / name / "session.json").write_text(json.dumps({"not": "a session"}))
    res = CliRunner().invoke(app, ["annotate", name, "--out", "scene"])
    said = res.output + str(res.exception or "")  # the TdofError main() prints as one line
    assert res.exit_code != 0
    # the pipeline read the folder as a raw session (and refused its session.json in one line) ...
    assert f"{name}/session.json" in said and "missing field" in said
    # ... and nothing took it for the subcommand
    assert "No such option" not in said
    assert not (tmp_path / "scene").exists() or not any((tmp_path / "scene").iterdir())


def test_without_a_session_the_subcommand_stays_itself(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "review").mkdir()  # a folder, but no raw session in it
    res = CliRunner().invoke(app, ["annotate", "review", "--out", "scene"])
    assert res.exit_code != 0 and "No such option" in res.output
