"""The per-frame parameter record and the head-to-camera transform: the one home of both.

A frame's parameters (``FrameParams``) are a dict of (B, ...) float tensors with the keys
``FRAME_KEYS``: ``expression`` (B, n_expr), the axis-angle joint rotations ``root_pose``,
``neck_pose``, ``jaw_pose``, ``eye_left_pose``, ``eye_right_pose`` (B, 3, radians, FLAME's
convention), and ``translation`` (B, 3, metres, camera frame). Datasets store them as (T, ...)
tensors in ``tracking.safetensors``; avatars as per-frame ``nn.Parameter`` s.

The camera is fixed at the origin (OpenCV axes: x right, y down, z forward); the head moves.
A canonical head point x (metres, y up, face toward +z), posed by the head model with a frame's
joint rotations, lands in the camera frame at ``diag(1, -1, -1) x + translation``
(:func:`head_to_camera`).
"""

from __future__ import annotations

import numpy as np
import torch

FRAME_KEYS = ("expression", "root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose", "translation")
POSE_KEYS = FRAME_KEYS[1:6]  # the head model's joint rotations, in its POSE_ARGS order
FLIP = (1.0, -1.0, -1.0)  # canonical head axes (y up, z toward the viewer) -> OpenCV camera axes

FrameParams = dict[str, torch.Tensor]


def head_to_camera(points: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) posed canonical points -> camera space: ``diag(1, -1, -1) x + translation``
    (``translation`` (B, 3) metres)."""
    return points * points.new_tensor(FLIP) + translation[:, None].to(points.dtype)


def flip_matrix() -> np.ndarray:
    """(3, 3) ``diag(1, -1, -1)``: the rotation part of :func:`head_to_camera`."""
    return np.diag(FLIP)


def head_to_camera_matrices(root_pose: np.ndarray, translation: np.ndarray, root_joint: np.ndarray) -> np.ndarray:
    """(T, 4, 4) rigid transforms canonical head space -> camera (OpenCV) of the whole head, from
    the root rotation ``root_pose`` (T, 3; about the rest root joint ``root_joint`` (3,)) and
    ``translation`` (T, 3)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(root_pose).as_matrix()  # (T, 3, 3)
    F = flip_matrix()
    out = np.zeros((len(R), 4, 4))
    out[:, :3, :3] = F @ R
    out[:, :3, 3] = (F @ (root_joint - R @ root_joint).T).T + translation
    out[:, 3, 3] = 1
    return out


def select(params: FrameParams, rows) -> FrameParams:
    """The rows ``rows`` (an index tensor, list or slice) of every parameter."""
    return {k: params[k][rows] for k in FRAME_KEYS}


def from_tracking(tracking: dict[str, torch.Tensor]) -> FrameParams:
    """The (T, ...) float32 frame parameters of a dataset's tracking tensors."""
    missing = [k for k in FRAME_KEYS if k not in tracking]
    if missing:
        from headforge.errors import HeadforgeError

        raise HeadforgeError(f"tracking has no {', '.join(missing)}")
    return {k: tracking[k].float().clone() for k in FRAME_KEYS}
