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


SUPERVISION = ("predicted", "gt")
GT_PER_FRAME = ("gt_normals", "gt_labels", "gt_known")


def load_ground_truth(root: Path, index: torch.Tensor, resolution: int) -> dict[str, torch.Tensor]:
    """A synthetic subject's ground truth for the dataset frames ``index`` (N,), at
    ``resolution`` (``headforge synth``'s gt/, docs/benchmark.md): ``landmarks`` (N, 478, 2)
    pixels (centres at integers; open-head's embedded points on the subject's surface,
    projected), ``gt_normals`` (N, H, W, 3) uint8 camera-space normals as (n + 1) / 2 * 255
    (n = 0 off the subject), ``gt_labels`` (N, H, W) uint8 synth labels, ``gt_known`` (N,) bool:
    whether the frame has its maps."""
    import cv2
    from safetensors.numpy import load_file

    from headforge.data.dataset import read_image

    gt = Path(root) / "gt"
    if not (gt / "landmarks.safetensors").is_file():
        raise HeadforgeError(f"{root} has no gt/landmarks.safetensors: ground-truth supervision needs a subject "
                             "written by this version of headforge synth")
    table = load_file(str(gt / "landmarks.safetensors"))
    row = {int(f): i for i, f in enumerate(table["frames"])}
    missing = [int(t) for t in index if int(t) not in row]
    if missing:
        raise HeadforgeError(f"{gt / 'landmarks.safetensors'} has no landmarks of frame {missing[0]}")
    size = None
    normals = np.zeros((len(index), resolution, resolution, 3), np.uint8)
    labels = np.zeros((len(index), resolution, resolution), np.uint8)
    known = np.zeros(len(index), bool)
    for i, t in enumerate(index.tolist()):
        n_path, l_path = gt / "normals" / f"{t:05d}.png", gt / "labels" / f"{t:05d}.png"
        if not (n_path.is_file() and l_path.is_file()):
            continue
        n = read_image(n_path).astype(np.float32) * 2 - 1  # (S, S, 3); 0 off the subject
        size = n.shape[0]
        n = cv2.resize(n, (resolution, resolution), interpolation=cv2.INTER_AREA)
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where(length > 0.5, n / np.maximum(length, 1e-6), 0)  # the edge's half-covered pixels out
        normals[i] = np.round((n + 1) / 2 * 255).astype(np.uint8)
        label = cv2.imread(str(l_path), cv2.IMREAD_UNCHANGED)
        if label is None or label.shape[:2] != (size, size):
            raise HeadforgeError(f"{l_path} is unreadable or not {size}x{size}")
        labels[i] = cv2.resize(label, (resolution, resolution), interpolation=cv2.INTER_NEAREST)
        known[i] = True
    if not known.any():
        raise HeadforgeError(f"{gt} has no normal and label maps of the training frames: regenerate it with headforge synth")
    scale = resolution / (size or resolution)
    lmk = torch.from_numpy(table["landmarks"][[row[int(t)] for t in index]]).float()
    return {"landmarks": (lmk + 0.5) * scale - 0.5, "gt_normals": torch.from_numpy(normals),
            "gt_labels": torch.from_numpy(labels), "gt_known": torch.from_numpy(known)}


