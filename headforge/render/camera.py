"""Pinhole cameras in the OpenCV convention.

World: headforge canonical space (metres, y up, face toward +z). Camera: x right, y down,
z forward (OpenCV). ``R, t`` map world to camera: ``x_cam = R @ x_world + t``. Intrinsics
``K`` in pixels; pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class PinholeCamera:
    K: np.ndarray  # (3, 3) intrinsics in pixels
    R: np.ndarray  # (3, 3) world-to-camera rotation
    t: np.ndarray  # (3,) world-to-camera translation (metres)
    width: int
    height: int

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,)."""
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixel coordinates."""
        cam = points @ self.R.T + self.t
        uvw = cam @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins and unit directions (world) through ``pixels`` (N, 2), default all
        pixel centres in row-major order."""
        if pixels is None:
            ys, xs = np.mgrid[0:self.height, 0:self.width]
            pixels = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
        homo = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=1)
        dirs = homo @ np.linalg.inv(self.K).T @ self.R  # camera -> world: multiply by R^T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return np.broadcast_to(self.centre, dirs.shape).copy(), dirs


def look_at_head(width: int = 512, height: int = 512, focal: float | None = None,
                 distance: float = 0.6, yaw_deg: float = 0.0, pitch_deg: float = 0.0,
                 target=(0.0, 0.0, 0.0)) -> PinholeCamera:
    """A camera ``distance`` metres in front of ``target`` (on +z), orbited by yaw (about
    +y) and pitch (about +x), looking at the target. Default focal gives ~30 deg FOV."""
    focal = focal if focal is not None else 1.8 * width
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    orbit = Rotation.from_euler("yx", [yaw_deg, -pitch_deg], degrees=True).as_matrix()
    # Frontal camera: looks along -z (world), image y down = world -y.
    R0 = np.diag([1.0, -1.0, -1.0])
    R = R0 @ orbit.T
    centre = np.asarray(target, dtype=np.float64) + orbit @ np.array([0.0, 0.0, distance])
    return PinholeCamera(K=K, R=R, t=-R @ centre, width=width, height=height)
