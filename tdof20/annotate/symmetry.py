"""An object model's symmetries and its canonical frame, found numerically (the catalog's
convention, ``tdof20.objects``); used by :mod:`~tdof20.annotate.modelbuild`.

Canonical frame (:func:`canonical_frame`):

* z: the object's axis — its symmetry axis when it has one, else the best approximate one (the
  axis about which turned copies of the surface stay closest to it: a mug's body axis) — pointing
  along ``up`` (the table normal: z up, the base at z_min).
* origin: on that axis at the mid-height of the model's extent along z.
* x: continuous symmetry — the input's x projected off the axis (arbitrary but deterministic);
  n-fold — towards a point of largest radius (a corner); none — towards the side with the most
  surface far from the axis (a handle, a spout).

Symmetries are found on the open outside of the model only (samples from which a cone of rays
about the normal leaves the object: a vessel's inside and the floor of a deep cavity are seen by
few cameras and reconstructed worst). A candidate axis (``up`` if given, else the three
principal axes of the surface) is refined by Gauss-Newton so that copies of the surface turned
about it land on the surface (point-to-plane, distances truncated so that a handle does not
pull). Then, with distances from the turned surface samples to the mesh (open3d ray casting):
continuous if every turn of a set of 14 leaves all but ``sym_max_fraction`` of the samples
within ``sym_tol_mm``; else the largest n in 8..2 whose turns by 360°·k/n pass (the axis refined
again for those turns); else none. BOP form: ``{"symmetries_continuous": [{"axis": [0,0,1],
"offset": [0,0,0]}]}``, ``{"symmetries_discrete": [16 numbers per turn k = 1..n-1]}`` or ``{}``.
"""

from __future__ import annotations

import numpy as np

from tdof20.annotate.modelbuild_config import ModelBuildConfig
from tdof20.geometry import rotation_matrix
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.o3d import o3d

__all__ = ["MeshSurface", "axis_basis", "canonical_frame", "symmetry_kind"]


_CONT_TEST_DEG = np.r_[np.arange(30.0, 360.0, 30.0), 7.0, 13.0, 187.0]   # the turns of the continuous test
_CONT_FIT_DEG = np.array([50.0, 130.0, 230.0])                           # the turns the axis is fitted with


class MeshSurface:
    """Closest-point and distance queries to a triangle mesh (open3d ray casting, float32)."""

    def __init__(self, V: np.ndarray, F: np.ndarray):
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(V, np.float32)),
                                 o3d.core.Tensor(np.ascontiguousarray(F, np.uint32)))

    def distance(self, P: np.ndarray) -> np.ndarray:
        q = o3d.core.Tensor(np.ascontiguousarray(P, np.float32))
        return self.scene.compute_distance(q).numpy().astype(np.float64)

    def closest(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(P, np.float32)))
        return r["points"].numpy().astype(np.float64), r["primitive_normals"].numpy().astype(np.float64)


def axis_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(a, float) / np.linalg.norm(a)
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return a, e1, np.cross(a, e1)


def _turn(P: np.ndarray, a: np.ndarray, p: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """P (M,3) turned about the line (p, a) by each angle (rad) -> (K*M,3)."""
    Rs = np.stack([rotation_matrix(a, t) for t in angles])
    return (np.einsum("kij,mj->kmi", Rs, P - p) + p).reshape(-1, 3)


def _refine_axis(surf: MeshSurface, S: np.ndarray, a: np.ndarray, p: np.ndarray, angles: np.ndarray,
                 trunc: float, iters: int = 10) -> tuple[np.ndarray, np.ndarray, float]:
    """Gauss-Newton on the axis (direction a, point p) so that the samples S turned by
    ``angles`` lie on the surface (point-to-plane; pairs farther than ``trunc`` left out).
    Returns (a, p, mean truncated distance)."""
    a, e1, e2 = axis_basis(a)
    p = np.asarray(p, float)
    steps = np.array([1e-4, 1e-4, 1e-2, 1e-2])
    lam = 1e-3
    for _ in range(iters):
        a, e1, e2 = axis_basis(a)
        X = _turn(S, a, p, angles)
        c, nrm = surf.closest(X)
        r = np.einsum("ij,ij->i", X - c, nrm)
        keep = np.linalg.norm(X - c, axis=1) < trunc
        if keep.sum() < 12:
            break
        J = np.empty((len(X), 4))
        for k in range(4):
            da = a + (steps[k] * e1 if k == 0 else steps[k] * e2 if k == 1 else 0)
            dp = p + (steps[k] * e1 if k == 2 else steps[k] * e2 if k == 3 else 0)
            J[:, k] = np.einsum("ij,ij->i", _turn(S, da / np.linalg.norm(da), dp, angles) - X, nrm) / steps[k]
        Jk, rk = J[keep], r[keep]
        H = Jk.T @ Jk
        dx = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), Jk.T @ rk)
        a = a + dx[0] * e1 + dx[1] * e2
        a /= np.linalg.norm(a)
        p = p + dx[2] * e1 + dx[3] * e2
        if abs(dx[0]) + abs(dx[1]) < 1e-6 and abs(dx[2]) + abs(dx[3]) < 1e-4:
            break  # a right hypothesis converges in a few steps; a wrong one wanders until iters
    cost = float(np.minimum(surf.distance(_turn(S, a, p, angles)), trunc).mean())
    return a, p, cost


