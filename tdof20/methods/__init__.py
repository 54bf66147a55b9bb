"""Networks and pose recovery: the ResNet34 encoder, HFF6DoF, keypoint voting, fitting, losses.

    from tdof20.methods import HFF6DoF, geometry_map, vote_keypoints_batched, kabsch_torch, hff_loss
"""

from tdof20.methods.fitting import kabsch_torch
from tdof20.methods.hff6dof import HFF6DoF, count_macs, count_parameters, fill_depth_holes, geometry_map
from tdof20.methods.losses import hff_loss
from tdof20.methods.resnet import ResNet34, load_torchvision_state_dict
from tdof20.methods.voting import vote_keypoints, vote_keypoints_batched, vote_keypoints_list

__all__ = [
    "HFF6DoF", "ResNet34", "count_macs", "count_parameters", "fill_depth_holes", "geometry_map", "hff_loss",
    "kabsch_torch", "load_torchvision_state_dict", "vote_keypoints", "vote_keypoints_batched",
    "vote_keypoints_list",
]
