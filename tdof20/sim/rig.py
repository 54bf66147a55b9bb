"""Geometry of the simulated rig: a UR5 arm carrying the camera, and the turntable.

Frames (millimetres): ``base`` is the robot base frame (z up); ``table`` is the turntable frame
at angle 0 (origin at the centre of the table top, z up); the table turns about its z axis, so
at angle theta the table frame is ``T_base_table0 @ Rz(theta)``; ``cam`` is the OpenCV camera
frame (x right, y down, z forward) with ``T_base_cam = T_base_tcp @ T_tcp_cam``.

The arm positions are joint vectors of a real UR5 (standard DH parameters), chosen by inverse
kinematics so that the camera looks at the table from several elevations; the session records
both the joints and ``T_base_tcp = fk(q)``, so the simulated session is exactly as consistent as
the real robot's read-back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tdof20.geometry import PinholeCamera, compose, invert, look_at, make_T, rotation_about_axis

# UR5 standard Denavit-Hartenberg parameters (Universal Robots), millimetres and radians.
UR5_D = np.array([89.159, 0.0, 0.0, 109.15, 94.65, 82.3])
UR5_A = np.array([0.0, -425.0, -392.25, 0.0, 0.0, 0.0])
UR5_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
UR5_REACH_MM = 850.0
#: the shoulder (the origin of joint 2's frame: joint 1 turns about it) in the base frame, mm
UR5_SHOULDER = np.array([0.0, 0.0, UR5_D[0]])
#: the farthest the tool flange (T_base_tcp's origin) gets from the shoulder, mm: joints 2-4 turn
#: about parallel axes (alpha 0), so the upper arm and forearm (a2, a3) lie in a plane normal to
#: them and the offsets d2..d4 along them; the wrist's offsets (a4..a6, d5, d6) add at most their
#: lengths. 1001 mm for the UR5: a bound, never less than what the arm reaches.
UR5_FLANGE_REACH_MM = float(np.hypot(abs(UR5_A[1]) + abs(UR5_A[2]), abs(UR5_D[1] + UR5_D[2] + UR5_D[3]))
                            + np.abs(UR5_A[3:]).sum() + np.abs(UR5_D[4:]).sum())


def ur5_fk(q: np.ndarray) -> np.ndarray:
    """Forward kinematics: 6 joint angles (rad) -> T_base_tcp (4,4), mm."""
    q = np.asarray(q, dtype=float).reshape(6)
    T = np.eye(4)
    for th, d, a, al in zip(q, UR5_D, UR5_A, UR5_ALPHA):
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct],
                          [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    return T


def ur5_ik(T_target: np.ndarray, q_seed: np.ndarray, tol_mm: float = 1e-3) -> np.ndarray:
    """Numerical inverse kinematics near ``q_seed`` (rad). Raises ValueError if unreachable: at
    once for a flange farther from the shoulder than the arm reaches (:data:`UR5_FLANGE_REACH_MM`),
    where the search (8 starts of up to 2,000 evaluations) could only fail."""
    from scipy.optimize import least_squares  # imported on first use: importing the rig stays light
    from scipy.spatial.transform import Rotation

    T_target = np.asarray(T_target, dtype=float)
    R_t = T_target[:3, :3]
    dist = float(np.linalg.norm(T_target[:3, 3] - UR5_SHOULDER))
    # the largest position residual is at least the distance beyond the reach over sqrt(3)
    if not dist - UR5_FLANGE_REACH_MM <= np.sqrt(3.0) * tol_mm:  # (NaN: no pose either)
        raise ValueError(f"UR5 cannot reach the target pose (its flange {dist:.0f} mm from the shoulder, "
                         f"the arm reaches {UR5_FLANGE_REACH_MM:.0f} mm)")

    def residual(q):
        T = ur5_fk(q)
        rot = Rotation.from_matrix(R_t.T @ T[:3, :3]).as_rotvec()
        return np.concatenate([T[:3, 3] - T_target[:3, 3], 100.0 * rot])

    best = None
    for k in range(8):
        seed = np.asarray(q_seed, dtype=float) + (0 if k == 0 else np.random.default_rng(k).normal(0, 0.3, 6))
        sol = least_squares(residual, seed, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        err = np.abs(sol.fun).max()
        if best is None or err < best[1]:
            best = (sol.x, err)
        if err < tol_mm:
            break
    q, err = best
    if err >= tol_mm:
        raise ValueError(f"UR5 cannot reach the target pose (residual {err:.3f})")
    return (q + np.pi) % (2 * np.pi) - np.pi


def oakd_camera(width: int = 640, height: int = 480, depth_scale: float = 1.0) -> PinholeCamera:
    """Intrinsics like an OAK-D colour camera at 640x480 (about 69 deg horizontal field of view)."""
    K = np.array([[465.0, 0.0, 319.5], [0.0, 465.0, 239.5], [0.0, 0.0, 1.0]])
    cam = PinholeCamera(K, 640, 480, depth_scale)
    return cam if (width, height) == (640, 480) else cam.scaled(width, height)


# A camera bracket: 60 mm beside and 45 mm ahead of the flange, tilted by about 2 degrees.
DEFAULT_T_TCP_CAM = compose(make_T(np.eye(3), [0.0, -60.0, 45.0]),
                            rotation_about_axis([1.0, 0.5, 0.0], np.radians(2.0)))
UR5_HOME = np.array([0.0, -1.3, 1.6, -1.8, -1.57, 0.0])


@dataclass(frozen=True)
class RigLayout:
    """Where things stand in the base frame, and how the arm positions are chosen."""

    table_centre: tuple = (850.0, 0.0, -100.0)   # centre of the table top in the base frame, mm
    table_radius: float = 250.0                    # turntable top radius, mm
    table_thickness: float = 40.0                  # turntable disk height, mm
    view_distance: float = 450.0                   # camera to look-at point, mm
    look_height: float = 60.0                      # look-at point above the table centre, mm
    elevations_deg: tuple = (22.0, 36.0, 50.0, 64.0)
    azimuth_deg: float = 180.0                     # camera stands on the robot's side of the table
    T_tcp_cam: np.ndarray = field(default_factory=lambda: DEFAULT_T_TCP_CAM.copy())

    @property
    def T_base_table0(self) -> np.ndarray:
        return make_T(np.eye(3), self.table_centre)

    def T_base_table(self, angle_deg: float) -> np.ndarray:
        """Table frame at turntable angle ``angle_deg`` (counter-clockwise seen from above)."""
        return self.T_base_table0 @ rotation_about_axis([0, 0, 1], np.radians(angle_deg))

    def elevations(self, n_arms: int) -> np.ndarray:
        if n_arms == len(self.elevations_deg):
            return np.asarray(self.elevations_deg, dtype=float)
        if n_arms < 1:
            raise ValueError("need at least one arm position")
        lo, hi = self.elevations_deg[0], self.elevations_deg[-1]
        return np.linspace(lo, hi, n_arms) if n_arms > 1 else np.array([(lo + hi) / 2])

    def camera_target(self, elevation_deg: float) -> np.ndarray:
        """Desired T_base_cam looking at the table from ``elevation_deg`` above its plane."""
        el, az = np.radians(elevation_deg), np.radians(self.azimuth_deg)
        target = np.asarray(self.table_centre, dtype=float) + [0.0, 0.0, self.look_height]
        eye = target + self.view_distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return look_at(eye, target, up=(0.0, 0.0, 1.0))

    def arm_positions(self, n_arms: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(q (6,) rad, T_base_tcp (4,4) = fk(q))] for ``n_arms`` elevations."""
        out = []
        seed = UR5_HOME
        for el in self.elevations(n_arms):
            T_tcp = self.camera_target(el) @ invert(self.T_tcp_cam)
            q = ur5_ik(T_tcp, seed)
            out.append((q, ur5_fk(q)))
            seed = q
        return out
