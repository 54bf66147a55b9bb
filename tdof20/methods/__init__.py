"""Pose estimation methods behind one interface (:mod:`tdof20.methods.registry`), and their shared
parts: the ResNet encoders, HFF6DoF, keypoint voting, fitting, losses.

    from tdof20.methods.registry import get_method, method_names
    m = get_method("pvnet")              # the method's module is imported on first use
    from tdof20.methods import HFF6DoF, geometry_map, vote_keypoints_batched, kabsch_torch, hff_loss

Importing this package (and the registry) does not import torch: the names below load on first
access, so ``tdof20 --help`` and ``tdof20 train --help`` stay fast.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "kabsch_torch": "tdof20.methods.fitting",
    "HFF6DoF": "tdof20.methods.hff6dof", "count_macs": "tdof20.methods.hff6dof",
    "count_parameters": "tdof20.methods.hff6dof", "fill_depth_holes": "tdof20.methods.data",
    "geometry_map": "tdof20.methods.hff6dof",
    "hff_loss": "tdof20.methods.losses",
    "ResNet34": "tdof20.methods.resnet", "load_torchvision_state_dict": "tdof20.methods.resnet",
    "vote_keypoints": "tdof20.methods.voting", "vote_keypoints_batched": "tdof20.methods.voting",
    "vote_keypoints_list": "tdof20.methods.voting",
    "Method": "tdof20.methods.registry", "get_method": "tdof20.methods.registry",
    "method_names": "tdof20.methods.registry", "register": "tdof20.methods.registry",
    "PoseMethod": "tdof20.methods.contract",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'tdof20.methods' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
