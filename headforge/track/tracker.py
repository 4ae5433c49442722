"""Analysis-by-synthesis tracking of a whole clip at once.

Unknowns: identity shape shared by the clip; per frame: expression, root rotation and
translation (rigid head pose), neck, jaw and eye rotations; one focal length. Camera: OpenCV
pinhole at the origin looking down +z, principal point at the crop centre; the head's
canonical frame (y up, face toward +z) is turned to the camera frame by diag(1, -1, -1).

Energy (NHA Sec. 3.1, App. A): L1 landmark reprojection error in inter-ocular units (face-oval points
down-weighted) + NHA's eye-lid distance term (so blinks are tracked) + priors on shape,
expression and joint rotations + temporal smoothness of every per-frame parameter. Frames
without landmarks have no data term: smoothness carries them.

Stages: rigid pose (+ focal) -> everything on landmarks -> optionally a photometric refinement
with the renderer (:mod:`headforge.track.photometric`), which keeps the landmark energy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.landmarks import N_MEDIAPIPE, LandmarkSpec
from headforge.head.model import HeadModel
from headforge.head.pose import FRAME_KEYS, head_to_camera
from headforge.render.camera import project_points



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
    frames: dict[str, torch.Tensor]  # FRAME_KEYS -> (T, ...)
    K: np.ndarray  # (3, 3) crop-pixel intrinsics
    projected: np.ndarray  # (T, L, 2) model landmarks in crop pixels
    errors: np.ndarray  # (T, L) px distance to the matching detections (NaN on invalid frames)
    spec: LandmarkSpec  # which detection each model landmark matches
    photometric_l1: float | None = None  # mean colour error of the photometric stage (None: not run)
    photometric_preview: np.ndarray | None = None  # crop | render | error rows (uint8), see photometric.refine

    def median_px(self, exclude_oval: bool = True) -> float:
        cols = ~self.spec.contour if exclude_oval else np.ones(len(self.spec.contour), bool)
        return float(np.nanmedian(self.errors[:, cols]))


class ClipParameters:
    """The unknowns of a clip (leaf tensors with gradients) and how they drive a head model.

    shape (1, n_shape) — the first ``n_shape`` identity components, the rest stay 0;
    expression logits or values (T, E); poses (T, 3) axis-angle; translation (T, 3) metres in
    camera space; ``log_focal`` scalar (crop pixels).
    """

    def __init__(self, model: HeadModel, T: int, n_shape: int, translation: np.ndarray, focal: float,
                 optimise_focal: bool, resolution: int):
        self.n_model_shape, self.resolution = model.n_shape, resolution
        self.bounded = model.meta.get("expression_range") == [0.0, 1.0]
        self.log_focal = torch.tensor(float(np.log(focal)), dtype=torch.float32, requires_grad=optimise_focal)
        self.shape = torch.zeros(1, n_shape, requires_grad=True)
        self.expr = torch.full((T, model.n_expr), -4.0 if self.bounded else 0.0, requires_grad=True)
        self.poses = {k: torch.zeros(T, 3, requires_grad=True) for k in FRAME_KEYS[1:6]}
        self.trans = torch.tensor(translation, dtype=torch.float32, requires_grad=True)

    @property
    def rigid(self) -> list[torch.Tensor]:
        return [self.poses["root_pose"], self.trans] + ([self.log_focal] if self.log_focal.requires_grad else [])

    @property
    def everything(self) -> list[torch.Tensor]:
        return self.rigid + [self.shape, self.expr] + [self.poses[k] for k in FRAME_KEYS[2:6]]

    def expression(self, idx=slice(None)) -> torch.Tensor:
        return torch.sigmoid(self.expr[idx]) if self.bounded else self.expr[idx]

    def full_shape(self) -> torch.Tensor:
        """(1, S) all identity coefficients of the model."""
        return torch.cat([self.shape, torch.zeros(1, self.n_model_shape - self.shape.shape[1])], 1)

    def model_inputs(self, idx=slice(None)) -> dict[str, torch.Tensor]:
        """HeadModel keyword arguments for frames ``idx`` (root pose included, no translation)."""
        expression = self.expression(idx)
        return {"shape": self.full_shape().expand(len(expression), -1), "expression": expression,
                **{k: self.poses[k][idx] for k in FRAME_KEYS[1:6]}}

    def to_camera(self, points: torch.Tensor, idx=slice(None)) -> torch.Tensor:
        """(B, N, 3) posed canonical points of frames ``idx`` -> camera space (metres)."""
        return head_to_camera(points, self.trans[idx])

    def K(self) -> torch.Tensor:
        """(3, 3) intrinsics of the ``resolution``^2 crop (differentiable in the focal)."""
        c = (self.resolution - 1) / 2
        f = self.log_focal.exp()
        zero = torch.tensor(0.0)
        return torch.stack([torch.stack([f, zero, torch.tensor(c)]), torch.stack([zero, f, torch.tensor(c)]),
                            torch.tensor([0.0, 0.0, 1.0])])

    def result_frames(self) -> dict[str, torch.Tensor]:
        return {"expression": self.expression().detach(), **{k: v.detach() for k, v in self.poses.items()},
                "translation": self.trans.detach()}


class LandmarkEnergy:
    """The landmark terms of the clip energy (see the module docstring) for a landmarks-only model."""

    def __init__(self, model: HeadModel, params: ClipParameters, landmarks: np.ndarray, valid: np.ndarray,
                 spec: LandmarkSpec, config: TrackerConfig, inter_ocular_px: float):
        self.model, self.params, self.spec, self.config = model, params, spec, config
        self.target = torch.tensor(np.nan_to_num(landmarks), dtype=torch.float32)
        self.valid = torch.tensor(valid)
        weight = torch.ones(len(spec.detection_ids))
        weight[torch.from_numpy(spec.contour)] = config.oval_weight
        self.frame_w = self.valid.float()[:, None] * weight  # (T, L)
        self.scale = 1.0 / max(inter_ocular_px, 1.0)

    def project(self) -> torch.Tensor:
        """(T, L, 2) model landmarks in crop pixels."""
        out = self.model(**self.params.model_inputs(), translation=None)
        return project_points(self.params.to_camera(out.landmarks), self.params.K())

    def __call__(self, stage_all: bool) -> torch.Tensor:
        p, c = self.params, self.config
        proj = self.project()
        err = (proj - self.target).norm(dim=-1) * self.scale  # (T, L), inter-ocular units
        data = (self.frame_w * err).sum() / self.frame_w.sum()  # L1 on landmark distances, as NHA
        if not stage_all:
            return data + c.smooth * (_smooth(p.poses["root_pose"]) + _smooth(p.trans))
        pairs = self.spec.eyelid_pairs
        lid_model = proj[:, pairs[:, 0]] - proj[:, pairs[:, 1]]
        lid_det = self.target[:, pairs[:, 0]] - self.target[:, pairs[:, 1]]
        lid = (self.valid.float()[:, None] * (lid_model - lid_det).norm(dim=-1) * self.scale).sum() / (self.valid.sum() * len(pairs))
        e = p.expression()
        prior = (c.shape_prior * p.shape.pow(2).mean()
                 + c.expression_prior * (e.abs().mean() if p.bounded else e.pow(2).mean())
                 + c.pose_prior * sum(p.poses[k].pow(2).mean() for k in FRAME_KEYS[2:6]))
        smooth = sum(_smooth(v) for v in [e] + list(p.poses.values())) + _smooth(p.trans)
        return data + c.eyelid_weight * lid + prior + c.smooth * smooth


def track_landmarks(model: HeadModel, landmarks: np.ndarray, valid: np.ndarray, resolution: int,
                    config: TrackerConfig = TrackerConfig(), progress=None, photometric=None) -> TrackResult:
    """Fit ``model`` to MediaPipe landmarks (T, 478, 2) in crop pixels of a ``resolution``^2 crop.

    Models embedding MediaPipe's 478 points use them all; models embedding iBUG-68 (FLAME)
    use the matching 68 detections (:class:`~headforge.head.landmarks.LandmarkSpec`).

    Pass ``HeadModel(data, landmarks_only=True)``: the same landmarks at a fraction of the cost.
    ``photometric``: a :class:`headforge.track.photometric.PhotometricTarget` (images, masks,
    the full model) to refine the fit with the renderer after the landmark stages.
    """
    T = len(landmarks)
    if landmarks.shape[1:] != (N_MEDIAPIPE, 2):
        raise HeadforgeError(f"landmarks must be (T, {N_MEDIAPIPE}, 2), got {landmarks.shape}")
    if not valid.any():
        raise HeadforgeError("no valid frames to track")
    spec = LandmarkSpec.for_model(model.num_landmarks)
    landmarks = landmarks[:, spec.detection_ids]  # detections matching the model's landmarks
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

    params = ClipParameters(model, T, config.n_shape, trans0, f0, config.focal is None, resolution)
    energy = LandmarkEnergy(model, params, landmarks, valid, spec, config, eye_img)
    for stage_all, steps, leaves in ((False, config.rigid_steps, params.rigid), (True, config.steps, params.everything)):
        opt = torch.optim.Adam(leaves, lr=config.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1), eta_min=config.lr * 0.05)
        for step in range(steps):
            opt.zero_grad()
            loss = energy(stage_all)
            loss.backward()
            opt.step()
            sched.step()
            if progress is not None:
                progress(float(loss.detach()))
    outcome = None
    if photometric is not None:
        from headforge.track.photometric import refine

        outcome = refine(params, energy, photometric, progress)
    with torch.no_grad():
        proj = energy.project()
        K = params.K()
    projected = proj.numpy()
    errors = np.linalg.norm(projected - landmarks, axis=-1)
    errors[~valid] = np.nan
    return TrackResult(params.full_shape().detach(), params.result_frames(), K.numpy().astype(np.float64),
                       projected, errors, spec, outcome and outcome.l1, outcome and outcome.preview)


def _smooth(x: torch.Tensor) -> torch.Tensor:
    """Mean squared first difference over time (T, ...)."""
    return (x[1:] - x[:-1]).pow(2).mean() if len(x) > 1 else x.sum() * 0
