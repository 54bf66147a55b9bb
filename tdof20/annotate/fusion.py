"""The reconstruct stage's data around :func:`~tdof20.annotate.reconstruct.reconstruct` (the TSDF,
the table top, the clusters): which registered frames are fused and how their depth is cropped,
and what the stage leaves in ``work/reconstruction/`` for the model and place stages.

* in: :func:`fuse_selection` (at most ``fuse_max_frames``, the same share of every arm position,
  spread over its turn), :func:`crop_depth` (a frame's depth outside the turntable volume set to 0);
* out: :func:`write_reconstruction` — ``scene_points.ply``, ``scene_mesh.ply``, ``cluster_000.ply``
  ... (points with the TSDF's normals) and ``reconstruction.json`` (format
  ``tdof20-reconstruction``: table plane, turntable axis, frames fused, per cluster its file,
  size, centroid, :func:`cluster_shape` and checksum, the problems met, a few viewpoints);
  :func:`load_reconstruction` and :func:`read_ply_points` read them back.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tdof20.annotate.reconstruct import Reconstruction
from tdof20.annotate.state import sha_file
from tdof20.errors import TdofError
from tdof20.formats import read_json, write_json
from tdof20.o3d import o3d

__all__ = ["RECONSTRUCTION_FORMAT", "cluster_shape", "crop_depth", "fuse_selection", "load_reconstruction",
           "point_cloud", "read_ply_points", "write_ply_points", "write_reconstruction"]

RECONSTRUCTION_FORMAT = "tdof20-reconstruction"


# ---------------------------------------------------------------------------------------------
# what goes into the TSDF
# ---------------------------------------------------------------------------------------------
def fuse_selection(frames: list, max_frames: int) -> list:
    """At most ``max_frames`` of the frames (0 = all), the same share of each arm position,
    spread evenly over its steps."""
    if not max_frames or len(frames) <= max_frames:
        return list(frames)
    arms = sorted({f.arm for f in frames})
    per = max(1, max_frames // len(arms))
    out = []
    for a in arms:
        fa = [f for f in frames if f.arm == a]
        idx = np.unique(np.linspace(0, len(fa) - 1, min(per, len(fa))).round().astype(int))
        out += [fa[i] for i in idx]
    return out


def crop_depth(z: np.ndarray, cam, T_ref_frame: np.ndarray, axis_point: np.ndarray, up: np.ndarray,
               radius: float, max_height: float, below: float = 20.0) -> np.ndarray:
    """Depth (mm) with every pixel outside the turntable volume set to 0: a cylinder of
    ``radius`` about the axis, from ``below`` under the table top to ``max_height`` above it
    (the axis moved into the frame's camera)."""
    R, t = T_ref_frame[:3, :3], T_ref_frame[:3, 3]
    p = R.T @ (np.asarray(axis_point, float) - t)
    a = R.T @ up
    rel = cam.backproject(z) - p.astype(np.float32)
    h = rel @ a.astype(np.float32)
    r2 = np.einsum("hwc,hwc->hw", rel, rel) - h * h
    keep = (z > 0) & (h > -below) & (h < max_height) & (r2 < radius * radius)
    return np.where(keep, z, 0.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# point clouds on disk
# ---------------------------------------------------------------------------------------------
def point_cloud(points: np.ndarray) -> "o3d.geometry.PointCloud":
    """An open3d cloud of (N,3) points."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64).reshape(-1, 3)))


def write_ply_points(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Write (N,3) points (and their normals, when there is one per point) as a binary PLY, atomically."""
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    pc = point_cloud(points)
    if normals is not None and len(normals) == len(points):
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64).reshape(-1, 3))
    if not o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False):
        raise TdofError("cannot write the point cloud", path)
    os.replace(tmp, path)


def read_ply_points(path: Path, with_normals: bool = False):
    """(N,3) points of a PLY cloud; with ``with_normals`` also its (N,3) normals or None."""
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, np.float64)
    if len(pts) == 0:
        raise TdofError("empty or unreadable point cloud (rerun the reconstruct stage)", path)
    if not with_normals:
        return pts
    return pts, (np.asarray(pc.normals, np.float64) if pc.has_normals() else None)


# ---------------------------------------------------------------------------------------------
# work/reconstruction/
# ---------------------------------------------------------------------------------------------
def cluster_shape(points: np.ndarray, up: np.ndarray, d: float) -> tuple[float, float]:
    """(height above the table, footprint radius) of points standing on the plane up.x + d = 0:
    the 99.5th percentile of the heights, and the 99th percentile of the horizontal distances
    from the median horizontal position."""
    h = points @ up + d
    flat = points - np.outer(points @ up, up)
    r = np.linalg.norm(flat - np.median(flat, axis=0), axis=1)
    return float(np.percentile(h, 99.5)), float(np.percentile(r, 99))


def write_reconstruction(d: Path, rec: Reconstruction, axis_point: np.ndarray, axis_dir: np.ndarray,
                         frames_fused: int, fuse_max_frames: int, problems: list[dict],
                         viewpoints: list[np.ndarray]) -> dict:
    """Write the reconstruction into the folder ``d`` (created; clusters of an earlier run removed):
    the scene's points and mesh, one PLY per cluster, and ``reconstruction.json`` (returned)
    with the turntable axis (``axis_point``, ``axis_dir``) it was cropped about, the number of
    frames fused, the problems met and ``viewpoints`` (camera centres in the reference frame)."""
    d.mkdir(parents=True, exist_ok=True)
    for old in d.glob("cluster_*.ply"):
        old.unlink()
    write_ply_points(d / "scene_points.ply", rec.points)
    if rec.mesh is not None and len(rec.mesh.triangles):
        tmp = d / "scene_mesh.tmp.ply"
        o3d.io.write_triangle_mesh(str(tmp), rec.mesh, write_ascii=False)
        os.replace(tmp, d / "scene_mesh.ply")
    up, off = rec.plane[:3], float(rec.plane[3])
    clusters = []
    for i, c in enumerate(rec.clusters):
        name = f"cluster_{i:03d}.ply"
        write_ply_points(d / name, c, rec.cluster_normals[i] if i < len(rec.cluster_normals) else None)
        h, r = cluster_shape(c, up, off)
        clusters.append({"file": name, "n_points": int(len(c)), "centroid": [float(x) for x in c.mean(0)],
                         "height_mm": round(h, 3), "radius_mm": round(r, 3), "sha256": sha_file(d / name)})
    meta = {"format": RECONSTRUCTION_FORMAT, "plane": [float(x) for x in rec.plane],
            "axis_point": [float(x) for x in axis_point], "axis_dir": [float(x) for x in axis_dir],
            "frames_fused": frames_fused, "fuse_max_frames": fuse_max_frames, "n_points": int(len(rec.points)),
            "points": "scene_points.ply", "mesh": "scene_mesh.ply" if (d / "scene_mesh.ply").exists() else None,
            "clusters": clusters, "dropped_clusters": list(rec.dropped), "problems": problems,
            "viewpoints": [[float(x) for x in v] for v in viewpoints]}
    write_json(d / "reconstruction.json", meta)
    return meta


def load_reconstruction(d: Path) -> tuple[dict, list[np.ndarray]]:
    """``reconstruction.json`` of the folder ``d`` and its clusters' (N,3) points."""
    meta = read_json(d / "reconstruction.json")
    return meta, [read_ply_points(d / c["file"]) for c in meta["clusters"]]
