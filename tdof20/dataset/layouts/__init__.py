"""Dataset layouts: one reader class per layout behind one interface
(:class:`~tdof20.dataset.layouts.base.DatasetReader`), and the registry that opens a folder with
the right one (docs/dataset.md).

    ds = open_dataset(ROOT)                        # detects the layout
    ds.layout, ds.obj_ids, ds.object_name(5)       # "tdof20" | "bop", [1, 5, 30], "obj_000005"
    ds.frames("simple", "train")                   # [(scene_id, im_id), ...] of a split part
    ds.scene(28).rgb(0); ds.depth_mm(28, 0, "restored")

The layouts: :class:`~tdof20.dataset.layouts.tdof20.Tdof20Reader` (tdof20's own, ``dataset build``)
and :class:`~tdof20.dataset.layouts.bop.BopReader` (the BOP toolkit's standard one). A new layout
is one module with a :class:`DatasetReader` subclass (its ``layout`` name, ``detect(root)`` and
the abstract members) and one line below: ``register_layout(MyReader)``. Layouts are asked in
the order they were registered; the first whose ``detect`` says yes reads the folder.
"""

from __future__ import annotations

from pathlib import Path

from tdof20.dataset.layouts.base import DatasetReader
from tdof20.dataset.layouts.bop import BopReader
from tdof20.dataset.layouts.tdof20 import Tdof20Reader
from tdof20.errors import TdofError

#: the registered layouts, name -> reader class, in the order they are asked
LAYOUTS: dict[str, type[DatasetReader]] = {}
NOT_A_DATASET = ("not a dataset: neither a tdof20 dataset (dataset_info.json) nor a BOP dataset "
                 "(split folders with scenes)")


def register_layout(cls: type[DatasetReader]) -> type[DatasetReader]:
    """Add a reader class to :data:`LAYOUTS` under its ``layout`` name (usable as a class decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, DatasetReader)):
        raise TypeError(f"a layout is a DatasetReader subclass, got {cls!r}")
    name = getattr(cls, "layout", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"{cls.__name__} needs a 'layout' name")
    if LAYOUTS.get(name, cls) is not cls:
        raise ValueError(f"the layout '{name}' is already registered ({LAYOUTS[name].__name__})")
    LAYOUTS[name] = cls
    return cls


register_layout(Tdof20Reader)
register_layout(BopReader)


def detect_layout(root: str | Path) -> str:
    """The name of the first registered layout whose ``detect`` accepts ``root``; a one-line
    TdofError for a missing folder or a folder that is none."""
    root = Path(root)
    if not root.is_dir():
        raise TdofError("no such dataset folder", root)
    for name, cls in LAYOUTS.items():
        if cls.detect(root):
            return name
    raise TdofError(NOT_A_DATASET, root)


def open_dataset(root: str | Path, split: str | None = None, *, names: str | Path | None = None,
                 cache_dir: str | Path | None = None) -> DatasetReader:
    """The dataset at ``root``, read by its layout's class. ``split``: the split the caller works on
    (tdof20: a protocol such as 'simple'; BOP: a split folder such as 'test'), the default of the
    methods that take one. ``names``: a JSON file {"<obj_id>": name} naming the objects.
    ``cache_dir``: where rendered restored depth goes (default ROOT/.cache)."""
    root = Path(root)
    ds = LAYOUTS[detect_layout(root)](root, names=names, cache_dir=cache_dir)
    if split is not None:
        ds.split = ds.check_split(split)
    return ds


__all__ = ["LAYOUTS", "NOT_A_DATASET", "BopReader", "DatasetReader", "Tdof20Reader", "detect_layout", "open_dataset",
           "register_layout"]
