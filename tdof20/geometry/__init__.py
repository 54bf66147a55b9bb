"""Camera model, rigid transforms, fitting and sampling: pure vectorised numpy, millimetres."""

from tdof20.geometry.camera import PinholeCamera
from tdof20.geometry.fitting import kabsch
from tdof20.geometry.normals import normals_from_xyz
from tdof20.geometry.sampling import farthest_point_sampling
from tdof20.geometry.transforms import (
    compose,
    invert,
    look_at,
    make_T,
    orthonormalize,
    rotation_about_axis,
    rotation_angle,
    rotation_matrix,
    split_T,
    transform_points,
)

__all__ = [
    "PinholeCamera", "kabsch", "normals_from_xyz", "farthest_point_sampling", "compose", "invert",
    "look_at", "make_T", "orthonormalize", "rotation_about_axis", "rotation_angle", "rotation_matrix",
    "split_T", "transform_points",
]