def _off_fraction(surf: MeshSurface, S: np.ndarray, a: np.ndarray, p: np.ndarray, angles: np.ndarray,
                  tol: float) -> float:
    """Fraction of the samples that some turn of ``angles`` takes farther than ``tol`` off the surface."""
    d = surf.distance(_turn(S, a, p, angles)).reshape(len(angles), len(S))
    return float((d.max(axis=0) > tol).mean())


def _symmetry_about(surf: MeshSurface, S_fit: np.ndarray, S_test: np.ndarray, a: np.ndarray, p: np.ndarray,
                    trunc: float, cfg: ModelBuildConfig) -> tuple[str | int | None, np.ndarray, np.ndarray, float]:
    """Classify the symmetry about a candidate axis -> (kind: "continuous" | n | None, a, p, cost).

    Every hypothesis starts from the candidate (a, p): refining for the wrong turns (e.g.
    generic turns of a square) can drift off the true axis."""
    a0, p0 = a, p
    a, p, cost = _refine_axis(surf, S_fit, a0, p0, np.radians(_CONT_FIT_DEG), trunc)
    if _off_fraction(surf, S_test, a, p, np.radians(_CONT_TEST_DEG), cfg.sym_tol_mm) <= cfg.sym_max_fraction:
        return "continuous", a, p, cost
    for n in range(8, 1, -1):
        turns = 2.0 * np.pi * np.arange(1, n) / n
        an, pn, cn = _refine_axis(surf, S_fit, a0, p0, turns, trunc)
        if _off_fraction(surf, S_test, an, pn, turns, cfg.sym_tol_mm) <= cfg.sym_max_fraction:
            return n, an, pn, cn
    return None, a, p, cost


