"""The dataset reader's stable import point: the names of :mod:`tdof20.dataset.layouts`, where one
reader class per layout (tdof20's, standard BOP) sits behind one interface (docs/dataset.md).

    ds = open_dataset(ROOT)                        # detects the layout
    ds.obj_ids, ds.object_name(5)                  # [1, 5, 30], "obj_000005"
    ds.frames("simple", "train")                   # [(scene_id, im_id), ...] of a split part
    ds.scene(28).rgb(0); ds.depth_mm(28, 0, "restored")

``Dataset`` is the readers' abstract base class (:class:`~tdof20.dataset.layouts.base.DatasetReader`).
"""

from __future__ import annotations

from tdof20.dataset.layouts import LAYOUTS, NOT_A_DATASET, detect_layout, open_dataset, register_layout
from tdof20.dataset.layouts.base import (CACHE_DIR, DEPTH_DIRS, DEPTH_MODES, KEYPOINTS_FILE, NAMES_FILE, PARTS,
                                         DatasetReader, composite_model_depth)
from tdof20.dataset.layouts.bop import BOP_INFO, BOP_TARGETS, SPLIT_FOLDER, bop_split_folders
from tdof20.dataset.layouts.tdof20 import DATASET_INFO

Dataset = DatasetReader

__all__ = ["BOP_INFO", "BOP_TARGETS", "CACHE_DIR", "DATASET_INFO", "DEPTH_DIRS", "DEPTH_MODES", "Dataset",
           "DatasetReader", "KEYPOINTS_FILE", "LAYOUTS", "NAMES_FILE", "NOT_A_DATASET", "PARTS", "SPLIT_FOLDER",
           "bop_split_folders", "composite_model_depth", "detect_layout", "open_dataset", "register_layout"]
