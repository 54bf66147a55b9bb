"""BOP object models: ``models_info.json`` (diameter, bounding box, symmetries) and the model
meshes ``obj_{obj_id:06d}.ply`` in millimetres, as the BOP toolkit documents them
(``docs/bop_datasets_format.md`` of https://github.com/thodan/bop_toolkit)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop_json import check_nums, check_rotation, flat, is_num, write_bop_json
from tdof20.formats.io import atomic_write_bytes, dumps_json, read_bytes, read_json

MODELS_INFO = "models_info.json"


# ---------------------------------------------------------------------------------------------
# models_info.json
# ---------------------------------------------------------------------------------------------
_MODEL_NUM = ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


def _check_model_entry(path: Path, obj_id: int, e: Any) -> None:
    w = f"object {obj_id}"
    if not isinstance(e, dict):
        raise TdofError(f"{w}: entry must be an object, got {type(e).__name__}", path)
    if "diameter" not in e:
        raise TdofError(f"{w}: missing field 'diameter'", path)
    if not is_num(e["diameter"]) or e["diameter"] <= 0:
        raise TdofError(f"{w}: diameter must be a number > 0 (mm), got {e['diameter']!r}", path)
    for k in _MODEL_NUM:
        if k in e and not is_num(e[k]):
            raise TdofError(f"{w}: {k} must be a finite number, got {e[k]!r}", path)
        if k.startswith("size") and k in e and e[k] < 0:
            raise TdofError(f"{w}: {k} must be >= 0, got {e[k]!r}", path)
    sd = e.get("symmetries_discrete", [])
    if not isinstance(sd, list):
        raise TdofError(f"{w}: symmetries_discrete must be a list of 16-number transforms", path)
    for i, s in enumerate(sd):
        T = check_nums(path, s, 16, f"{w}: symmetries_discrete[{i}]").reshape(4, 4)
        check_rotation(path, flat(T[:3, :3]), f"{w}: symmetries_discrete[{i}] rotation")
    sc = e.get("symmetries_continuous", [])
    if not isinstance(sc, list):
        raise TdofError(f"{w}: symmetries_continuous must be a list of {{axis, offset}}", path)
    for i, s in enumerate(sc):
        if not isinstance(s, dict) or "axis" not in s or "offset" not in s:
            raise TdofError(f"{w}: symmetries_continuous[{i}] must be an object with 'axis' and 'offset'", path)
        if np.linalg.norm(check_nums(path, s["axis"], 3, f"{w}: symmetries_continuous[{i}].axis")) == 0:
            raise TdofError(f"{w}: symmetries_continuous[{i}].axis has zero length", path)
        check_nums(path, s["offset"], 3, f"{w}: symmetries_continuous[{i}].offset")


def _models_info_path(path: str | Path) -> Path:
    p = Path(path)
    return p if p.suffix == ".json" else p / MODELS_INFO


def write_models_info(dir: str | Path, infos: dict[int, dict]) -> Path:
    """Validate and write ``<dir>/models_info.json`` ({"<obj_id>": {"diameter": mm, "min_x", ...,
    "size_z", optional "symmetries_discrete", "symmetries_continuous"}}) atomically."""
    path = _models_info_path(dir)
    content = {}
    for obj_id, e in infos.items():
        e = json.loads(dumps_json(e, indent=None))
        _check_model_entry(path, int(obj_id), e)
        content[str(int(obj_id))] = e
    write_bop_json(path, content)
    return path


def read_models_info(path: str | Path) -> dict[int, dict]:
    """Read ``models_info.json`` (give the models folder or the file) -> {obj_id: entry}."""
    p = _models_info_path(path)
    data = read_json(p)
    if not isinstance(data, dict):
        raise TdofError(f"must hold a JSON object keyed by object id, got {type(data).__name__}", p)
    out = {}
    for k, e in data.items():
        try:
            obj_id = int(k)
        except ValueError:
            raise TdofError(f"key {k!r} is not an integer object id", p) from None
        _check_model_entry(p, obj_id, e)
        out[obj_id] = e
    return out




# ---------------------------------------------------------------------------------------------
# model meshes (obj_{id:06d}.ply)
# ---------------------------------------------------------------------------------------------
def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """``<models_dir>/obj_{obj_id:06d}.ply``."""
    return Path(models_dir) / f"obj_{int(obj_id):06d}.ply"


def read_model_mesh(path: str | Path, need_faces: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read a model (PLY/OBJ/STL, mm) -> vertices (V,3) float64, faces (F,3) int64. One reader
    for every stage; a missing, unreadable, empty or non-finite model raises TdofError naming the
    file (``need_faces=False`` accepts a point cloud: faces then has shape (0,3))."""
    import trimesh
    from trimesh.resolvers import FilePathResolver

    p = Path(path)
    data = read_bytes(p, "model file")
    try:
        geom = trimesh.load(io.BytesIO(data), file_type=p.suffix.lstrip(".").lower() or None, process=False,
                            resolver=FilePathResolver(str(p)))
    except Exception as e:  # trimesh raises many types on bad files
        raise TdofError(f"cannot read the model ({type(e).__name__}: {e})", p) from None
    if isinstance(geom, trimesh.Scene):
        geom = geom.to_geometry() if len(geom.geometry) else None
    V = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    F = np.asarray(getattr(geom, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(V) == 0:
        raise TdofError("the model has no vertices", p)
    if not np.isfinite(V).all():
        raise TdofError("the model has NaN or inf vertices", p)
    if need_faces and len(F) == 0:
        raise TdofError("the model has no faces (a triangle mesh is needed)", p)
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise TdofError("the model's faces index vertices that do not exist", p)
    return V, F


def write_model_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a model atomically as binary little-endian PLY with vertex normals (mm), the form
    the BOP toolkit and trimesh read."""
    import trimesh

    tm = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)
    p = Path(path)
    atomic_write_bytes(p, trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True))
    return p


__all__ = ["MODELS_INFO", "write_models_info", "read_models_info", "model_path", "read_model_mesh", "write_model_mesh"]
