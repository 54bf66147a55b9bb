"""The simulated rig: UR5 kinematics, scenes, stickers, the ray-cast renderer, sensor models, truth."""