def detector_bias(detected: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """(L, 2) pixels: the mean of ``detected`` - ``truth`` (T, L, 2) over the frames where a
    landmark was detected (0 where it never was): the detector's systematic offset from the
    ground-truth points, e.g. MediaPipe's from open-head's embedded landmarks on a synth subject
    (1.4-1.7 px median at 256 px, docs/nha_table1.md)."""
    d = detected - truth
    ok = torch.isfinite(d).all(-1, keepdim=True)
    return (torch.nan_to_num(d) * ok).sum(0) / ok.sum(0).clamp(min=1)


class FrameData:
    """The valid frames of one split (train or val) of a dataset, resized to ``resolution``:
    uint8 images and masks, landmarks, the landmark face oval, and the protocol's head and face
    regions (bool) from ``head`` (a :class:`~headforge.metrics.protocol.TrackedHead`).

    ``supervision="gt"`` (training split of a synthetic subject only): the subject's ground-truth
    landmarks replace the detected ones, and its normal and label maps come along
    (:func:`load_ground_truth`). A validation split never carries ground truth: its frames are
    fitted (test-time fitting) from what a real clip would give."""

    PER_FRAME = ("images", "masks", "landmarks", "face_regions", "face_known", "index", "regions", "face_scored")

    def __init__(self, root: Path, split: str, resolution: int, head, supervision: str = "predicted"):
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
        self.index = torch.tensor(idx)
        if supervision not in SUPERVISION:
            raise HeadforgeError(f"supervision must be one of {', '.join(SUPERVISION)}, got {supervision!r}")
        self.per_frame = FrameData.PER_FRAME
        self.detector_bias = None
        if supervision == "gt" and split == "train":
            gt = load_ground_truth(root, self.index, resolution)
            self.detector_bias = detector_bias(self.landmarks, gt["landmarks"])
            self.landmarks = gt.pop("landmarks")
            for key, value in gt.items():
                setattr(self, key, value)
            self.per_frame = FrameData.PER_FRAME + GT_PER_FRAME
        self.face_regions, self.face_known = face_oval_masks(self.landmarks, resolution)
        self.K = scale_intrinsics(torch.tensor(ds.meta["intrinsics"], dtype=torch.float32), scale)
        self.resolution = resolution
        tracked = {k: v[self.index] for k, v in from_tracking(ds.tracking).items()}
        self.regions, self.face_scored = head.regions(tracked, Cameras.at_origin(self.K, len(self), resolution))

    def correct_detections(self, bias: torch.Tensor) -> None:
        """Subtract a detector's per-landmark bias (L, 2) pixels at this resolution
        (:func:`detector_bias`, measured on other frames) from the detected landmarks, and redraw
        the face ovals from them."""
        if bias.shape != self.landmarks.shape[1:]:
            raise HeadforgeError(f"a landmark bias must be {tuple(self.landmarks.shape[1:])}, got {tuple(bias.shape)}")
        self.landmarks = self.landmarks - bias.to(self.landmarks)
        self.face_regions, self.face_known = face_oval_masks(self.landmarks.cpu(), self.resolution)
        self.face_regions, self.face_known = self.face_regions.to(self.landmarks.device), self.face_known.to(self.landmarks.device)

    def __len__(self) -> int:
        return len(self.index)

    def to(self, device: torch.device | str) -> "FrameData":
        """Move the per-frame tensors and the intrinsics to ``device`` (in place)."""
        for key in (*self.per_frame, "K"):
            setattr(self, key, getattr(self, key).to(device))
        return self

    def subset(self, rows: torch.Tensor) -> "FrameData":
        """A view of the frames ``rows`` (positions in this split)."""
        sub = object.__new__(FrameData)
        sub.__dict__.update(self.__dict__)
        for key in self.per_frame:
            setattr(sub, key, getattr(self, key)[rows])
        return sub

    def batch(self, rows: torch.Tensor) -> dict:
        """image (B, H, W, 3), mask and face_region (B, H, W) in [0, 1], face_known (B,) bool
        (a face oval was detected), landmarks (B, L, 2) pixels, index (B,) dataset frames,
        region / face_scored (B, H, W) bool: the protocol's head and face regions. With ground truth
        also gt_normals (B, H, W, 3) camera-space unit normals (length < 0.5 off the subject), gt_labels
        (B, H, W) long synth labels and gt_known (B,) bool (the frame has its maps)."""
        out = {"image": self.images[rows].float() / 255, "mask": self.masks[rows].float() / 255,
               "face_region": self.face_regions[rows].float() / 255, "face_known": self.face_known[rows],
               "landmarks": self.landmarks[rows], "index": self.index[rows], "region": self.regions[rows],
               "face_scored": self.face_scored[rows]}
        if "gt_known" in self.per_frame:
            out.update(gt_normals=self.gt_normals[rows].float() / 255 * 2 - 1, gt_labels=self.gt_labels[rows].long(),
                       gt_known=self.gt_known[rows])
        return out
