"""Video preprocessing: MediaPipe landmarks (tracking mode) and selfie masks per frame, and a
temporally smooth square crop window around the face.

Crop windows are (cx, cy, size) in source-frame pixels; a crop maps the window onto a
``resolution``^2 image. Frames where MediaPipe finds no face are flagged invalid; their
windows are interpolated from the neighbours so the crop never jumps.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from headforge.data.video import iter_frames
from headforge.errors import HeadforgeError


@dataclass
class ClipDetections:
    frame_indices: np.ndarray  # (T,) indices in the source video
    landmarks: np.ndarray  # (T, 478, 2) source pixels, NaN where no face
    valid: np.ndarray  # (T,) bool
    frame_size: tuple[int, int]  # (width, height) of the source frames
    seconds: float  # wall-clock seconds spent

    def save(self, path) -> None:
        np.savez(path, frame_indices=self.frame_indices, landmarks=self.landmarks, valid=self.valid,
                 frame_size=np.array(self.frame_size), seconds=self.seconds)

    @classmethod
    def load(cls, path) -> "ClipDetections":
        with np.load(path) as z:
            return cls(z["frame_indices"], z["landmarks"], z["valid"], tuple(int(v) for v in z["frame_size"]),
                       float(z["seconds"]))


def detect_clip(path, every: int = 1, max_frames: int | None = None, progress=None) -> ClipDetections:
    """MediaPipe face mesh in tracking mode (478 points with irises) on every kept frame."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    import mediapipe as mp

    start = time.perf_counter()
    face_mesh = mp.solutions.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=True,
                                                min_detection_confidence=0.5, min_tracking_confidence=0.5)
    indices, landmarks, size = [], [], (0, 0)
    try:
        for i, image in iter_frames(path, every, max_frames):
            h, w = image.shape[:2]
            size = (w, h)
            result = face_mesh.process(image)
            if result.multi_face_landmarks:
                pts = np.array([(p.x, p.y) for p in result.multi_face_landmarks[0].landmark]) * [w, h] - 0.5
            else:
                pts = np.full((478, 2), np.nan)
            indices.append(i)
            landmarks.append(pts)
            if progress is not None:
                progress(len(indices))
    finally:
        face_mesh.close()
    if not indices:
        raise HeadforgeError(f"{path} has no frames to process")
    lmk = np.stack(landmarks)
    return ClipDetections(np.array(indices), lmk, ~np.isnan(lmk[:, 0, 0]), size, time.perf_counter() - start)


class Segmenter:
    """MediaPipe selfie segmentation: (H, W, 3) uint8 -> (H, W) uint8 foreground * 255."""

    def __init__(self):
        os.environ.setdefault("GLOG_minloglevel", "2")
        import mediapipe as mp

        self._model = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        mask = self._model.process(image).segmentation_mask
        return (np.clip(mask, 0, 1) * 255 + 0.5).astype(np.uint8)

    def close(self) -> None:
        self._model.close()


def crop_windows(landmarks: np.ndarray, valid: np.ndarray, frame_size: tuple[int, int], scale: float = 1.9,
                 smooth_sigma: float = 2.0) -> np.ndarray:
    """Square crop windows (T, 3) = (cx, cy, size) around the face, smooth over time.

    The centre follows the landmark bounding box (Gaussian-smoothed over ``smooth_sigma``
    frames); the size is constant over the clip (``scale`` x the median face extent), so the
    avatar never sees zoom jitter. Invalid frames take interpolated centres.
    """
    if not valid.any():
        raise HeadforgeError("no face was found in any frame")
    T = len(valid)
    lo = np.full((T, 2), np.nan)
    hi = np.full((T, 2), np.nan)
    lo[valid], hi[valid] = landmarks[valid].min(axis=1), landmarks[valid].max(axis=1)
    centre = 0.5 * (lo + hi)
    extent = np.max(hi - lo, axis=1)
    t = np.arange(T)
    for k in range(2):
        centre[:, k] = np.interp(t, t[valid], centre[valid, k])
    if T > 1 and smooth_sigma > 0:
        centre = gaussian_filter1d(centre, smooth_sigma, axis=0, mode="nearest")
    # Never larger than the frame (padding adds nothing); then keep the window inside it.
    width, height = frame_size
    size = min(float(np.median(extent[valid]) * scale), float(min(width, height)))
    centre[:, 0] = np.clip(centre[:, 0], size / 2 - 0.5, width - size / 2 - 0.5)
    centre[:, 1] = np.clip(centre[:, 1], size / 2 - 0.5, height - size / 2 - 0.5)
    return np.concatenate([centre, np.full((T, 1), size)], axis=1)


def crop_matrix(window: np.ndarray, resolution: int) -> np.ndarray:
    """2x3 affine matrix mapping source pixels to crop pixels (pixel centres at integers)."""
    cx, cy, size = window
    s = resolution / size
    return np.array([[s, 0, (resolution - 1) / 2 - s * cx], [0, s, (resolution - 1) / 2 - s * cy]])


def crop(image: np.ndarray, window: np.ndarray, resolution: int, interpolation=cv2.INTER_AREA) -> np.ndarray:
    """Resample the window of ``image`` (H, W[, C]) to (resolution, resolution[, C]); outside the
    frame is black (zero)."""
    M = crop_matrix(window, resolution)
    flags = interpolation if resolution < window[2] else cv2.INTER_LINEAR
    return cv2.warpAffine(image, M, (resolution, resolution), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def transform_points(points: np.ndarray, window: np.ndarray, resolution: int) -> np.ndarray:
    """(N, 2) source pixels -> crop pixels."""
    M = crop_matrix(window, resolution)
    return points @ M[:, :2].T + M[:, 2]
