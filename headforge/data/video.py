"""Video decoding with PyAV (rotation metadata honoured), or a folder of numbered images.

A folder source (``frames/00000.png``, ... sorted by name; PNG/JPEG, all of one size) behaves
like a video at :data:`FOLDER_FPS` (a folder has no rate of its own: ``headforge track`` takes
the real one as an option): what ``headforge synth`` renders, or frames a user exported from
another tool.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}
FOLDER_FPS = 30.0  # the frame rate assumed for a folder of frames


def image_files(folder: str | Path) -> list[Path]:
    """The images of a frame folder, sorted by name; an error if there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise HeadforgeError(f"not a folder: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not files:
        raise HeadforgeError(f"no PNG/JPEG frames in folder {folder}")
    return files


def _read_image(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise HeadforgeError(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def is_video(path: str | Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def _check_file(path: Path) -> None:
    if not path.is_file():
        raise HeadforgeError(f"video not found: {path}")
    if path.stat().st_size == 0:
        raise HeadforgeError(f"video is empty (0 bytes): {path}")


def _upright(frame) -> np.ndarray:
    image = frame.to_ndarray(format="rgb24")
    rotation = int(getattr(frame, "rotation", 0) or 0)
    return np.ascontiguousarray(np.rot90(image, k=(rotation // 90) % 4)) if rotation else image


def video_info(path: str | Path) -> dict:
    """fps, frame count (container's estimate, may be 0) and size of the first video stream."""
    import av

    path = Path(path)
    if path.is_dir():
        files = image_files(path)
        h, w = _read_image(files[0]).shape[:2]
        return {"fps": FOLDER_FPS, "frames": len(files), "width": w, "height": h}
    _check_file(path)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise HeadforgeError(f"no video stream in {path}")
            stream = container.streams.video[0]
            fps = float(stream.average_rate or stream.base_rate or 30)
            return {"fps": fps, "frames": int(stream.frames or 0), "width": stream.codec_context.width,
                    "height": stream.codec_context.height}
    except HeadforgeError:
        raise
    except Exception as exc:
        raise HeadforgeError(f"cannot decode video {path}: {exc}") from None


def iter_frames(path: str | Path, every: int = 1, max_frames: int | None = None):
    """Yield (frame index, (H, W, 3) uint8 RGB upright) for every ``every``-th frame of a video
    file or an image folder."""
    import av

    path = Path(path)
    if every < 1:
        raise HeadforgeError(f"--every must be >= 1, got {every}")
    if path.is_dir():
        size = None
        for count, i in enumerate(range(0, len(files := image_files(path)), every)):
            if max_frames is not None and count >= max_frames:
                return
            image = _read_image(files[i])
            size = size or image.shape[:2]
            if image.shape[:2] != size:
                raise HeadforgeError(f"{files[i]} is {image.shape[1]}x{image.shape[0]}, the frames before it in "
                                     f"{path} are {size[1]}x{size[0]}")
            yield i, image
        return
    _check_file(path)
    count = 0
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise HeadforgeError(f"no video stream in {path}")
            container.streams.video[0].thread_type = "AUTO"
            for i, frame in enumerate(container.decode(video=0)):
                if i % every:
                    continue
                if max_frames is not None and count >= max_frames:
                    return
                yield i, _upright(frame)
                count += 1
    except HeadforgeError:
        raise
    except Exception as exc:
        raise HeadforgeError(f"cannot decode video {path}: {exc}") from None


def read_frame(path: str | Path, index: int = 0) -> np.ndarray:
    """Frame ``index`` (0-based, decode order) of a video as (H, W, 3) uint8 RGB, upright."""
    if index < 0:
        raise HeadforgeError(f"frame index must be >= 0, got {index}")
    for i, image in iter_frames(path):
        if i == index:
            return image
    raise HeadforgeError(f"{path} has fewer than {index + 1} frames")


def read_picture(path: str | Path, frame: int = 0) -> np.ndarray:
    """An RGB uint8 image from a picture file, or frame ``frame`` of a video file."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if is_video(path):
        return read_frame(path, frame)
    if not path.is_file():
        raise HeadforgeError(f"image not found: {path}")
    try:
        return np.asarray(Image.open(path).convert("RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise HeadforgeError(f"cannot read image {path}: {exc}") from None
