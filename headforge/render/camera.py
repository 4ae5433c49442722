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


# ---- batched torch cameras for the differentiable renderer --------------------------------
import torch  # noqa: E402

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])  # camera axes: x right, y up, z backward


@dataclass
class Cameras:
    """A batch of pinhole cameras (OpenCV convention), torch tensors.

    K: (B, 3, 3) intrinsics in pixels; R: (B, 3, 3) and t: (B, 3) world-to-camera
    (``x_cam = R x_world + t``); one image size for the batch.
    """

    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    width: int
    height: int

    def __post_init__(self):
        B = self.K.shape[0]
        if self.K.shape != (B, 3, 3) or self.R.shape != (B, 3, 3) or self.t.shape != (B, 3):
            raise ValueError(f"Cameras need K (B,3,3), R (B,3,3), t (B,3); got {tuple(self.K.shape)}, "
                             f"{tuple(self.R.shape)}, {tuple(self.t.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def batch_size(self) -> int:
        return self.K.shape[0]

    @classmethod
    def at_origin(cls, K: torch.Tensor, batch: int, width: int, height: int | None = None) -> "Cameras":
        """``batch`` cameras at the origin with OpenCV axes (R = I, t = 0) and intrinsics ``K``
        (3, 3) or (B, 3, 3): the camera of every headforge dataset, where the head moves."""
        K = K.expand(batch, 3, 3)
        return cls(K, torch.eye(3, dtype=K.dtype, device=K.device).expand(batch, 3, 3), K.new_zeros(batch, 3),
                   width, width if height is None else height)

    @classmethod
    def from_pinhole(cls, cams: list[PinholeCamera], dtype=torch.float32) -> "Cameras":
        if len({(c.width, c.height) for c in cams}) != 1:
            raise ValueError("all cameras of a batch must share one image size")
        as_t = lambda key: torch.tensor(np.stack([getattr(c, key) for c in cams]), dtype=dtype)  # noqa: E731
        return cls(as_t("K"), as_t("R"), as_t("t"), cams[0].width, cams[0].height)

    def pinhole(self, index: int = 0) -> PinholeCamera:
        n = lambda x: x[index].detach().double().cpu().numpy()  # noqa: E731
        return PinholeCamera(n(self.K), n(self.R), n(self.t), self.width, self.height)

    def to(self, device) -> "Cameras":
        return Cameras(self.K.to(device), self.R.to(device), self.t.to(device), self.width, self.height)

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) world points -> (B, N, 3) camera coordinates (z forward, metres)."""
        return points @ self.R.transpose(1, 2).to(points.dtype) + self.t[:, None].to(points.dtype)

    def project_finite(self, points: torch.Tensor) -> torch.Tensor:
        """:meth:`project` with non-finite results set to 0, for differentiable stages: NaN
        points are invisible anyway, and a NaN in a masked-out branch would still poison
        gradients (0 * NaN = NaN)."""
        xyz = self.project(points)
        return torch.where(torch.isfinite(xyz), xyz, torch.zeros_like(xyz))

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) world points -> (B, N, 3): pixel x, pixel y, camera depth z."""
        cam = self.world_to_camera(points)
        z = cam[..., 2:3]
        safe = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
        uv = (cam @ self.K.transpose(1, 2).to(points.dtype))[..., :2] / safe
        return torch.cat([uv, z], dim=-1)

    # -- converters ------------------------------------------------------------------------
    def to_opengl_c2w(self) -> torch.Tensor:
        """(B, 4, 4) camera-to-world matrices with OpenGL camera axes (x right, y up, z back)."""
        c2w = torch.zeros(self.batch_size, 4, 4, dtype=self.R.dtype, device=self.R.device)
        flip = torch.as_tensor(OPENCV_TO_OPENGL, dtype=self.R.dtype, device=self.R.device)
        c2w[:, :3, :3] = self.R.transpose(1, 2) @ flip
        c2w[:, :3, 3] = -(self.R.transpose(1, 2) @ self.t[..., None])[..., 0]
        c2w[:, 3, 3] = 1
        return c2w

    @classmethod
    def from_opengl_c2w(cls, c2w: torch.Tensor, K: torch.Tensor, width: int, height: int) -> "Cameras":
        flip = torch.as_tensor(OPENCV_TO_OPENGL, dtype=c2w.dtype, device=c2w.device)
        R = (c2w[:, :3, :3] @ flip).transpose(1, 2)
        t = -(R @ c2w[:, :3, 3:4])[..., 0]
        return cls(K, R, t, width, height)

    def to_nerf_transforms(self, file_paths: list[str] | None = None) -> dict:
        """A NeRF/instant-ngp style ``transforms.json`` dict (per-frame intrinsics)."""
        c2w = self.to_opengl_c2w().detach().cpu().double().numpy()
        K = self.K.detach().cpu().double().numpy()
        frames = []
        for i in range(self.batch_size):
            frames.append({"file_path": file_paths[i] if file_paths else f"{i:05d}.png",
                           "transform_matrix": c2w[i].tolist(), "fl_x": K[i, 0, 0], "fl_y": K[i, 1, 1],
                           "cx": K[i, 0, 2] + 0.5, "cy": K[i, 1, 2] + 0.5,  # NeRF: pixel corners at integers
                           "w": self.width, "h": self.height})
        return {"camera_model": "OPENCV", "frames": frames}

    @classmethod
    def from_nerf_transforms(cls, transforms: dict) -> "Cameras":
        frames = transforms["frames"]
        sizes = {(int(f.get("w", transforms.get("w", 0))), int(f.get("h", transforms.get("h", 0)))) for f in frames}
        if len(sizes) != 1:
            raise ValueError("transforms.json frames must share one image size")
        width, height = sizes.pop()
        K = torch.zeros(len(frames), 3, 3, dtype=torch.float64)
        for i, f in enumerate(frames):
            get = lambda key: float(f.get(key, transforms.get(key)))  # noqa: E731
            K[i] = torch.tensor([[get("fl_x"), 0, get("cx") - 0.5], [0, get("fl_y"), get("cy") - 0.5], [0, 0, 1]],
                                dtype=torch.float64)
        c2w = torch.tensor([f["transform_matrix"] for f in frames], dtype=torch.float64)
        return cls.from_opengl_c2w(c2w, K, width, height)


def project_points(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(..., N, 3) camera-space points (OpenCV, z forward) -> (..., N, 2) pixels (centres at
    integers) with the (3, 3) intrinsics ``K``: x by K[0, 0], y by K[1, 1]."""
    return points[..., :2] / points[..., 2:] * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]


def scale_intrinsics(K: torch.Tensor, scale: float) -> torch.Tensor:
    """(3, 3) intrinsics for an image resized by ``scale`` (pixel centres at integers in both)."""
    K = K.clone()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
    return K
