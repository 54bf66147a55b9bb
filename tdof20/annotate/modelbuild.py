"""Object models from reconstructed clusters: surface, canonical frame, symmetries, samples,
keypoints, the BOP models folder, and checked loading of a user's models folder (``--models``).

    m = build_model_from_cluster(rec.clusters[0], rec.plane, viewpoints=cam_centres)
    write_models({obj_id: m}, scene_dir / "models")
    models = load_models(user_dir, obj_ids=[5, 15])          # {obj_id: (V, F, info)}

Surface (:func:`build_model_from_cluster`): the cluster's own normals when the caller has them —
the TSDF's gradients (:attr:`tdof20.annotate.reconstruct.Reconstruction.cluster_normals`), the
only reliable ones for the few-mm walls of glassware; else normals by PCA over the nearest
neighbours, oriented towards the viewpoints that see each point (hidden-point removal per
viewpoint; without viewpoints a virtual ring of cameras above the table, as on the rig). The
estimated ones cannot tell the two sides of a thin wall apart: a vessel built from them comes
out solid (measured on the simulated jar single/13: the model 1.4-1.5 mm from the truth,
0.4-0.6 mm with the TSDF's normals; the outside right either way); the bottom the table hides
is closed by a disc of points on the table plane under the footprint (the 2D convex hull of the
lowest points, shrunk where the wall narrows towards the table — a fillet, a round bottom — as
far as the wall's slope above carries it) and a skirt from the disc's edge up to the lowest
points; the inside no camera saw gets a wall (below); screened Poisson (pymeshlab); then faces
farther than ``trim_mm`` from the data are cut, the largest component kept, holes closed, the
mesh decimated to ``target_faces`` and checked watertight with trimesh.

The inside no camera saw (``inner_walls``, :func:`_inner_walls`): the opaque twins show a vase's
belly, a bottle's or a flask's body only from outside — their narrow necks hide the inside —
and Poisson closed such a vessel solid under a ragged cap where the trimmed sheet had been
(measured at 640x480, 4 arms x 24 steps: the vase single/12 2.1-2.8 mm from the truth, 4.5
times its volume; the wine bottle 1.35 mm). A vessel's glass is a wall of about one thickness:
it is measured where the cameras saw a wall from both sides (a neck, a rim), and the outside of
a first Poisson surface whose inward rays meet no data for ``wall_search_mm`` — a large
connected region of it, not the middle of a thick base — is copied one thickness inwards with
the opposite normals, the gaps of the seen outside in front of it filled from that first surface.
Now 0.41 mm for the vase, 0.69 mm for the bottle (``docs/annotate.md`` lists every object
measured). An object whose walls were never seen from both sides, or whose unseen inside is
small, is built as before.

Canonical frame and symmetries (:func:`~tdof20.annotate.symmetry.canonical_frame`): found
numerically on the built mesh, see :mod:`~tdof20.annotate.symmetry`; the options of the build
are :class:`~tdof20.annotate.modelbuild_config.ModelBuildConfig`.

Models folder (:func:`write_models`), every file written atomically::

    models/obj_{id:06d}.ply         binary little-endian PLY, mm: float x y z nx ny nz,
                                    uchar-int vertex_indices (trimesh and bop_toolkit read it)
    models/models_info.json         BOP: diameter, min_x.., size_x.., symmetries (+ "source", ...)
    models/keypoints.json           {"<obj_id>": 9x3 mm}: the bounding-box centre, then 8 farthest
                                    points of surface samples (tdof20.objects.keypoints.surface_keypoints,
                                    so it equals what the network's loader computes from the PLY)
    models/obj_{id:06d}_samples.npy (n_samples,3) float32 mm, Monte-Carlo area-uniform samples
"""

from __future__ import annotations

import dataclasses
import io
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from tdof20.annotate.modelbuild_config import ModelBuildConfig
from tdof20.annotate.symmetry import MeshSurface, axis_basis, canonical_frame
from tdof20.dataset.models import load_models  # noqa: F401  (re-exported: the models check is the dataset's)
from tdof20.errors import TdofError
from tdof20.formats import atomic_write_bytes, write_json
from tdof20.formats.bop_models import model_path, write_model_mesh, write_models_info
from tdof20.geometry import farthest_point_sampling
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.o3d import o3d
from tdof20.objects.catalog import mesh_diameter
from tdof20.objects.keypoints import surface_keypoints

