"""Analysis-by-synthesis landmark tracking of a whole clip at once.

Unknowns: identity shape shared by the clip; per frame: expression, root rotation and
translation (rigid head pose), neck, jaw and eye rotations; one focal length. Camera: OpenCV
pinhole at the origin looking down +z, principal point at the crop centre; the head's
canonical frame (y up, face toward +z) is turned to the camera frame by diag(1, -1, -1).

Energy (NHA Sec. 3.1, App. A): L1 landmark reprojection error in inter-ocular units (face-oval points
down-weighted) + NHA's eye-lid distance term (so blinks are tracked) + priors on shape,
expression and joint rotations + temporal smoothness of every per-frame parameter. Frames
without landmarks have no data term: smoothness carries them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.fit import FLIP, project  # noqa: F401  (re-exported for the pipeline)
from headforge.head.landmarks import N_MEDIAPIPE, LandmarkSpec
from headforge.head.model import HeadModel

FRAME_PARAMS = ("expression", "root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose", "translation")


@dataclass
class TrackerConfig:
    rigid_steps: int = 150
    steps: int = 450
    lr: float = 0.02
    n_shape: int = 50
    oval_weight: float = 0.3
    eyelid_weight: float = 1.0
    shape_prior: float = 1e-3
    expression_prior: float = 2e-3
    pose_prior: float = 1e-2  # neck, jaw and eyes
    smooth: float = 0.5  # weight of squared first differences (radians, metres, expression units)
    focal_factor: float = 1.6  # initial focal length / crop size
    focal: float | None = None  # known focal length in crop pixels (then not optimised)

    @classmethod
    def quick(cls) -> "TrackerConfig":
        return cls()

    @classmethod
    def paper(cls) -> "TrackerConfig":
        return cls(rigid_steps=300, steps=1500, n_shape=100)


@dataclass
class TrackResult:
    shape: torch.Tensor  # (1, n_shape) full width of the model
    frames: dict[str, torch.Tensor]  # FRAME_PARAMS -> (T, ...)
    K: np.ndarray  # (3, 3) crop-pixel intrinsics
    projected: np.ndarray  # (T, L, 2) model landmarks in crop pixels
    errors: np.ndarray  # (T, L) px distance to the matching detections (NaN on invalid frames)
    spec: LandmarkSpec  # which detection each model landmark matches

    def median_px(self, exclude_oval: bool = True) -> float:
        cols = ~self.spec.contour if exclude_oval else np.ones(len(self.spec.contour), bool)
        return float(np.nanmedian(self.errors[:, cols]))


def track_landmarks(model: HeadModel, landmarks: np.ndarray, valid: np.ndarray, resolution: int,
                    config: TrackerConfig = TrackerConfig(), progress=None) -> TrackResult:
    """Fit ``model`` to MediaPipe landmarks (T, 478, 2) in crop pixels of a ``resolution``^2 crop.

    Models embedding MediaPipe's 478 points use them all; models embedding iBUG-68 (FLAME)
    use the matching 68 detections (:class:`~headforge.head.landmarks.LandmarkSpec`).

    Pass ``HeadModel(data, landmarks_only=True)``: the same landmarks at a fraction of the cost.
    """
    T = len(landmarks)
    if landmarks.shape[1:] != (N_MEDIAPIPE, 2):
        raise HeadforgeError(f"landmarks must be (T, {N_MEDIAPIPE}, 2), got {landmarks.shape}")
    if not valid.any():
        raise HeadforgeError("no valid frames to track")
    spec = LandmarkSpec.for_model(model.num_landmarks)
    landmarks = landmarks[:, spec.detection_ids]  # detections matching the model's landmarks
    bounded = model.meta.get("expression_range") == [0.0, 1.0]
    target = torch.tensor(np.nan_to_num(landmarks), dtype=torch.float32)
    valid_t = torch.tensor(valid)
    weight = torch.ones(len(spec.detection_ids))
    weight[torch.from_numpy(spec.contour)] = config.oval_weight
    frame_w = valid_t.float()[:, None] * weight  # (T, 478)
    c = (resolution - 1) / 2

    # Initial depth and position from the inter-ocular distance.
    with torch.no_grad():
        rest = model().landmarks[0]
    # outer eye corners: MediaPipe 33/263 = iBUG 36/45
    a, b = [int(np.nonzero(spec.detection_ids == k)[0][0]) for k in (33, 263)]
    eye_model = (rest[a] - rest[b]).norm().item()
    det = landmarks[valid]
    eye_img = float(np.median(np.linalg.norm(det[:, a] - det[:, b], axis=-1)))
    f0 = config.focal if config.focal is not None else config.focal_factor * resolution
    depth = f0 * eye_model / max(eye_img, 1.0)
    mid = np.nan_to_num(0.5 * (landmarks[:, a] + landmarks[:, b]), nan=c)
    trans0 = np.stack([(mid[:, 0] - c) * depth / f0, (mid[:, 1] - c) * depth / f0, np.full(T, depth)], 1)

    log_focal = torch.tensor(float(np.log(f0)), dtype=torch.float32, requires_grad=config.focal is None)
    shape = torch.zeros(1, config.n_shape, requires_grad=True)
    expr = torch.full((T, model.n_expr), -4.0 if bounded else 0.0, requires_grad=True)
    poses = {k: torch.zeros(T, 3, requires_grad=True) for k in FRAME_PARAMS[1:6]}
    trans = torch.tensor(trans0, dtype=torch.float32, requires_grad=True)
    rigid = [poses["root_pose"], trans] + ([log_focal] if config.focal is None else [])
    everything = rigid + [shape, expr] + [poses[k] for k in FRAME_PARAMS[2:6]]
    scale = 1.0 / max(eye_img, 1.0)

    def expression():
        return torch.sigmoid(expr) if bounded else expr

    def evaluate():
        full_shape = torch.cat([shape, torch.zeros(1, model.n_shape - config.n_shape)], 1).expand(T, -1)
        out = model(shape=full_shape, expression=expression(), translation=None,
                    **{k: poses[k] for k in FRAME_PARAMS[1:6]})
        cam = out.landmarks @ FLIP.T + trans[:, None]
        K = torch.stack([torch.stack([log_focal.exp(), torch.tensor(0.0), torch.tensor(c)]),
                         torch.stack([torch.tensor(0.0), log_focal.exp(), torch.tensor(c)]),
                         torch.tensor([0.0, 0.0, 1.0])])
        return project(cam, K), K

    def energy(stage_all: bool):
        proj, _ = evaluate()
        err = (proj - target).norm(dim=-1) * scale  # (T, 478), inter-ocular units
        data = (frame_w * err).sum() / frame_w.sum()  # L1 on landmark distances, as NHA
        if not stage_all:
            return data + config.smooth * (_smooth(poses["root_pose"]) + _smooth(trans))
        pairs = spec.eyelid_pairs
        lid_model = proj[:, pairs[:, 0]] - proj[:, pairs[:, 1]]
        lid_det = target[:, pairs[:, 0]] - target[:, pairs[:, 1]]
        lid = (valid_t.float()[:, None] * (lid_model - lid_det).norm(dim=-1) * scale).sum() / (valid_t.sum() * len(pairs))
        e = expression()
        prior = (config.shape_prior * shape.pow(2).mean()
                 + config.expression_prior * (e.abs().mean() if bounded else e.pow(2).mean())
                 + config.pose_prior * sum(poses[k].pow(2).mean() for k in FRAME_PARAMS[2:6]))
        smooth = sum(_smooth(v) for v in [e] + list(poses.values())) + _smooth(trans)
        return data + config.eyelid_weight * lid + prior + config.smooth * smooth

    for stage_all, steps, params in ((False, config.rigid_steps, rigid), (True, config.steps, everything)):
        opt = torch.optim.Adam(params, lr=config.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1), eta_min=config.lr * 0.05)
        for step in range(steps):
            opt.zero_grad()
            loss = energy(stage_all)
            loss.backward()
            opt.step()
            sched.step()
            if progress is not None:
                progress(float(loss.detach()))
    with torch.no_grad():
        proj, K = evaluate()
    projected = proj.numpy()
    errors = np.linalg.norm(projected - landmarks, axis=-1)
    errors[~valid] = np.nan
    full_shape = torch.cat([shape.detach(), torch.zeros(1, model.n_shape - config.n_shape)], 1)
    frames = {"expression": expression().detach(), **{k: v.detach() for k, v in poses.items()}, "translation": trans.detach()}
    return TrackResult(full_shape, frames, K.numpy().astype(np.float64), projected, errors, spec)


def _smooth(x: torch.Tensor) -> torch.Tensor:
    """Mean squared first difference over time (T, ...)."""
    return (x[1:] - x[:-1]).pow(2).mean() if len(x) > 1 else x.sum() * 0
