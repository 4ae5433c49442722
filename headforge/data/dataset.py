"""The headforge dataset format written by ``headforge track`` and ``headforge synth``.

    DATASET/
      dataset.json          format/version, model, resolution, fps, intrinsics K (crop pixels,
                            OpenCV), per-frame records {index, source_frame, valid, split,
                            image, mask, crop: [cx, cy, size] in source pixels}
      tracking.safetensors  shape (1, S); per frame (T, ...): expression, root_pose, neck_pose,
                            jaw_pose, eye_left_pose, eye_right_pose, translation (metres, camera
                            frame), landmarks (T, 478, 2) MediaPipe in crop pixels, valid (T,)
      frames/00000.png      RGB crops, resolution^2
      masks/00000.png       foreground masks (selfie segmentation), uint8
      metrics.json, overlay.mp4, transforms.json (NeRF-style, head-centric cameras)

``fps`` is the rate of the kept frames: the source video's rate (or the rate given for a folder
of frames, 30 by default) divided by ``every``.

The camera is fixed at the origin (OpenCV axes); the head moves (headforge.head.pose: a posed
canonical head vertex x lands at diag(1, -1, -1) x + translation).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from headforge.errors import HeadforgeError
from headforge.head.pose import FRAME_KEYS

FORMAT = "headforge-dataset"
VERSION = 1


TRACKING_KEYS = ("shape", "expression", "root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose",
                 "translation", "landmarks", "valid")
META_KEYS = ("model", "resolution", "intrinsics", "frames")


def read_meta(root: str | Path) -> dict:
    """``dataset.json`` of a dataset folder, checked for format, version and required keys."""
    root = Path(root)
    path = root / "dataset.json"
    if not path.is_file():
        partial = root.with_name(root.name + ".partial")
        hint = f" (an unfinished run is in {partial}: re-run the command to resume)" if partial.exists() else ""
        raise HeadforgeError(f"{root} is not a headforge dataset: dataset.json missing{hint}")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise HeadforgeError(f"{path} is not valid JSON: {exc}") from None
    if meta.get("format") != FORMAT:
        raise HeadforgeError(f"{path} is not a headforge dataset (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise HeadforgeError(f"{root} was written by dataset version {meta.get('version')}, this headforge reads "
                             f"version {VERSION}: re-run headforge track")
    missing = [key for key in META_KEYS if key not in meta]
    if missing:
        raise HeadforgeError(f"{path} lacks {', '.join(repr(k) for k in missing)}: re-run headforge track")
    return meta


def load_tracking(root: str | Path, meta: dict | None = None) -> dict[str, torch.Tensor]:
    """``tracking.safetensors`` of a dataset folder as tensors; a one-line error when it is
    missing, unreadable (truncated, not safetensors), lacks a key, or does not cover the frames
    of ``dataset.json`` (``meta``, read when not given)."""
    root = Path(root)
    meta = read_meta(root) if meta is None else meta
    path = root / "tracking.safetensors"
    if not path.is_file():
        raise HeadforgeError(f"{path} is missing")
    try:
        tracking = load_file(str(path))
    except Exception as exc:  # safetensors raises its own SafetensorError, OSError, ...
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise HeadforgeError(f"{path} is unreadable (truncated or not safetensors: {reason}): re-run headforge track") from None
    missing = [key for key in TRACKING_KEYS if key not in tracking]
    if missing:
        raise HeadforgeError(f"{path} lacks {', '.join(missing)}: re-run headforge track")
    T = len(meta["frames"])
    short = [key for key in TRACKING_KEYS if key != "shape" and tracking[key].shape[0] != T]
    if short or tracking["shape"].ndim != 2:
        key = short[0] if short else "shape"
        raise HeadforgeError(f"{path}: '{key}' has shape {tuple(tracking[key].shape)}, dataset.json lists {T} frames")
    return tracking


def read_image(path: Path, grey: bool = False) -> np.ndarray:
    """A dataset image as float32 in [0, 1]: (H, W, 3) RGB, or (H, W) with ``grey``; a one-line
    error names a missing or unreadable file."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise HeadforgeError(f"{path} is missing")
    try:
        with Image.open(path) as handle:
            array = np.asarray(handle.convert("L") if grey else handle.convert("RGB"), np.float32)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise HeadforgeError(f"{path} is unreadable: {exc}") from None
    return array / 255


class HeadDataset(torch.utils.data.Dataset):
    """Frames of a headforge dataset as dicts of tensors.

    Item: image (H, W, 3) float in [0, 1], mask (H, W) float, landmarks (478, 2), the frame's
    head-model parameters (expression, *_pose, translation) and ``shape`` (S,), ``index``.
    """

    def __init__(self, root: str | Path, split: str = "train", valid_only: bool = True):
        if split not in ("train", "val", "all"):
            raise HeadforgeError(f"split must be train, val or all, got {split!r}")
        self.root = Path(root)
        self.meta = read_meta(self.root)
        self.tracking = load_tracking(self.root, self.meta)
        self.K = torch.tensor(self.meta["intrinsics"], dtype=torch.float32)
        self.records = [r for r in self.meta["frames"]
                        if (split == "all" or r["split"] == split) and (r["valid"] or not valid_only)]
        for r in self.records[:1] + self.records[-1:]:
            for key in ("image", "mask"):
                if not (self.root / r[key]).is_file():
                    raise HeadforgeError(f"{self.root / r[key]} is missing")

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> dict:
        r = self.records[i]
        t = r["index"]
        image = torch.from_numpy(read_image(self.root / r["image"]))
        mask = torch.from_numpy(read_image(self.root / r["mask"], grey=True))
        size = self.meta["resolution"]
        if image.shape[:2] != (size, size) or mask.shape != (size, size):
            wrong = r["image"] if image.shape[:2] != (size, size) else r["mask"]
            raise HeadforgeError(f"{self.root / wrong} is not {size}x{size} as dataset.json says")
        item = {"index": t, "image": image, "mask": mask, "landmarks": self.tracking["landmarks"][t],
                "shape": self.tracking["shape"][0]}
        for key in FRAME_KEYS:
            item[key] = self.tracking[key][t]
        return item


def export_transforms(root: str | Path, root_joint: np.ndarray) -> dict:
    """NeRF-style ``transforms.json`` in the head's canonical frame: per frame the camera pose
    that sees the (static) canonical head as the real camera saw the moving head."""
    meta = read_meta(root)
    return transforms_from(meta, load_tracking(root, meta), root_joint)


def transforms_from(meta: dict, tracking: dict, root_joint: np.ndarray) -> dict:
    """:func:`export_transforms` from in-memory ``dataset.json`` content and tracking tensors."""
    from headforge.head.pose import head_to_camera_matrices
    from headforge.render.camera import Cameras

    w2c = head_to_camera_matrices(tracking["root_pose"].double().numpy(), tracking["translation"].double().numpy(), root_joint)
    T = len(w2c)
    K = torch.tensor(meta["intrinsics"], dtype=torch.float64).expand(T, 3, 3)
    cams = Cameras(K, torch.from_numpy(w2c[:, :3, :3]), torch.from_numpy(w2c[:, :3, 3]), meta["resolution"], meta["resolution"])
    out = cams.to_nerf_transforms([r["image"] for r in meta["frames"]])
    for frame, record in zip(out["frames"], meta["frames"]):
        frame.update(mask_path=record["mask"], valid=record["valid"], split=record["split"])
    return out
