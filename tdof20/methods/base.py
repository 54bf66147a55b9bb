"""What every method module is given about the dataset it works on: :class:`MethodMeta`.

Every method's pieces (the contract, :class:`tdof20.methods.contract.PoseMethod`: ``build(cfg,
meta)``, ``transform(cfg, meta, train)``, ``loss(net, batch, cfg, meta)``, ``predict_poses(net,
batch, cfg, meta)``) are given a ``meta``: the one object that tells them which objects exist,
their keypoints, sizes, symmetries and surface samples, and the network input size::

    meta = MethodMeta.from_catalog((1, 5, 12), image_size=(96, 128))
    c = meta.class_of(12)            # 3: class index of obj 12 (0 = background)
    meta.obj_of(c)                   # 12

torch-free (numpy and the catalog), so it pickles into DataLoader workers and loads without a GPU
stack.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from tdof20.errors import TdofError
from tdof20.objects import get_object

#: surface samples per object that :meth:`MethodMeta.from_catalog` takes (DenseFusion's 500 model
#: points for its ADD loss; FFB6D/PVN3D use the mesh vertices — enough for an ADD loss either way)
DEFAULT_MODEL_POINTS = 500
#: the smallest and largest image side a method takes (a typo such as 100000x100000 would try to
#: allocate tens of GB before failing)
IMAGE_SIDE = (8, 4096)


@dataclass(frozen=True, eq=False)
class MethodMeta:
    """The dataset's objects as a method sees them (all lengths in mm).

    obj_ids: the dataset's objects, in class order: class index ``c = obj_ids.index(o) + 1``;
        class 0 is the background.
    keypoints: obj_id -> (9,3) model keypoints, centre first (tdof20.objects.keypoints).
    diameters: obj_id -> diameter.
    symmetric: obj_id -> whether ADD-S (closest point) applies.
    model_points: obj_id -> (M,3) surface samples of the model (ADD losses).
    image_size: (H, W) of the network input.
    """

    obj_ids: tuple[int, ...]
    keypoints: Mapping[int, np.ndarray]
    diameters: Mapping[int, float]
    symmetric: Mapping[int, bool]
    model_points: Mapping[int, np.ndarray]
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        ids = tuple(int(o) for o in self.obj_ids)
        if not ids:
            raise TdofError("MethodMeta needs at least one object id")
        if len(set(ids)) != len(ids):
            raise TdofError(f"MethodMeta object ids repeat: {ids}")
        if any(o < 1 for o in ids):
            raise TdofError(f"MethodMeta object ids must be >= 1 (0 is the background): {ids}")
        for name in ("keypoints", "diameters", "symmetric", "model_points"):
            table = getattr(self, name)
            missing = [o for o in ids if o not in table]
            if missing:
                raise TdofError(f"MethodMeta.{name} lacks objects {missing}")
        kp = {o: np.asarray(self.keypoints[o], dtype=np.float64).reshape(-1, 3) for o in ids}
        ks = {len(v) for v in kp.values()}
        if len(ks) != 1:
            raise TdofError(f"MethodMeta keypoints differ in count between objects: {sorted(ks)}")
        hw = tuple(int(v) for v in self.image_size)
        if len(hw) != 2 or min(hw) < 1:
            raise TdofError(f"MethodMeta image_size must be (H, W) > 0, got {self.image_size}")
        object.__setattr__(self, "obj_ids", ids)
        object.__setattr__(self, "keypoints", kp)
        object.__setattr__(self, "diameters", {o: float(self.diameters[o]) for o in ids})
        object.__setattr__(self, "symmetric", {o: bool(self.symmetric[o]) for o in ids})
        object.__setattr__(self, "model_points", {
            o: np.asarray(self.model_points[o], dtype=np.float64).reshape(-1, 3) for o in ids})
        object.__setattr__(self, "image_size", hw)

    # ---------------------------------------------------------------------------------------
    @property
    def n_classes(self) -> int:
        """Objects + background."""
        return len(self.obj_ids) + 1

    @property
    def n_keypoints(self) -> int:
        return len(next(iter(self.keypoints.values())))

    def class_of(self, obj_id: int) -> int:
        """Class index (1..n) of ``obj_id``; TdofError for an object outside the dataset."""
        try:
            return self.obj_ids.index(int(obj_id)) + 1
        except ValueError:
            raise TdofError(f"object id {obj_id} is not one of this method's objects {self.obj_ids}") from None

    def obj_of(self, c: int) -> int:
        """obj_id of class index ``c`` (1..n); 0 for the background."""
        c = int(c)
        if c == 0:
            return 0
        if not 1 <= c <= len(self.obj_ids):
            raise TdofError(f"class index {c} is outside 0..{len(self.obj_ids)}")
        return self.obj_ids[c - 1]

    def class_lut(self, max_obj_id: int | None = None) -> np.ndarray:
        """(max_obj_id+1,) int64 table obj_id -> class index (0 for background and unknown ids),
        to turn a label image of obj_ids into class indices with one gather."""
        top = max(self.obj_ids) if max_obj_id is None else int(max_obj_id)
        lut = np.zeros(max(top, max(self.obj_ids)) + 1, dtype=np.int64)
        for c, o in enumerate(self.obj_ids, start=1):
            lut[o] = c
        return lut

    def keypoint_array(self) -> np.ndarray:
        """(n_classes, K, 3) keypoints by class index (row 0, the background, is zeros)."""
        out = np.zeros((self.n_classes, self.n_keypoints, 3), dtype=np.float64)
        for c, o in enumerate(self.obj_ids, start=1):
            out[c] = self.keypoints[o]
        return out

    def to_json(self) -> dict:
        """Plain-typed dict (a run records its meta); :meth:`from_json` reads it back."""
        return {
            "obj_ids": list(self.obj_ids),
            "keypoints": {str(o): self.keypoints[o].tolist() for o in self.obj_ids},
            "diameters": {str(o): self.diameters[o] for o in self.obj_ids},
            "symmetric": {str(o): self.symmetric[o] for o in self.obj_ids},
            "model_points": {str(o): self.model_points[o].tolist() for o in self.obj_ids},
            "image_size": list(self.image_size),
        }

    @classmethod
    def from_json(cls, d: Mapping) -> MethodMeta:
        try:
            return cls(
                obj_ids=tuple(int(o) for o in d["obj_ids"]),
                keypoints={int(k): np.asarray(v, dtype=np.float64) for k, v in d["keypoints"].items()},
                diameters={int(k): float(v) for k, v in d["diameters"].items()},
                symmetric={int(k): bool(v) for k, v in d["symmetric"].items()},
                model_points={int(k): np.asarray(v, dtype=np.float64) for k, v in d["model_points"].items()},
                image_size=tuple(int(v) for v in d["image_size"]),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise TdofError(f"malformed method meta ({type(exc).__name__}: {exc})") from None

    @classmethod
    def from_catalog(cls, obj_ids: Sequence[int], image_size: Sequence[int],
                     n_model_points: int = DEFAULT_MODEL_POINTS, seed: int = 0) -> MethodMeta:
        """Meta of catalog objects (tdof20.objects): their keypoints, diameters, symmetries and
        ``n_model_points`` area-uniform surface samples (deterministic in ``seed``)."""
        objs = {int(o): get_object(int(o)) for o in obj_ids}
        return cls(
            obj_ids=tuple(objs),
            keypoints={o: np.asarray(m.keypoints) for o, m in objs.items()},
            diameters={o: float(m.diameter) for o, m in objs.items()},
            symmetric={o: bool(m.symmetric) for o, m in objs.items()},
            model_points={o: m.sample_surface(int(n_model_points), seed) for o, m in objs.items()},
            image_size=tuple(int(v) for v in image_size),
        )
