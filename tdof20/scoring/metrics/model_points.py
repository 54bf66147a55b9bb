"""One object's model points as the fast kernels see them: :class:`ModelPoints` and what it
precomputes lazily (centred float32 monomials, a KD-tree, :class:`Clusters` of points, a
:class:`DistanceGrid` and :class:`PointTree` s), and :class:`Bounds`, the per-pose intervals the
kernels return (:mod:`tdof20.scoring.metrics.kernels` for ADD, 2D projection and ADD-S,
:mod:`tdof20.scoring.metrics.mssd_mspd` for MSSD and MSPD).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy.spatial is imported on first use: importing the scorer (as the CLI does) stays light
    from scipy.spatial import cKDTree

from tdof20.scoring.metrics.reference import _pts


@dataclass
class Clusters:
    """A partition of the model points into compact clusters (recursive median splits)."""

    label: np.ndarray  # (N,) cluster of each point
    n: np.ndarray  # (M,) points per cluster
    c: np.ndarray  # (M,3) centroids
    a: np.ndarray  # (M,) mean |p - c|
    s2: np.ndarray  # (M,) mean |p - c|^2
    r: np.ndarray  # (M,) max |p - c|

    @property
    def M(self) -> int:
        return len(self.n)

    @cached_property
    def w(self) -> np.ndarray:
        return self.n / self.n.sum()

    @cached_property
    def cT32(self) -> np.ndarray:
        return np.ascontiguousarray(self.c.T, dtype=np.float32)


def _median_splits(P: np.ndarray, leaf: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Split ``P`` (N,3) level by level, every segment longer than ``leaf`` at the median of its
    longest box side. Returns the point order and the segment bounds of every level (the first
    ``[0, N]``, the last the leaves) into it."""
    N = len(P)
    order = np.arange(N)
    cuts = np.array([0, N])
    history = [cuts]
    while True:
        starts, sizes = cuts[:-1], np.diff(cuts)
        split = sizes > leaf
        if not split.any():
            break
        seg = np.repeat(np.arange(len(sizes)), sizes)
        X = P[order]
        ext = np.maximum.reduceat(X, starts) - np.minimum.reduceat(X, starts)
        key = X[np.arange(N), np.argmax(ext, axis=1)[seg]]
        order = order[np.lexsort((key, seg))]
        cuts = np.sort(np.concatenate([cuts, starts[split] + sizes[split] // 2]))
        history.append(cuts)
    return order, history


def make_clusters(P: np.ndarray, leaf: int) -> Clusters:
    """Split ``P`` (N,3) recursively at the median of its longest box side into clusters of at
    most ``leaf`` points (all segments of a level split at once)."""
    P = _pts(P)
    N = len(P)
    order, history = _median_splits(P, leaf)
    cuts = history[-1]
    M = len(cuts) - 1
    label = np.empty(N, dtype=np.int64)
    label[order] = np.repeat(np.arange(M), np.diff(cuts))
    n = np.bincount(label, minlength=M).astype(np.float64)
    c = np.stack([np.bincount(label, P[:, i], M) for i in range(3)], axis=1) / n[:, None]
    dn = np.sqrt(((P - c[label]) ** 2).sum(1))
    r = np.zeros(M)
    np.maximum.at(r, label, dn)
    return Clusters(label, n, c, np.bincount(label, dn, M) / n, np.bincount(label, dn * dn, M) / n, r)


@dataclass
class DistanceGrid:
    """Exact distance to the point set and its nearest point at the nodes of a regular grid
    (node (i,j,k) at lo + h (i,j,k)); float32 planar copies for the kernels."""

    lo: np.ndarray  # (3,)
    h: float
    shape: np.ndarray  # (3,) int
    node: np.ndarray  # (G,4) float32: the nearest point's x, y, z and the distance

    @property
    def hi(self) -> np.ndarray:
        return self.lo + self.h * (self.shape - 1)

    @cached_property
    def strides(self) -> np.ndarray:
        s = self.shape
        return np.array([s[1] * s[2], s[2], 1], dtype=np.float32)

    @cached_property
    def dist(self) -> np.ndarray:
        return np.ascontiguousarray(self.node[:, 3])

    @cached_property
    def d2(self) -> np.ndarray:
        return self.dist * self.dist


def make_grid(P: np.ndarray, tree: cKDTree, margin: float, max_nodes: int, min_h: float) -> DistanceGrid:
    """The :class:`DistanceGrid` of ``P`` (``tree`` on it) over its box grown by ``margin``: about
    ``max_nodes`` nodes, spaced at least ``min_h`` apart."""
    lo = P.min(0) - margin
    ext = P.max(0) + margin - lo
    h = max(min_h, float(np.cbrt(np.prod(ext) / max_nodes)))
    shape = np.ceil(ext / h).astype(np.int64) + 1
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d, idx = tree.query(G, workers=-1)
    node = np.concatenate([P[idx], d[:, None]], axis=1).astype(np.float32)
    return DistanceGrid(lo, h, shape, node)


@dataclass
class TreeLevel:
    """One level of a :class:`PointTree`: per node its representative, radius and children."""

    rep: np.ndarray  # (n,) index (into the tree's points) of each node's representative point
    r: np.ndarray  # (n,) largest distance from the representative to the node's points
    child_start: np.ndarray  # (n,) first child in the next level
    child_count: np.ndarray  # (n,)


@dataclass
class PointTree:
    """Nested clusters of points (recursive median splits along the longest box side): level 0
    has about ``first`` nodes, each next level splits every node into up to ``branching``
    children, the last level holds single points (r = 0). A node's representative is its point
    nearest to the node's centroid."""

    pts: np.ndarray
    levels: list
    screen: np.ndarray = None  # (k,) indices of a few spread-out points (farthest-point order)


def _spread_points(P: np.ndarray, k: int) -> np.ndarray:
    """Indices of k points of P by farthest-point sampling, from the point farthest from the centroid."""
    i = int(np.argmax(((P - P.mean(0)) ** 2).sum(1)))
    out = [i]
    d = ((P - P[i]) ** 2).sum(1)
    for _ in range(min(k, len(P)) - 1):
        i = int(np.argmax(d))
        out.append(i)
        d = np.minimum(d, ((P - P[i]) ** 2).sum(1))
    return np.array(out, np.int64)


def make_point_tree(P: np.ndarray, first: int = 32, branching: int = 2) -> PointTree:
    P = _pts(P)
    order, history = _median_splits(P, 1)
    D = len(history) - 1
    step = max(1, int(round(np.log2(branching))))
    d0 = min(D, max(0, int(np.ceil(np.log2(max(1, first))))))
    depths = list(range(d0, D, step)) + [D]
    X = P[order]
    levels = []
    for li, dep in enumerate(depths):
        c = history[dep]
        starts, sizes = c[:-1], np.diff(c)
        seg = np.repeat(np.arange(len(sizes)), sizes)
        cen = np.add.reduceat(X, starts) / sizes[:, None]
        dc = ((X - cen[seg]) ** 2).sum(1)
        srt = np.lexsort((dc, seg))
        rep = order[srt[starts]]
        r = np.sqrt(np.maximum.reduceat(((X - P[rep][seg]) ** 2).sum(1), starts))
        if li + 1 < len(depths):
            nxt = history[depths[li + 1]]
            cs = np.searchsorted(nxt, starts)
            cc = np.searchsorted(nxt, c[1:]) - cs
        else:
            cs = cc = np.zeros(len(starts), np.int64)
        levels.append(TreeLevel(rep, r, cs, cc))
    return PointTree(P, levels, _spread_points(P, 8))


@dataclass(eq=False)
class ModelPoints:
    """One object's model points and what the fast kernels precompute from them (built lazily):
    centred float32 monomials for ADD and proj2d, a KD-tree, two cluster levels and a distance
    grid for ADD-S, the symmetries and two point trees (hull vertices, all points) for MSSD and MSPD."""

    pts: np.ndarray  # (N,3) mm
    diameter: float
    symmetric: bool = False
    coarse_leaf: int = 0  # 0: automatic, about 96 clusters
    fine_leaf: int = 6
    grid_nodes: int = 40_000
    grid_margin: float = 0.15  # of the diameter (at least 10 mm)
    sym_R: np.ndarray | None = None  # (S,3,3) symmetry transformations (BOP discretisation; MSSD, MSPD)
    sym_t: np.ndarray | None = None  # (S,3); None: the identity only

    def __post_init__(self):
        self.pts = np.ascontiguousarray(_pts(self.pts))

    @cached_property
    def syms(self) -> tuple[np.ndarray, np.ndarray]:
        """(R (S,3,3), t (S,3)) symmetry transformations, the identity alone when none are given."""
        if self.sym_R is None:
            return np.eye(3)[None], np.zeros((1, 3))
        return np.asarray(self.sym_R, np.float64).reshape(-1, 3, 3), np.asarray(self.sym_t, np.float64).reshape(-1, 3)

    @cached_property
    def hull_idx(self) -> np.ndarray:
        """Indices of the points on the convex hull (all points where the hull is degenerate)."""
        from scipy.spatial import ConvexHull, QhullError

        try:
            return np.sort(ConvexHull(self.pts).vertices)
        except (QhullError, ValueError):
            return np.arange(self.n)

    @cached_property
    def hull_tree(self) -> PointTree:
        """Nested clusters of the hull vertices (MSSD: a convex function peaks on the hull)."""
        return make_point_tree(self.pts[self.hull_idx])

    @cached_property
    def pts_tree(self) -> PointTree:
        """Nested clusters of all points (MSPD)."""
        return make_point_tree(self.pts)

    @cached_property
    def sym_centre(self) -> tuple[np.ndarray, float]:
        """(centre, radius) of a ball holding the symmetric images R_s m + t_s of :attr:`centre`."""
        R, t = self.syms
        c = np.einsum("sij,j->si", R, self.centre) + t
        m = 0.5 * (c.min(0) + c.max(0))
        return m, float(np.sqrt(((c - m) ** 2).sum(1).max()))

    @property
    def n(self) -> int:
        return len(self.pts)

    @cached_property
    def centre(self) -> np.ndarray:
        return 0.5 * (self.pts.min(0) + self.pts.max(0))

    @cached_property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pts.min(0), self.pts.max(0)

    @cached_property
    def radius(self) -> float:
        """Largest distance of a point from ``centre``."""
        return float(np.sqrt(((self.pts - self.centre) ** 2).sum(1).max()))

    @cached_property
    def tree(self) -> cKDTree:
        from scipy.spatial import cKDTree

        return cKDTree(self.pts, leafsize=32)

    @cached_property
    def quad(self) -> np.ndarray:
        """(10,N) float32 monomials of the centred points: x^2 y^2 z^2 2xy 2xz 2yz 2x 2y 2z 1."""
        x, y, z = (self.pts - self.centre).T
        return np.ascontiguousarray(np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z,
                                              2 * x, 2 * y, 2 * z, np.ones_like(x)]), dtype=np.float32)

    @cached_property
    def hom(self) -> np.ndarray:
        """(4,N) float32 homogeneous centred points."""
        x, y, z = (self.pts - self.centre).T
        return np.ascontiguousarray(np.stack([x, y, z, np.ones_like(x)]), dtype=np.float32)

    @cached_property
    def hom_sample(self) -> np.ndarray:
        """(4,512) a fixed random subset of :attr:`hom` (estimates of 2D projection errors)."""
        if self.n <= 512:
            return self.hom
        idx = np.random.default_rng(0).choice(self.n, 512, replace=False)
        return np.ascontiguousarray(self.hom[:, np.sort(idx)])

    @cached_property
    def coarse(self) -> Clusters:
        return make_clusters(self.pts, self.coarse_leaf or max(8, -(-self.n // 96)))

    @cached_property
    def proj(self) -> Clusters:
        """About 32 clusters (2D projection bounds)."""
        return make_clusters(self.pts, max(8, -(-self.n // 32)))

    @cached_property
    def fine(self) -> Clusters:
        return make_clusters(self.pts, self.fine_leaf)

    @cached_property
    def grid(self) -> DistanceGrid:
        margin = max(10.0, self.grid_margin * self.diameter)
        return make_grid(self.pts, self.tree, margin, self.grid_nodes, self.diameter / 400)

    @cached_property
    def pts32T(self) -> np.ndarray:
        return np.ascontiguousarray(self.pts.T, dtype=np.float32)


@dataclass
class Bounds:
    """Per-pose interval containing the exact error, and an estimate."""

    lo: np.ndarray
    hi: np.ndarray
    est: np.ndarray
