"""Photometric refinement of a landmark track with the differentiable renderer (issue 4's
optional stage; NHA App. A and DECA-style trackers do the same).

After the landmark stages, the head model is rendered into the crops with a per-vertex albedo
and 2nd-order SH lighting fixed to the camera (both shared by the clip, both unknown), and the
whole clip state (shape, per-frame expression/poses/translation, focal) is refined on

* photometric L1 on the pixels where the model's face region is visible and the foreground
  mask is set (hair, beard and background never reach the face-region pixels of a good fit);
* a one-sided silhouette term: rendered head coverage outside the foreground mask (the head
  can be hidden by hair or clothes, but never sticks out of the person);
* the landmark energy of the tracker (all frames, every step), which anchors frames the
  minibatch does not visit and keeps the expression semantics;
* smoothness of the albedo over the mesh.

Shading is what landmarks lack: the light is fixed to the camera while the head turns, so the
albedo (fixed to the head) and the normals separate, and the cheek/jaw outline against the
background constrains the face width. Frames are drawn in minibatches, so the cost grows with
``steps * batch``, not with the clip length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from headforge.errors import HeadforgeError
from headforge.head.model import HeadModel
from headforge.head.topology import laplacian_smooth, vertex_normals
from headforge.render import mesh
from headforge.render.camera import Cameras, scale_intrinsics
from headforge.render.shading import constant_sh, sh_shading


@dataclass
class PhotometricConfig:
    steps: int = 300
    appearance_steps: int = 40  # first, albedo and light only (the geometry waits for them)
    batch: int = 4
    size: int = 256  # crops are compared at size^2
    lr: float = 0.002  # per-frame parameters
    lr_shape: float = 0.02
    lr_appearance: float = 0.03
    photo_weight: float = 1.0
    silhouette_weight: float = 2.0
    landmark_weight: float = 2.0
    albedo_smooth: float = 1.0
    depth_anchor: float = 1000.0  # weight of the squared relative change of the clip's mean depth
    regions: tuple[str, ...] = ("face",)  # model regions compared photometrically ...
    exclude: tuple[str, ...] = ()  # ... minus these (e.g. "eyelids", "lips" for heavy make-up)
    robust_scale: float = 0.1  # per-pixel error e -> s log(1 + e / s): hair strands and highlights weigh less
    seed: int = 0

    @classmethod
    def quick(cls) -> "PhotometricConfig":
        return cls()

    @classmethod
    def paper(cls) -> "PhotometricConfig":
        return cls(steps=1500, batch=8, size=512)


@dataclass
class PhotometricTarget:
    """What the photometric stage compares against.

    images: (T, S, S, 3) float in [0, 1], the crops resized to ``config.size``; masks: (T, S, S)
    float foreground in [0, 1]; usable: (T,) bool, frames that may be sampled (with a face);
    model: the full head model (the tracker's landmark model has only landmark vertices).
    """

    images: torch.Tensor
    masks: torch.Tensor
    usable: np.ndarray
    model: HeadModel
    config: PhotometricConfig


class Appearance(torch.nn.Module):
    """Per-vertex albedo (sigmoid of logits) and SH lighting in camera coordinates."""

    def __init__(self, n_vertices: int, mean_colour: torch.Tensor):
        super().__init__()
        logit = torch.logit(mean_colour.clamp(0.05, 0.95))
        self.albedo_logits = torch.nn.Parameter(logit.expand(n_vertices, 3).clone())
        self.sh = torch.nn.Parameter(constant_sh(1.0))

    def albedo(self) -> torch.Tensor:
        return torch.sigmoid(self.albedo_logits)


def render_batch(model: HeadModel, vertices: torch.Tensor, appearance: Appearance, K: torch.Tensor, size: int):
    """Shade camera-space ``vertices`` (B, V, 3) -> colour (B, S, S, 3), antialiased coverage
    (B, S, S) and the fragments."""
    B = vertices.shape[0]
    faces = model.faces
    cams = Cameras.at_origin(K, B, size)
    frags = mesh.rasterize(cams, vertices.detach(), faces)
    bary = mesh.barycentrics(frags, cams, vertices, faces)
    normals = F.normalize(mesh.interpolate(vertex_normals(vertices, faces), frags, faces, bary), dim=-1, eps=1e-8)
    albedo = mesh.interpolate(appearance.albedo(), frags, faces, bary)
    rgb = albedo * sh_shading(normals, appearance.sh)
    hit = frags.mask[..., None].to(vertices.dtype)
    coverage = mesh.antialias(hit, frags, cams, vertices, faces)[..., 0]
    return rgb, coverage, frags


@dataclass
class PhotometricOutcome:
    l1: float  # mean photometric L1 (sum over RGB, colours in [0, 1]) of the last 20 steps
    preview: np.ndarray  # (3 S, 3 S, 3) uint8: rows = first/middle/last usable frame; crop | render | error


def refine(params, energy, target: PhotometricTarget, progress=None) -> PhotometricOutcome:
    """Refine ``params`` (:class:`~headforge.track.tracker.ClipParameters`) in place."""
    cfg, model = target.config, target.model
    usable = np.nonzero(target.usable)[0]
    size = target.images.shape[1]
    scale = size / params.resolution
    region_faces = _region_faces(model, cfg.regions, cfg.exclude)
    fg = target.masks[usable] > 0.5
    mean_colour = (target.images[usable] * fg[..., None]).sum((0, 1, 2)) / fg.sum().clamp(min=1)
    appearance = Appearance(model.num_vertices, mean_colour)
    rng = np.random.default_rng(cfg.seed)
    # The focal stays at the landmark estimate: shading and silhouettes do not constrain it (a
    # longer focal and a larger head project alike) and letting it move lets the size drift.
    frame_leaves = [p for p in params.everything if p is not params.shape and p is not params.log_focal]
    opt = torch.optim.Adam([{"params": list(appearance.parameters()), "lr": cfg.lr_appearance},
                            {"params": frame_leaves, "lr": 0.0, "base": cfg.lr},
                            {"params": [params.shape], "lr": 0.0, "base": cfg.lr_shape}])
    depth0 = params.trans[:, 2].detach().mean()

    def shade(idx):
        out = model(**params.model_inputs(idx), translation=None)
        verts = params.to_camera(out.vertices, idx)
        rgb, coverage, frags = render_batch(model, verts, appearance, scale_intrinsics(params.K(), scale), size)
        compare = region_faces[frags.face_id.clamp(min=0)] & frags.mask & (target.masks[idx] > 0.5)
        return rgb, coverage, compare

    recent = []
    for step in range(cfg.steps):
        joint = step >= cfg.appearance_steps
        for group in opt.param_groups[1:]:
            group["lr"] = group["base"] * _cosine(step - cfg.appearance_steps, cfg.steps - cfg.appearance_steps) if joint else 0.0
        idx = torch.from_numpy(np.sort(rng.choice(usable, size=min(cfg.batch, len(usable)), replace=False)))
        opt.zero_grad()
        rgb, coverage, compare = shade(idx)
        image, mask = target.images[idx], target.masks[idx]
        error = (rgb - image).abs().sum(-1)[compare]
        photo = error.mean() if compare.any() else rgb.sum() * 0
        robust = cfg.robust_scale * torch.log1p(error / cfg.robust_scale).mean() if compare.any() else photo
        outside = (coverage * (mask < 0.5)).sum((1, 2)) / coverage.detach().sum((1, 2)).clamp(min=1)
        albedo = appearance.albedo()
        smooth = (laplacian_smooth(albedo, model.faces, 1.0, iterations=1) - albedo).abs().sum(-1).mean()
        loss = cfg.photo_weight * robust + cfg.silhouette_weight * outside.mean() + cfg.albedo_smooth * smooth
        if joint:
            anchor = (params.trans[:, 2].mean() / depth0 - 1).pow(2)
            loss = loss + cfg.landmark_weight * energy(True) + cfg.depth_anchor * anchor
        loss.backward()
        if not joint:  # appearance-only steps leave the geometry's Adam state alone
            for p in params.everything:
                p.grad = None
        opt.step()
        recent = (recent + [float(photo.detach())])[-20:]
        if progress is not None:
            progress(float(loss.detach()))
    with torch.no_grad():
        idx = torch.from_numpy(usable[[0, len(usable) // 2, len(usable) - 1]])
        rgb, coverage, compare = shade(idx)
    image = target.images[idx]
    render = image * (1 - coverage[..., None]) + rgb.clamp(0, 1) * coverage[..., None]
    error = torch.where(compare[..., None], (rgb - image).abs().sum(-1, keepdim=True).clamp(0, 1) * torch.tensor([1.0, 0.2, 0.2]),
                        image * 0.3)
    preview = torch.cat([torch.cat([image[b], render[b], error[b]], 1) for b in range(len(idx))], 0)
    l1 = float(np.mean(recent)) if recent else float("nan")
    return PhotometricOutcome(l1, (preview.numpy() * 255).round().astype(np.uint8))


def _cosine(step: int, total: int, floor: float = 0.05) -> float:
    t = min(max(step, 0) / max(total, 1), 1.0)
    return floor + (1 - floor) * 0.5 * (1 + np.cos(np.pi * t))


def _region_faces(model: HeadModel, regions: tuple[str, ...], exclude: tuple[str, ...] = ()) -> torch.Tensor:
    """(F,) bool: triangles with all three corners in one of ``regions`` and none of ``exclude``."""
    inside = torch.zeros(model.num_vertices, dtype=torch.bool)
    for name in regions:
        inside[model.region(name)] = True
    for name in exclude:
        if name in model.region_names:
            inside[model.region(name)] = False
    return inside[model.faces].all(-1)


def load_target(frames: list, masks: list, usable: np.ndarray, model: HeadModel, config: PhotometricConfig) -> PhotometricTarget:
    """Read crop and mask image files (lists of paths, one per frame) resized to ``config.size``."""
    import cv2

    size = config.size
    images = np.empty((len(frames), size, size, 3), np.uint8)
    alphas = np.empty((len(frames), size, size), np.uint8)
    for t, (f, m) in enumerate(zip(frames, masks)):
        bgr, alpha = cv2.imread(str(f), cv2.IMREAD_COLOR), cv2.imread(str(m), cv2.IMREAD_GRAYSCALE)
        if bgr is None or alpha is None:
            raise HeadforgeError(f"cannot read crop or mask of frame {t}: {f}, {m}")
        images[t] = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), (size, size), interpolation=cv2.INTER_AREA)
        alphas[t] = cv2.resize(alpha, (size, size), interpolation=cv2.INTER_AREA)
    return PhotometricTarget(torch.from_numpy(images).float() / 255, torch.from_numpy(alphas).float() / 255,
                             usable, model, config)
