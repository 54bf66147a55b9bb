"""The options of the model build (``[build]`` of the annotate config): surface, symmetry test,
samples and keypoints, the unseen inside of vessels (:mod:`~tdof20.annotate.modelbuild`,
:mod:`~tdof20.annotate.symmetry`)."""

from __future__ import annotations

from dataclasses import dataclass

from tdof20.config import check_ranges

__all__ = ["ModelBuildConfig"]


@dataclass(frozen=True)
class ModelBuildConfig:
    min_points: int = 500              # a smaller cluster is an error
    normal_knn: int = 24               # neighbours of the PCA normal
    poisson_depth: int = 9             # octree depth of screened Poisson (cell ~ 1.1*size/2^depth)
    poisson_samples_per_node: float = 1.5
    poisson_point_weight: float = 4.0  # screening: how strongly the surface passes through the points
    poisson_threads: int = 1           # measured: 2.5 s with 1 thread, 25-150 s with 2 on a busy 2-core machine
    base_band_mm: float = 3.0          # the footprint: hull of the points this close above the lowest
    base_max_gap_mm: float = 12.0      # the bottom is closed when the lowest point is this close to the table
    trim_mm: float = 3.0               # faces farther than this from every input point are cut
    target_faces: int = 20000          # decimation target
    sym_tol_mm: float = 1.5            # a turned sample within this of the surface is "on" it
    sym_max_fraction: float = 0.008    # at most this fraction of turned samples may be off
    sym_samples: int = 6000            # surface samples of the symmetry test
    sym_open_deg: float = 35.0         # half-angle of the cone that must see out of a sample (outer surface)
    n_samples: int = 10000             # Monte-Carlo samples written with the model
    n_keypoints: int = 9
    seed: int = 0
    inner_walls: bool = True           # give the unseen inside of a vessel a wall (module docstring)
    wall_max_mm: float = 8.0           # seen "walls" thicker than this (handles, stems, bases) are not walls
    wall_search_mm: float = 25.0       # a point whose inward ray meets no data this far faces an unseen inside ...
    wall_min_share: float = 0.15       # ... when such points make a connected region of this share of the points

    def __post_init__(self) -> None:
        check_ranges(self, "build", positive=(
            "min_points", "normal_knn", "poisson_depth", "poisson_samples_per_node", "poisson_point_weight",
            "poisson_threads", "base_band_mm", "base_max_gap_mm", "trim_mm", "target_faces", "sym_tol_mm",
            "sym_samples", "sym_open_deg", "n_samples", "n_keypoints", "wall_max_mm", "wall_search_mm"),
            non_negative=("seed",), fraction=("sym_max_fraction", "wall_min_share"))
