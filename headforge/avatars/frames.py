"""A dataset split held in memory at the training resolution, with the scoring protocol's
regions (:mod:`headforge.metrics.protocol`) precomputed from the tracked head model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.landmarks import FACE_OVAL_LOOP


def face_oval_masks(landmarks: torch.Tensor, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The landmark-derived face region: (N, H, W) uint8 coverage of each frame's detected
    face-oval loop (MediaPipe's FACE_OVAL_LOOP; ``landmarks`` (N, L, 2) pixels, centres at
    integers) and (N,) bool, whether the frame has one (all loop points detected, MediaPipe's
    478 landmarks). Coverage = a 4x4 supersampled fill averaged down (cv2's own antialiased
    fill grows polygons by about half a pixel)."""
    import cv2

    ss, shift = 4, 4  # supersampling; cv2 fixed-point bits for sub-pixel corners
    out = np.zeros((len(landmarks), resolution, resolution), np.uint8)
    known = np.zeros(len(landmarks), bool)
    if landmarks.shape[1] == 478:
        canvas = np.zeros((resolution * ss, resolution * ss), np.uint8)
        for i, lmk in enumerate(landmarks.numpy()):
            loop = (lmk[list(FACE_OVAL_LOOP)] + 0.5) * ss - 0.5
            if np.isfinite(loop).all():
                canvas[:] = 0
                cv2.fillPoly(canvas, [np.round(loop * (1 << shift)).astype(np.int32)], 255, cv2.LINE_8, shift)
                out[i] = cv2.resize(canvas, (resolution, resolution), interpolation=cv2.INTER_AREA)
                known[i] = True
    return torch.from_numpy(out), torch.from_numpy(known)


class FrameData:
    """The valid frames of one split (train or val) of a dataset, resized to ``resolution``:
    uint8 images and masks, landmarks, the landmark face oval, and the protocol's head and face
    regions (bool) from ``head`` (a :class:`~headforge.metrics.protocol.TrackedHead`)."""

    PER_FRAME = ("images", "masks", "landmarks", "face_regions", "face_known", "index", "regions", "face_scored")

    def __init__(self, root: Path, split: str, resolution: int, head):
        from headforge.data.dataset import HeadDataset
        from headforge.head.pose import from_tracking
        from headforge.render.camera import Cameras, scale_intrinsics

        ds = HeadDataset(root, split)
        if len(ds) == 0:
            raise HeadforgeError(f"{root} has no valid {split} frames")
        self.meta = ds.meta
        scale = resolution / ds.meta["resolution"]
        imgs, masks, lmks, idx = [], [], [], []
        for i in range(len(ds)):
            item = ds[i]
            x = torch.cat([item["image"], item["mask"][..., None]], -1).permute(2, 0, 1)[None]
            x = torch.nn.functional.interpolate(x, size=(resolution, resolution), mode="area")[0].permute(1, 2, 0)
            imgs.append((x[..., :3] * 255).round().to(torch.uint8))
            masks.append((x[..., 3] * 255).round().to(torch.uint8))
            lmks.append((item["landmarks"] + 0.5) * scale - 0.5)
            idx.append(item["index"])
        self.images, self.masks = torch.stack(imgs), torch.stack(masks)
        self.landmarks = torch.stack(lmks).float()
        self.face_regions, self.face_known = face_oval_masks(self.landmarks, resolution)
        self.index = torch.tensor(idx)
        self.K = scale_intrinsics(torch.tensor(ds.meta["intrinsics"], dtype=torch.float32), scale)
        self.resolution = resolution
        tracked = {k: v[self.index] for k, v in from_tracking(ds.tracking).items()}
        self.regions, self.face_scored = head.regions(tracked, Cameras.at_origin(self.K, len(self), resolution))

    def __len__(self) -> int:
        return len(self.index)

    def to(self, device: torch.device | str) -> "FrameData":
        """Move the per-frame tensors and the intrinsics to ``device`` (in place)."""
        for key in (*self.PER_FRAME, "K"):
            setattr(self, key, getattr(self, key).to(device))
        return self

    def subset(self, rows: torch.Tensor) -> "FrameData":
        """A view of the frames ``rows`` (positions in this split)."""
        sub = object.__new__(FrameData)
        sub.__dict__.update(self.__dict__)
        for key in FrameData.PER_FRAME:
            setattr(sub, key, getattr(self, key)[rows])
        return sub

    def batch(self, rows: torch.Tensor) -> dict:
        """image (B, H, W, 3), mask and face_region (B, H, W) in [0, 1], face_known (B,) bool
        (a face oval was detected), landmarks (B, L, 2) pixels, index (B,) dataset frames,
        region / face_scored (B, H, W) bool: the protocol's head and face regions."""
        return {"image": self.images[rows].float() / 255, "mask": self.masks[rows].float() / 255,
                "face_region": self.face_regions[rows].float() / 255, "face_known": self.face_known[rows],
                "landmarks": self.landmarks[rows], "index": self.index[rows], "region": self.regions[rows],
                "face_scored": self.face_scored[rows]}
