"""One TOML -> typed dataclass loader for every stage's options (capture, annotate, train).

    cfg = load_config_file(CaptureConfig, "rig.toml")     # read, convert, check: one-line errors
    cfg = config_from_data(AnnotateConfig, data, source)  # the same from a parsed document

Strict: an unknown table or key is an error naming the file and listing the known keys; a value of
the wrong type names the option (``[register] voxel_sizes_mm[1]: must be a number, got 'a'``).
A dataclass checks its own values in ``__post_init__`` (with :func:`check_ranges` for the common
"> 0" / ">= 0" / "fraction" rules) and raises :class:`TdofError`; the loader puts the file's name
in front, once. A field named ``source`` is filled with the file's path, never read from it.

Supported field types: bool, int, float, str, nested dataclasses (TOML tables), ``tuple[X, ...]``
(TOML arrays, nested too), a bare ``tuple`` (numbers) and ``X | None`` (TOML has no null: a value
given is an X; leaving the key out keeps the default).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, Iterable, NoReturn, TypeVar

from tdof20.errors import TdofError
from tdof20.formats.io import read_toml

T = TypeVar("T")

__all__ = ["ConfigError", "check_ranges", "config_from_data", "convert", "fail", "load_config_file"]


class ConfigError(TdofError):
    """A config value that is wrong (its message names the option; the loader adds the file)."""


def fail(src: str, where: str, msg: str) -> NoReturn:
    """Raise the one-line TdofError ``src: where: msg`` (either may be empty)."""
    raise TdofError(f"{where}: {msg}" if where else msg, src or None)


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def convert(value: Any, tp: Any, src: str = "", where: str = "") -> Any:
    """``value`` (parsed TOML) as type ``tp``; a mismatch is a TdofError naming ``src`` and ``where``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1:  # pragma: no cover - programming error
            raise TypeError(f"unsupported config type {tp}")
        return convert(value, inner[0], src, where)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            fail(src, where, f"must be a table, got {type(value).__name__}")
        return _build(tp, value, src, where)
    if tp is bool:
        if not isinstance(value, bool):
            fail(src, where, f"must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail(src, where, f"must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(src, where, f"must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            fail(src, where, f"must be a string, got {value!r}")
        return value
    if tp is tuple or origin is tuple:
        if not isinstance(value, (list, tuple)):
            fail(src, where, f"must be a list, got {value!r}")
        inner = args[0] if args else float
        return tuple(convert(v, inner, src, f"{where}[{i}]") for i, v in enumerate(value))
    raise TypeError(f"unsupported config type {tp}")  # pragma: no cover - programming error


def _build(cls: type, data: dict, src: str, where: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init and f.name != "source"]
    for key in data:
        if key not in names:
            fail(src, "", f"unknown option '{_join(where, key)}' (known: {', '.join(sorted(names))})")
    kw = {k: convert(v, hints[k], src, _join(where, k)) for k, v in data.items()}
    if src and "source" in {f.name for f in dataclasses.fields(cls)}:
        kw["source"] = src
    try:
        return cls(**kw)
    except TdofError as e:
        if e.path is not None:   # the dataclass named the file itself
            raise
        text = str(e)
        fail(src, f"[{where}]" if where and not text.startswith(where) else "", text)
    except (TypeError, ValueError) as e:
        fail(src, f"[{where}]" if where else "", f"invalid options ({e})")


def config_from_data(cls: type[T], data: Any, source: str | Path = "") -> T:
    """An instance of the dataclass ``cls`` from a parsed TOML document (strict; one-line errors
    naming ``source``)."""
    src = str(source) if source else ""
    if not isinstance(data, dict):
        fail(src, "", "must be a TOML document of tables")
    return _build(cls, data, src, "")


def load_config_file(cls: type[T], path: str | Path, what: str = "config file") -> T:
    """Read a TOML file into the dataclass ``cls``; a missing, unreadable or malformed file, an
    unknown key or a wrong value is one TdofError naming the file."""
    return config_from_data(cls, read_toml(path, what), str(path))


def check_ranges(obj: Any, section: str = "", positive: Iterable[str] = (), non_negative: Iterable[str] = (),
                 fraction: Iterable[str] = ()) -> None:
    """Raise a :class:`TdofError` naming ``section.field`` when a number (or any element of a tuple
    of numbers) of ``obj`` is not > 0 (``positive``), not >= 0 (``non_negative``) or outside
    [0, 1] (``fraction``). ``None`` values (options left to a default rule) pass."""
    rules = [(n, "> 0", lambda v: v > 0) for n in positive]
    rules += [(n, ">= 0", lambda v: v >= 0) for n in non_negative]
    rules += [(n, "in [0, 1]", lambda v: 0 <= v <= 1) for n in fraction]
    for name, text, ok in rules:
        value = getattr(obj, name)
        if value is None:
            continue
        values = value if isinstance(value, tuple) else (value,)
        if isinstance(value, tuple) and not value:
            raise ConfigError(f"{_join(section, name)} must not be empty")
        for v in values:
            if not ok(v):
                shown = list(value) if isinstance(value, tuple) else value
                raise ConfigError(f"{_join(section, name)} must be {text}, got {shown}")