def _symmetry_samples(surf: MeshSurface, V: np.ndarray, F: np.ndarray, cfg: ModelBuildConfig,
                      face_weights: np.ndarray | None) -> np.ndarray:
    """The surface samples the symmetry is judged on: only the open outer surface (a sample
    from which the outward normal ray and the rays of a cone of ``sym_open_deg`` about it all
    leave the object without hitting it again) and only faces with weight > 0. A vessel's inside
    is seen by few views and reconstructed worst — its floor too, which the normal ray alone
    would count as outside (it looks out through the opening: a deep jar's floor was the only
    surface that kept a reconstructed jar from being found continuous); the outside is what
    tells the poses of an object apart."""
    Fs = F if face_weights is None else F[np.asarray(face_weights).reshape(-1) > 0]
    if len(Fs) == 0:
        Fs = F
    S = sample_mesh_surface(V, Fs, 2 * cfg.sym_samples, cfg.seed)
    _, nrm = surf.closest(S)
    tri = V[F]
    if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
        nrm = -nrm  # faces wound inwards: the signed volume is negative
    size = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    t1 = np.cross(nrm, np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    c, sn = np.cos(np.radians(cfg.sym_open_deg)), np.sin(np.radians(cfg.sym_open_deg))
    dirs = [nrm] + [c * nrm + sn * (np.cos(phi) * t1 + np.sin(phi) * t2)
                    for phi in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)]
    origin = S + 1e-4 * size * nrm
    rays = np.concatenate([np.concatenate([origin, d], axis=1) for d in dirs]).astype(np.float32)
    leave = np.isinf(surf.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(len(dirs), len(S))
    out = leave.all(axis=0)
    if out.mean() < 0.1:  # no recognisable outside (an odd mesh): judge on everything
        out[:] = True
    return S[out][: cfg.sym_samples]


def _rank(kind) -> int:
    return 100 if kind == "continuous" else 0 if kind is None else int(kind)


def canonical_frame(vertices: np.ndarray, faces: np.ndarray, up: np.ndarray | None = None,
                    cfg: ModelBuildConfig = ModelBuildConfig(),
                    face_weights: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(T_model_from_input (4,4), symmetries in BOP form, expressed in the model frame).

    See the module docstring for the frame's convention and the symmetry test. ``up`` (the table
    normal in the input frame) is the first candidate axis and fixes the sign of z; without it
    the three principal axes of the surface are tried and z takes the sign of the input's z."""
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    surf = MeshSurface(V, F)
    S_test = _symmetry_samples(surf, V, F, cfg, face_weights)
    S_fit = S_test[: min(600, len(S_test))]
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    c = (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()  # on any symmetry axis
    size = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    trunc = max(3.0 * cfg.sym_tol_mm, 0.03 * size)
    if up is not None:
        up = np.asarray(up, float) / np.linalg.norm(up)
        cands = [up]
    else:
        w, U = np.linalg.eigh(np.cov((S_test - c).T))
        # a symmetry axis of order >= 3 is the principal axis whose spread differs from the others
        distinct = [min(abs(w[k] - w[j]) for j in range(3) if j != k) for k in range(3)]
        cands = [U[:, k] for k in np.argsort(distinct)[::-1]]
    best = None
    for a0 in cands:
        kind, a, p, cost = _symmetry_about(surf, S_fit, S_test, a0, c, trunc, cfg)
        key = (-_rank(kind), cost)
        if best is None or key < best[0]:
            best = (key, kind, a, p)
        if kind == "continuous":
            break
    _, kind, a, p = best
    ref = up if up is not None else np.array([0.0, 0.0, 1.0])
    if a @ ref < 0:
        a = -a
    if kind is None and up is not None:
        a = up  # an upright object without symmetry: z is the table normal itself
    # origin: on the axis at the mid-height of the extent along it
    h = (V - p) @ a
    o = p + 0.5 * (h.min() + h.max()) * a
    # x: by the kind of symmetry (module docstring)
    _, e1, e2 = axis_basis(a)
    rel = S_test - o
    rad = rel - np.outer(rel @ a, a)
    r = np.linalg.norm(rad, axis=1)
    phi = np.arctan2(rad @ e2, rad @ e1)
    if kind == "continuous":
        x_in = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = x_in - (x_in @ a) * a
        ang = np.arctan2(x @ e2, x @ e1)
    elif kind is None:
        ang = np.angle(np.sum(r * np.exp(1j * phi)))
    else:
        n = int(kind)
        ang = np.angle(np.sum((r - r.mean()) * np.exp(1j * n * phi))) / n
    x = np.cos(ang) * e1 + np.sin(ang) * e2
    y = np.cross(a, x)
    R = np.stack([x, y, a], axis=1)  # columns: the model axes in the input frame
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ o
    return T, _bop_symmetries(kind)


def _bop_symmetries(kind) -> dict:
    if kind == "continuous":
        return {"symmetries_continuous": [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]}
    if kind is None:
        return {}
    n = int(kind)
    out = []
    for k in range(1, n):
        T = np.eye(4)
        T[:3, :3] = rotation_matrix([0.0, 0.0, 1.0], 2.0 * np.pi * k / n)
        T[np.abs(T) < 1e-12] = 0.0
        out.append([float(v) for v in T.reshape(-1)])
    return {"symmetries_discrete": out}


def symmetry_kind(symmetries: dict) -> str | int | None:
    """"continuous", n (n-fold discrete) or None from a BOP symmetries dict."""
    if symmetries.get("symmetries_continuous"):
        return "continuous"
    if symmetries.get("symmetries_discrete"):
        return len(symmetries["symmetries_discrete"]) + 1
    return None

