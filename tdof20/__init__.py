"""tdof20 — build and benchmark 6DoF pose datasets of transparent objects.

Units: millimetres for every length; poses map model -> camera (x_cam = R @ x_model + t).
"""

__version__ = "0.1.0"
