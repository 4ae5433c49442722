"""Fit a head model to the MediaPipe landmarks of one image (rigid + shape + expression).

Camera: OpenCV pinhole at the origin, focal ``focal_factor * max(H, W)`` pixels, principal
point at the image centre. The head's canonical frame (y up, face toward +z) is turned to the
camera frame by diag(1, -1, -1), then rotated by the root pose and translated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.landmarks import FACE_OVAL, N_MEDIAPIPE, detect_mediapipe
from headforge.head.model import HeadModel
from headforge.head.pose import head_to_camera
from headforge.render.camera import project_points


@dataclass
class ImageFitConfig:
    steps: int = 300
    lr: float = 0.02
    n_shape: int = 50  # identity components optimised (the rest stay 0)
    shape_prior: float = 2e-3  # weight of ||shape||^2 (coefficients are ~N(0, 1))
    expression_prior: float = 1e-3
    oval_weight: float = 0.3  # face-oval points depend on the silhouette: trusted less
    focal_factor: float = 1.6

    @classmethod
    def quick(cls) -> "ImageFitConfig":
        return cls(steps=150)

    @classmethod
    def paper(cls) -> "ImageFitConfig":
        return cls(steps=600, n_shape=100)


@dataclass
class ImageFit:
    params: dict[str, torch.Tensor]  # HeadModel inputs, batch 1
    K: np.ndarray  # (3, 3)
    detected: np.ndarray  # (478, 2) px
    projected: np.ndarray  # (478, 2) px
    vertices_cam: np.ndarray  # (V, 3) camera-space vertices (metres)
    median_px: float
    median_px_inner: float


def fit_image(model: HeadModel, image: np.ndarray, config: ImageFitConfig = ImageFitConfig()) -> ImageFit:
    """Fit ``model`` (with a 478-point MediaPipe embedding) to ``image`` (H, W, 3)."""
    if model.num_landmarks != N_MEDIAPIPE:
        raise HeadforgeError(f"fit-image needs a model with MediaPipe's {N_MEDIAPIPE} landmarks; "
                             f"{model.name!r} has {model.num_landmarks}")
    detected = detect_mediapipe(image)
    if detected is None:
        raise HeadforgeError("no face found in the image")
    h, w = image.shape[:2]
    focal = config.focal_factor * max(h, w)
    K = torch.tensor([[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1.0]])
    target = torch.tensor(detected, dtype=torch.float32)
    weight = torch.ones(N_MEDIAPIPE)
    weight[FACE_OVAL] = config.oval_weight

    # Initial depth from the inter-ocular distance (model vs image).
    with torch.no_grad():
        rest = model().landmarks[0]
    eye_model = (rest[33] - rest[263]).norm().item()
    eye_image = float(np.linalg.norm(detected[33] - detected[263]))
    depth = focal * eye_model / max(eye_image, 1.0)
    centre = (target[[33, 263]].mean(0) - K[:2, 2]) * depth / focal

    shape = torch.zeros(1, config.n_shape, requires_grad=True)
    expr_logit = torch.full((1, model.n_expr), -4.0, requires_grad=True)  # expression in (0, 1)
    root = torch.zeros(1, 3, requires_grad=True)
    jaw = torch.zeros(1, 3, requires_grad=True)
    trans = torch.tensor([[centre[0].item(), centre[1].item(), depth]], requires_grad=True)
    opt = torch.optim.Adam([shape, expr_logit, root, jaw, trans], lr=config.lr)

    def params():
        full_shape = torch.cat([shape, torch.zeros(1, model.n_shape - config.n_shape)], 1)
        return dict(shape=full_shape, expression=torch.sigmoid(expr_logit), root_pose=root, jaw_pose=jaw)

    def landmarks_cam():
        out = model(**params())
        return out, head_to_camera(out.landmarks, trans)

    scale = 1.0 / max(eye_image, 1.0)  # loss in units of the inter-ocular distance
    for step in range(config.steps):
        # Rigid first (expression/shape frozen), then everything.
        rigid_only = step < config.steps // 4
        opt.zero_grad()
        _, lmk = landmarks_cam()
        err = (project_points(lmk, K)[0] - target).norm(dim=-1) * scale
        loss = (weight * torch.nn.functional.huber_loss(err, torch.zeros_like(err), reduction="none", delta=0.05)).mean()
        loss = loss + config.shape_prior * shape.pow(2).mean() + config.expression_prior * torch.sigmoid(expr_logit).mean()
        loss.backward()
        if rigid_only:
            shape.grad = None
            expr_logit.grad = None
            jaw.grad = None
        opt.step()
    with torch.no_grad():
        out, lmk = landmarks_cam()
        projected = project_points(lmk, K)[0].numpy()
        verts_cam = head_to_camera(out.vertices, trans)[0].numpy()
    errors = np.linalg.norm(projected - detected, axis=1)
    inner = np.setdiff1d(np.arange(N_MEDIAPIPE), FACE_OVAL)
    fitted = {k: v.detach() for k, v in params().items()} | {"translation": trans.detach()}
    return ImageFit(fitted, K.numpy(), detected, projected, verts_cam, float(np.median(errors)),
                    float(np.median(errors[inner])))


def overlay(image: np.ndarray, fit: ImageFit, faces: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """The image with the fitted model shaded on top, detected landmarks in green and the
    model's landmarks in red. Returns (H, W, 3) uint8."""
    from headforge.render.camera import PinholeCamera
    from headforge.render.raycast import raycast, shade_lambert

    h, w = image.shape[:2]
    cam = PinholeCamera(K=fit.K, R=np.eye(3), t=np.zeros(3), width=w, height=h)
    verts = fit.vertices_cam.astype(np.float64)
    hits = raycast(verts, faces, cam)
    albedo = np.broadcast_to(np.array([0.75, 0.8, 0.95]), hits.bary.shape)
    shaded = shade_lambert(hits, faces, verts, albedo, cam, light_dir=(0.3, -0.4, -1.0))
    base = image[..., :3].astype(np.float64) / (255.0 if image.dtype == np.uint8 else 1.0)
    out = np.where(hits.mask[..., None], (1 - alpha) * base + alpha * shaded, base)
    out = (np.clip(out, 0, 1) * 255).astype(np.uint8)
    r = max(0, round(min(h, w) / 500))
    for pts, colour in ((fit.detected, (40, 230, 40)), (fit.projected, (240, 40, 40))):
        for x, y in np.round(pts).astype(int):
            out[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1] = colour
    return out