KEYPOINTS_FILE = "keypoints.json"


@dataclass
class BuiltModel:
    vertices: np.ndarray               # (V,3) float64 mm, canonical model frame
    faces: np.ndarray                  # (F,3) int64
    T_ref_model: np.ndarray            # (4,4) model -> reconstruction reference frame
    symmetries: dict                   # BOP form (see tdof20.annotate.symmetry)
    watertight: bool
    info: dict = field(default_factory=dict)  # models_info entry (+ own keys: source, fit, timing)


# ------------------------------------------------------------------------------------------
# sampling and keypoints
# ------------------------------------------------------------------------------------------
def sample_points(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n,3) Monte-Carlo area-uniform surface samples, deterministic in ``seed`` (the catalog's
    sampler, :func:`tdof20.geometry.sampling.sample_mesh_surface`)."""
    return sample_mesh_surface(vertices, faces, n, seed)


def model_keypoints(vertices: np.ndarray, faces: np.ndarray, k: int = 9, seed: int = 0) -> np.ndarray:
    """(k,3): the bounding-box centre, then k-1 farthest-point samples of the surface — the
    project's one definition (:func:`tdof20.objects.keypoints.surface_keypoints`), so the
    keypoints written with a model are those any loader recomputes from the PLY."""
    return surface_keypoints(vertices, faces, k=k, seed=seed)


# ------------------------------------------------------------------------------------------
# the surface from a cluster
# ------------------------------------------------------------------------------------------
def _plane(table_plane) -> tuple[np.ndarray, float]:
    pl = np.asarray(table_plane, float).reshape(-1)
    if pl.size != 4 or not np.all(np.isfinite(pl)) or np.linalg.norm(pl[:3]) < 1e-9:
        raise TdofError(f"table plane must be 4 finite numbers (n, d) with n != 0, got {pl.tolist()}")
    s = np.linalg.norm(pl[:3])
    return pl[:3] / s, float(pl[3] / s)


def _virtual_viewpoints(P: np.ndarray, up: np.ndarray, n_az: int = 12) -> np.ndarray:
    """Cameras on rings above the object, as the rig's arm positions see it from the turntable."""
    c = P.mean(axis=0)
    _, e1, e2 = axis_basis(up)
    dist = 4.0 * float(np.linalg.norm(P - c, axis=1).max()) + 200.0
    out = [c + dist * up]
    for elev in np.radians([15.0, 40.0, 65.0]):
        for az in np.linspace(0.0, 2.0 * np.pi, n_az, endpoint=False):
            d = np.cos(elev) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(elev) * up
            out.append(c + dist * d)
    return np.asarray(out)


