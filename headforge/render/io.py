"""Writers for images and videos a person looks at. Both write to a temporary name and
rename when complete, so an interrupted run never leaves a file that looks finished."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError


def to_uint8(image: np.ndarray | torch.Tensor) -> np.ndarray:
    """(H, W, C) float in [0, 1] (or uint8) -> (H, W, 3) uint8 RGB (grey is repeated)."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    if image.dtype != np.uint8:
        image = (np.clip(np.nan_to_num(image), 0, 1) * 255 + 0.5).astype(np.uint8)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return np.ascontiguousarray(image[..., :3])


def _make_parent(path: Path) -> None:
    if path.is_dir():
        raise HeadforgeError(f"cannot write {path}: it is a folder")
    blocker = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise HeadforgeError(f"cannot write {path}: {blocker} is a file, not a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # no permission, read-only disk
        raise HeadforgeError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_png(path: str | Path, image: np.ndarray | torch.Tensor) -> Path:
    from PIL import Image

    path = Path(path)
    _make_parent(path)
    tmp = path.with_name(path.name + ".partial.png")
    try:
        Image.fromarray(to_uint8(image)).save(tmp)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise HeadforgeError(f"cannot write {path}: {exc}") from None
    tmp.replace(path)
    return path


def write_mp4(path: str | Path, frames: Iterable[np.ndarray | torch.Tensor], fps: float = 30.0,
              total: int | None = None, description: str = "writing video", crf: int = 18) -> Path:
    """Encode frames (H, W, 3) in [0, 1] or uint8 to H.264 MP4 with a progress bar.

    Frame sizes are padded to even numbers (yuv420p needs them). ``fps`` is kept exactly as a
    fraction (25, 29.97, 12.5, ...).
    """
    from fractions import Fraction

    import av
    from rich.progress import Progress

    if not 0 < fps <= 1000:
        raise HeadforgeError(f"fps must be in (0, 1000], got {fps}")
    rate = Fraction(fps).limit_denominator(1001)
    path = Path(path)
    _make_parent(path)
    tmp = path.with_name(path.name + ".partial.mp4")
    stream = None
    count = 0
    try:
        with av.open(str(tmp), mode="w") as container, Progress(transient=True) as progress:
            task = progress.add_task(description, total=total)
            for frame in frames:
                image = to_uint8(frame)
                h, w = image.shape[:2]
                if stream is None:
                    stream = container.add_stream("libx264", rate=rate)
                    stream.width, stream.height = w + w % 2, h + h % 2
                    stream.pix_fmt = "yuv420p"
                    stream.options = {"crf": str(crf)}
                if (h + h % 2, w + w % 2) != (stream.height, stream.width):
                    raise HeadforgeError(f"frame {count} is {w}x{h}, the video is {stream.width}x{stream.height}")
                image = np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
                for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                    container.mux(packet)
                count += 1
                progress.advance(task)
            if stream is None:
                raise HeadforgeError(f"no frames to write to {path}")
            for packet in stream.encode():
                container.mux(packet)
    except HeadforgeError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise HeadforgeError(f"cannot write {path}: {exc}") from None
    tmp.replace(path)
    return path
