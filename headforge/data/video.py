"""Video decoding with PyAV (rotation metadata honoured)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm"}


def is_video(path: str | Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def read_frame(path: str | Path, index: int = 0) -> np.ndarray:
    """Frame ``index`` (0-based, decode order) of a video as (H, W, 3) uint8 RGB, upright."""
    import av

    path = Path(path)
    if not path.is_file():
        raise HeadforgeError(f"video not found: {path}")
    if path.stat().st_size == 0:
        raise HeadforgeError(f"video is empty (0 bytes): {path}")
    if index < 0:
        raise HeadforgeError(f"frame index must be >= 0, got {index}")
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise HeadforgeError(f"no video stream in {path}")
            for i, frame in enumerate(container.decode(video=0)):
                if i == index:
                    image = frame.to_ndarray(format="rgb24")
                    rotation = int(getattr(frame, "rotation", 0) or 0)
                    return np.ascontiguousarray(np.rot90(image, k=(rotation // 90) % 4)) if rotation else image
    except HeadforgeError:
        raise
    except Exception as exc:  # PyAV raises several error types for broken files
        raise HeadforgeError(f"cannot decode video {path}: {exc}") from None
    raise HeadforgeError(f"{path} has fewer than {index + 1} frames")