def _thin_viewpoints(vp: np.ndarray, centre: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` viewpoints spread over their directions from the object."""
    if len(vp) <= k:
        return vp
    d = (vp - centre) / np.linalg.norm(vp - centre, axis=1, keepdims=True)
    pick = farthest_point_sampling(d, k)
    idx = cKDTree(d).query(pick)[1]
    return vp[np.unique(idx)]


def _oriented_normals(P: np.ndarray, viewpoints: np.ndarray, cfg: ModelBuildConfig) -> np.ndarray:
    """PCA normals over ``normal_knn`` neighbours, each turned towards the viewpoints that see its
    point (hidden-point removal); points no viewpoint sees take the sign their neighbours vote for."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(cfg.normal_knn))
    N = np.asarray(pc.normals).copy()
    radius = 100.0 * float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
    votes = np.zeros(len(P))
    for v in viewpoints:
        _, idx = pc.hidden_point_removal(np.asarray(v, float), radius)
        idx = np.asarray(idx)
        d = v - P[idx]
        votes[idx] += np.einsum("ij,ij->i", N[idx], d) / np.linalg.norm(d, axis=1)
    sign = np.sign(votes)
    if (sign == 0).any() and (sign != 0).any():
        _, nb = cKDTree(P).query(P, k=min(cfg.normal_knn, len(P)))
        for _ in range(20):
            todo = np.flatnonzero(sign == 0)
            if len(todo) == 0:
                break
            agree = np.einsum("ij,ikj->ik", N[todo], N[nb[todo]]) * sign[nb[todo]]
            s = np.sign(agree.sum(axis=1))
            if not s.any():
                break
            sign[todo] = s
    sign[sign == 0] = 1.0
    return N * sign[:, None]


def _polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid (2,) of a simple polygon (K,2)."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cr = x * yn - xn * y
    a = cr.sum() / 2.0
    if abs(a) < 1e-12:
        return poly.mean(axis=0)
    return np.array([((x + xn) * cr).sum(), ((y + yn) * cr).sum()]) / (6.0 * a)


_BASE_MIN_SHRINK = 0.5   # the extrapolated footprint keeps at least this share of the lowest points' outline


def _base_disc(P: np.ndarray, n: np.ndarray, d: float, spacing: float, cfg: ModelBuildConfig):
    """(points, normals) of the bottom the table hides: a disc on the table plane (normals -n)
    under the footprint — the 2D convex hull of the points within ``base_band_mm`` of the lowest,
    shrunk where the wall narrows towards the table (below) — filled on a grid, and the skirt
    from its outline up to the lowest points' outline (normals outwards). None when the object
    does not reach down to the table."""
    h = P @ n + d
    if h.min() > cfg.base_max_gap_mm:
        return None
    low = h < h.min() + cfg.base_band_mm
    band = P[low]
    _, e1, e2 = axis_basis(n)
    uv = np.stack([band @ e1, band @ e2], axis=1)
    if len(uv) < 3:
        return None
    try:
        hull = ConvexHull(uv)
    except Exception:  # collinear band points: no footprint to close
        return None
    from scipy.spatial import Delaunay

    poly_low = uv[hull.vertices]
    # a wall that narrows towards the table (a fillet, a round bottom) goes on narrowing below the
    # lowest points the table lets the cameras see: the outline is shrunk to where the wall's
    # slope between the lowest band and the one above it meets the table
    k, c = 1.0, _polygon_centroid(poly_low)
    up = P[(h >= h.min() + cfg.base_band_mm) & (h < h.min() + 2.0 * cfg.base_band_mm)]
    try:
        up_hull = ConvexHull(np.stack([up @ e1, up @ e2], axis=1)) if len(up) >= 3 else None
    except Exception:
        up_hull = None
    if up_hull is not None:
        r_low, r_up = np.sqrt(hull.volume / np.pi), np.sqrt(up_hull.volume / np.pi)   # sqrt(area / pi)
        if r_up > r_low > 0:
            r0 = r_low - (r_up - r_low) / cfg.base_band_mm * float(h[low].mean())
            k = float(np.clip(r0 / r_low, _BASE_MIN_SHRINK, 1.0))
    poly = c + (poly_low - c) * k
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    gu, gv = np.meshgrid(np.arange(lo[0], hi[0] + spacing, spacing), np.arange(lo[1], hi[1] + spacing, spacing))
    g = np.stack([gu.ravel(), gv.ravel()], axis=1)
    g = g[Delaunay(poly).find_simplex(g) >= 0]
    # the lowest points' outline, densely, with each point's outward normal in the plane
    outline, out2 = [], []
    for i in range(len(poly_low)):
        a, b = poly_low[i], poly_low[(i + 1) % len(poly_low)]
        m = max(2, int(np.linalg.norm(b - a) / spacing) + 1)
        outline.append(np.linspace(a, b, m, endpoint=False))
        e = (b - a) / max(np.linalg.norm(b - a), 1e-12)
        o = np.array([e[1], -e[0]])
        out2.append(np.tile(o if o @ (0.5 * (a + b) - c) >= 0 else -o, (m, 1)))
    outline, out2 = np.concatenate(outline), np.concatenate(out2)
    base = -d * n  # the plane's point nearest the origin
    pts = [base + g[:, :1] * e1 + g[:, 1:] * e2, base + (c + (outline - c) * k) @ np.stack([e1, e2])]
    nrm = [np.tile(-n, (len(g) + len(outline), 1))]
    # the skirt the table hides: from the footprint's outline up to the lowest points' outline
    top = float(h.min())
    run = (1.0 - k) * np.einsum("ij,ij->i", outline - c, out2)          # outward run of the skirt
    steps = max(2, int(np.hypot(top, float(run.max(initial=0.0))) / spacing) + 1)
    for f in np.linspace(0.0, 1.0, steps + 1)[1:]:
        q = c + (outline - c) * (k + (1.0 - k) * f)
        pts.append(base + q @ np.stack([e1, e2]) + f * top * n)
        m3 = top * (out2 @ np.stack([e1, e2])) - run[:, None] * n
        nrm.append(m3 / np.maximum(np.linalg.norm(m3, axis=1, keepdims=True), 1e-12))
    return np.concatenate(pts), np.concatenate(nrm)


_WALL_PERCENTILE = 10.0    # of the seen walls' thicknesses (see _wall_thickness)
_WALL_MIN_SPACINGS = 2.5   # a wall thinner than this many point spacings gets no inner twin (sparse points:
                           # measured on the catalog's vase, 3.5 mm walls, 1.6 mm spacing: the double wall came
                           # out dented and holed, the symmetry lost; 0.9 mm spacing, a TSDF's: right)


def _first_hits(tree: cKDTree, X: np.ndarray, D: np.ndarray, spacing: float,
                cfg: ModelBuildConfig) -> tuple[np.ndarray, np.ndarray]:
    """March the rays X + s D, s from 3 spacings to ``wall_search_mm`` in steps of the spacing:
    per ray the first s with a data point within 2 spacings (inf: none) and that point's index."""
    first = np.full(len(X), np.inf)
    hit = np.full(len(X), -1, np.int64)
    for depth in np.arange(3.0 * spacing, cfg.wall_search_mm + 1e-9, spacing):
        todo = np.flatnonzero(~np.isfinite(first))
        if len(todo) == 0:
            break
        d, j = tree.query(X[todo] + depth * D[todo], distance_upper_bound=2.0 * spacing, workers=-1)
        ok = np.isfinite(d)
        first[todo[ok]] = depth
        hit[todo[ok]] = j[ok]
    return first, hit


def _wall_thickness(P: np.ndarray, N: np.ndarray, tree: cKDTree, spacing: float,
                    cfg: ModelBuildConfig) -> float | None:
    """The thickness of the walls the cameras saw from both sides: the depth at which a point's
    inward ray first meets a point whose normal faces the other way, within ``wall_max_mm``
    (thicker: a handle, a stem, a base — not a wall); of those depths the 10th percentile: the
    TSDF only ever thickens a thin wall (the inner side, seen by few views through the opening,
    is pulled into the cavity; the outer side stays), least where it is seen best. Measured on
    the 640x480 reconstructions (walls 3.5, 2.0, 3.5 mm): the vase 3.64 (median 3.94), the
    round-bottom flask 3.04 (3.47), the wine bottle 4.17 (5.32). None when under 2 % of the
    points (and under 50) have such a twin: no walls seen."""
    _, hit = _first_hits(tree, P, -N, spacing, cfg)
    got = np.flatnonzero(hit >= 0)
    q = hit[got]
    thick = np.einsum("ij,ij->i", P[got] - P[q], N[got])
    wall = (np.einsum("ij,ij->i", N[got], N[q]) < -0.7) & (thick > 0) & (thick <= cfg.wall_max_mm)
    if wall.sum() < max(50, 0.02 * len(P)):
        return None
    return float(np.percentile(thick[wall], _WALL_PERCENTILE))


def _poisson(P: np.ndarray, N: np.ndarray, cfg: ModelBuildConfig) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson (pymeshlab) of oriented points -> the raw closed surface (V, F)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(P, np.float64),
                               v_normals_matrix=np.ascontiguousarray(N, np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(
        depth=cfg.poisson_depth, samplespernode=cfg.poisson_samples_per_node,
        pointweight=cfg.poisson_point_weight, preclean=True, threads=cfg.poisson_threads)
    m = ms.current_mesh()
    return m.vertex_matrix().copy(), m.face_matrix().astype(np.int64)


def _first_surface(P: np.ndarray, N: np.ndarray, tree: cKDTree, spacing: float,
                   cfg: ModelBuildConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A first screened Poisson of the data (octree depth - 1): its vertices within ``trim_mm``
    of the data (what the trimmed model keeps), thinned to one per spacing-sized cell, with
    their outward normals and their distances to the data. Complete and smooth where the data
    is sparse (a patch near the table few views saw)."""
    V, F = _poisson(P, N, dataclasses.replace(cfg, poisson_depth=max(6, cfg.poisson_depth - 1)))
    empty = np.zeros((0, 3))
    if len(F) == 0:
        return empty, empty, np.zeros(0)
    tri = V[F]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], cross)
    if np.einsum("ij,ij->i", tri[:, 0], cross).sum() < 0:     # wound inwards: flip
        vn = -vn
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
    d = tree.query(V, workers=-1)[0]
    sel = np.flatnonzero(d <= cfg.trim_mm)
    _, first = np.unique(np.floor(V[sel] / spacing).astype(np.int64), axis=0, return_index=True)
    sel = sel[np.sort(first)]
    return V[sel], vn[sel], d[sel]


def _inner_walls(P: np.ndarray, N: np.ndarray, spacing: float, cfg: ModelBuildConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float | None]:
    """The wall of an inside no camera saw: (gap points, their normals, inner wall points,
    their normals, the wall thickness t).

    t is measured where the cameras saw a wall from both sides (:func:`_wall_thickness`; none,
    or thinner than 2.5 point spacings: nothing added). The inner wall is the outside moved in
    by t, taken from a first Poisson surface of the data (:func:`_first_surface`), complete
    where the data is sparse: a surface point whose inward ray meets no data within
    ``wall_search_mm``, like the rays of 3/4 of its 16 neighbours, looks into an unseen inside
    when such points make a connected region (linked within 2 t) of at least ``wall_min_share``
    of the surface (a vase's belly behind its neck; not the middle of a glass's thick base, whose
    far side lies beyond the search). Such a point gets a twin t inwards with the opposite
    normal, unless the twin comes closer than 0.8 t to the data (the corner at the table); where
    the data itself is missing in front of it (more than 2 spacings away) the surface point is
    added too, so that both sides of the wall are sampled: a double wall with a gap in both sides
    is where Poisson's octree stays coarse and the wall vanishes (a hole through the model)."""
    empty, none = np.zeros((0, 3)), None
    if len(P) < 50:
        return empty, empty, empty, empty, none
    tree = cKDTree(P)
    t = _wall_thickness(P, N, tree, spacing, cfg)
    if t is None or t < _WALL_MIN_SPACINGS * spacing:
        return empty, empty, empty, empty, t
    X, NX, dX = _first_surface(P, N, tree, spacing, cfg)
    if len(X) < 50:
        return empty, empty, empty, empty, t
    depth, _ = _first_hits(tree, X, -NX, spacing, cfg)
    free = ~np.isfinite(depth)
    _, nb = cKDTree(X).query(X, k=16, workers=-1)
    free &= free[nb].mean(axis=1) >= 0.75                       # a free region, not a stray point
    idx = np.flatnonzero(free)
    if len(idx):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        pairs = cKDTree(X[idx]).query_pairs(max(3.0 * spacing, 2.0 * t), output_type="ndarray")
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
        _, lab = connected_components(g, directed=False)
        size = np.bincount(lab)
        free[idx[size[lab] < cfg.wall_min_share * len(X)]] = False
    gap = free & (dX > 2.0 * spacing)
    G, NG = X[gap], NX[gap]
    Q, NQ = X[free] - t * NX[free], -NX[free]
    keep = cKDTree(np.concatenate([P, G])).query(Q, workers=-1)[0] >= 0.8 * t
    return G, NG, Q[keep], NQ[keep], t


def _largest_component(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    labels = trimesh.graph.connected_component_labels(trimesh.graph.face_adjacency(F), node_count=len(F))
    if len(F) == 0:
        return V, F
    keep = labels == np.bincount(labels).argmax()
    F = F[keep]
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def _is_watertight(V: np.ndarray, F: np.ndarray) -> bool:
    import trimesh

    return bool(trimesh.Trimesh(vertices=V, faces=F, process=False).is_watertight)


def _surface_from_points(P: np.ndarray, N: np.ndarray, data: np.ndarray,
                         cfg: ModelBuildConfig) -> tuple[np.ndarray, np.ndarray, bool]:
    """Screened Poisson, trim, largest component, close holes, decimate -> (V, F, watertight)."""
    import pymeshlab

    V, F = _poisson(P, N, cfg)
    # trim what the data does not support (Poisson closes unseen regions with smooth sheets)
    far = cKDTree(data).query(V, workers=-1)[0] > cfg.trim_mm
    F = F[~far[F].any(axis=1)]
    V, F = _largest_component(V, F)
    if len(F) < 4:
        raise TdofError("the surface reconstruction of the cluster is empty (too few or too scattered points)")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=V, face_matrix=F))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_repair_non_manifold_vertices()
    # (new faces left unselected: the decimation below would otherwise touch only them)
    ms.meshing_close_holes(maxholesize=100000, selfintersection=False, newfaceselected=False)
    if ms.current_mesh().face_number() > cfg.target_faces:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=cfg.target_faces, preservetopology=True,
                                                    preservenormal=True, planarquadric=True, autoclean=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    V, F = m.vertex_matrix().copy(), m.face_matrix().astype(np.int64)
    for _ in range(3):  # decimation can leave a non-manifold edge: cut it out, close, again
        if _is_watertight(V, F):
            return V, F, True
        V, F = _largest_component(V, F)
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=V, face_matrix=F))
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
        ms.meshing_close_holes(maxholesize=100000, selfintersection=False, newfaceselected=False)
        ms.meshing_remove_unreferenced_vertices()
        m = ms.current_mesh()
        V, F = m.vertex_matrix().copy(), m.face_matrix().astype(np.int64)
    return V, F, _is_watertight(V, F)


def build_model_from_cluster(points: np.ndarray, table_plane: np.ndarray, cfg: ModelBuildConfig = ModelBuildConfig(),
                             viewpoints: np.ndarray | None = None, normals: np.ndarray | None = None) -> BuiltModel:
    """A watertight model from one object's cluster (N,3) mm in the reference frame.

    ``table_plane`` (4,): n·x + d = 0 with n up towards the objects. ``viewpoints`` (K,3): the
    camera centres in the reference frame (normals are turned towards the ones that see them;
    without them a virtual ring above the table). ``normals`` (N,3): oriented normals of the
    points if the caller has them (e.g. the TSDF's gradients) — then no estimation is done.
    Raises TdofError for a cluster that is too small or degenerate."""
    t0 = time.perf_counter()
    P = np.asarray(points, float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise TdofError(f"cluster must be an (N,3) array of points, got shape {P.shape}")
    ok = np.all(np.isfinite(P), axis=1)
    if normals is not None:
        normals = np.asarray(normals, float)
        if normals.shape != P.shape:
            raise TdofError(f"normals must match the cluster's shape {P.shape}, got {normals.shape}")
        ok &= np.all(np.isfinite(normals), axis=1)
        normals = normals[ok]
    P = P[ok]
    if len(P) < cfg.min_points:
        raise TdofError(f"cluster too small to build a model: {len(P)} points (need >= {cfg.min_points})")
    n, d = _plane(table_plane)
    h = P @ n + d
    above = h > -cfg.trim_mm
    P = P[above]
    if normals is not None:
        normals = normals[above]
    if len(P) < cfg.min_points:
        raise TdofError(f"cluster lies below the table plane: {len(P)} points above it (need >= {cfg.min_points})")
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False) / np.sqrt(len(P))
    if sv[1] < 2.0 or sv[2] < 0.5:
        raise TdofError(f"cluster is degenerate (spread {sv.round(2).tolist()} mm along its principal axes): "
                        "not an object's surface")
    spacing = float(np.median(cKDTree(P).query(P, k=2, workers=-1)[0][:, 1]))
    if normals is None:
        vp = _virtual_viewpoints(P, n) if viewpoints is None else np.asarray(viewpoints, float).reshape(-1, 3)
        vp = _thin_viewpoints(vp, P.mean(axis=0), 48)
        N = _oriented_normals(P, vp, cfg)
    else:
        N = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    disc = _base_disc(P, n, d, max(spacing, 0.5), cfg)
    if disc is not None:
        P_all, N_all = np.concatenate([P, disc[0]]), np.concatenate([N, disc[1]])
    else:
        P_all, N_all = P, N
    wall_mm, n_inner, n_gap = None, 0, 0
    if cfg.inner_walls:
        G, NG, Q, NQ, wall_mm = _inner_walls(P_all, N_all, spacing, cfg)
        n_inner, n_gap = len(Q), len(G)
        if len(Q):
            P_all, N_all = np.concatenate([P_all, G, Q]), np.concatenate([N_all, NG, NQ])
    data = P_all
    t_pre = time.perf_counter()
    V, F, watertight = _surface_from_points(P_all, N_all, data, cfg)
    t_surf = time.perf_counter()
    supported = cKDTree(data).query(V[F].mean(axis=1), workers=-1)[0] <= cfg.trim_mm  # not hole fillers
    T_model_ref, sym = canonical_frame(V, F, up=n, cfg=cfg, face_weights=supported)
    t_frame = time.perf_counter()
    V_m = V @ T_model_ref[:3, :3].T + T_model_ref[:3, 3]
    dist = MeshSurface(V, F).distance(P)
    info = _geometry_info(V_m)
    info.update(sym)
    info.update({"source": "poisson", "watertight": watertight, "n_cluster_points": int(len(P)),
                 "cluster_to_model_median_mm": float(np.median(dist)),
                 "cluster_to_model_p95_mm": float(np.percentile(dist, 95)),
                 "closed_bottom": disc is not None,
                 "wall_mm": None if wall_mm is None else round(wall_mm, 3), "inner_wall_points": int(n_inner),
                 "gap_fill_points": int(n_gap),
                 "time_s": {"normals": round(t_pre - t0, 3), "surface": round(t_surf - t_pre, 3),
                            "frame": round(t_frame - t_surf, 3), "total": round(time.perf_counter() - t0, 3)}})
    return BuiltModel(vertices=V_m, faces=F, T_ref_model=np.linalg.inv(T_model_ref), symmetries=sym,
                      watertight=watertight, info=info)


def _geometry_info(V: np.ndarray) -> dict:
    lo, hi = V.min(axis=0), V.max(axis=0)
    size = hi - lo
    return {"diameter": float(mesh_diameter(V)),
            "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2])}


# ------------------------------------------------------------------------------------------
# the models folder
# ------------------------------------------------------------------------------------------


def write_models(models: dict[int, BuiltModel], out_dir: str | Path, n_samples: int = 10000,
                 n_keypoints: int = 9, seed: int = 0) -> Path:
    """Write built models as a BOP models folder (see the module docstring): PLY meshes,
    models_info.json (with the symmetries and the build's own keys), keypoints.json and the
    Monte-Carlo samples; every file atomically. Returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    infos, kps = {}, {}
    for obj_id, m in sorted(models.items()):
        o = int(obj_id)
        # everything below from the vertices as the PLY stores them (float32): the keypoints are
        # then exactly those a reader of the PLY recomputes
        V = np.asarray(m.vertices, np.float64).astype(np.float32).astype(np.float64)
        F = np.asarray(m.faces, np.int64)
        write_model_mesh(model_path(out, o), V, F)
        S = sample_points(V, F, n_samples, seed=seed).astype(np.float32)
        buf = io.BytesIO()
        np.save(buf, S)
        atomic_write_bytes(out / f"obj_{o:06d}_samples.npy", buf.getvalue())
        kps[str(o)] = model_keypoints(V, F, n_keypoints, seed=seed).round(6).tolist()
        e = dict(m.info)
        for k in ("symmetries_continuous", "symmetries_discrete", "time_s"):  # (timing: not a property of the model)
            e.pop(k, None)
        e.update(_geometry_info(V))
        e.update(m.symmetries)
        infos[o] = e
    write_models_info(out, infos)
    write_json(out / KEYPOINTS_FILE, kps)
    return out
