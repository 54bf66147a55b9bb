"""A BOP models folder checked before it is used: :func:`load_models`.

One check for every stage that takes a user's models (annotate --models, dataset build): the
folder and models_info.json exist, every object has a readable mesh in millimetres whose diameter
agrees with models_info.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.bop import MODELS_INFO, model_path, read_model_mesh, read_models_info
from tdof20.objects.catalog import mesh_diameter

_METRES_BELOW_MM = 5.0     # no object of this field is under 5 mm across: a smaller model is in metres
_INFO_TOL = 0.05           # the mesh's diameter and models_info.json's may differ by 5 %


def load_models(models_dir: str | Path, obj_ids=None, need_faces: bool = True) -> dict[int, tuple[np.ndarray, np.ndarray, dict]]:
    """A user's (or a single-object scene's) BOP models folder -> {obj_id: (V (n,3) mm, F (m,3),
    models_info entry)}, every object of ``obj_ids`` (default: all of models_info.json).

    Checked before anything is used: the folder and models_info.json exist, every object has a
    readable triangle mesh, the mesh is in millimetres (a model under 5 mm across, or one a
    thousand times smaller than its models_info diameter, is in metres) and its diameter agrees
    with models_info.json within 5 %. Every problem raises TdofError naming the file.
    ``need_faces=False`` takes point clouds too (a BOP models_eval/ folder)."""
    d = Path(models_dir)
    if not d.is_dir():
        raise TdofError("models folder not found (--models: a BOP models folder, obj_{id:06d}.ply in mm + "
                        "models_info.json)", d)
    if not (d / MODELS_INFO).exists():
        raise TdofError(f"no {MODELS_INFO} in the models folder (a BOP models folder is expected)", d)
    infos = read_models_info(d)
    ids = sorted(infos) if obj_ids is None else sorted({int(o) for o in obj_ids})
    missing = [o for o in ids if o not in infos]
    if missing:
        raise TdofError(f"no entry for object(s) {missing} (the session's objects must have models)", d / MODELS_INFO)
    out = {}
    for o in ids:
        p = model_path(d, o)
        V, F = read_model_mesh(p, need_faces=need_faces)
        dia = float(mesh_diameter(V)) if len(V) >= 4 else float(np.ptp(V, axis=0).max())
        info_dia = float(infos[o]["diameter"])
        if info_dia < _METRES_BELOW_MM:
            raise TdofError(f"object {o}: diameter {info_dia:g} looks like metres, millimetres expected",
                            d / MODELS_INFO)
        if dia < _METRES_BELOW_MM:
            raise TdofError(f"the model is {dia:.4g} across: looks like metres, millimetres expected "
                            f"(models_info.json says {info_dia:.1f} mm)", p)
        if abs(dia - info_dia) > _INFO_TOL * info_dia:
            raise TdofError(f"the mesh is {dia:.1f} mm across but models_info.json says {info_dia:.1f} mm "
                            f"(another model, or another unit)", p)
        out[o] = (V, F, infos[o])
    return out
