"""What the import tests share: an import of a TDoF20 release stopped part-way (Ctrl-C while it
reads a frame's mask), as a user interrupting it would leave it."""

from __future__ import annotations

from pathlib import Path

import pytest

from tdof20.dataset import importer
from tdof20.dataset.importer import import_tdof20


def interrupt_import(src: Path, out: Path, monkeypatch, masks_read: int = 3 + 5) -> None:
    """Import ``src`` into ``out`` and stop it with a KeyboardInterrupt at the ``masks_read``-th
    mask read (default: 3 scene pre-checks, then the 5th frame: scene 2, frame 2), each frame
    flushed as it is written; the reader is put back afterwards."""
    calls = {"n": 0}
    real = importer.read_class_mask

    def dying(path):
        calls["n"] += 1
        if calls["n"] == masks_read:
            raise KeyboardInterrupt
        return real(path)

    monkeypatch.setattr(importer, "read_class_mask", dying)
    monkeypatch.setattr(importer, "FLUSH_EVERY", 1)
    with pytest.raises(KeyboardInterrupt):
        import_tdof20(src, out, show_progress=False)
    monkeypatch.setattr(importer, "read_class_mask", real)
