"""Energies that every avatar method can use, whatever its representation: they compare what a
method renders or projects with what :class:`headforge.avatars.frames.FrameData` holds -- the
landmarks (detected, or a synthetic subject's ground truth) and the ground-truth maps of
``--supervision gt`` -- not the geometry that produced them."""

from __future__ import annotations

import torch

from headforge.head.landmarks import EYELID_PAIRS

# MediaPipe upper/lower eyelid pairs (subject's right eye, then left): the eye opening
EYELID_UPPER, EYELID_LOWER = EYELID_PAIRS[:, 0].tolist(), EYELID_PAIRS[:, 1].tolist()


def landmark_term(projected: torch.Tensor, detected: torch.Tensor) -> torch.Tensor:
    """L1 (pixels) between projected model landmarks and detections, (B, L, 2) each, mean over
    the landmarks that were detected (NaN rows in ``detected`` are skipped); the first
    min(L, L') landmarks of both are compared."""
    n = min(projected.shape[1], detected.shape[1])
    ok = torch.isfinite(detected[:, :n]).all(-1)
    diff = (projected[:, :n] - torch.nan_to_num(detected[:, :n])).abs().sum(-1)
    return (diff * ok).sum() / ok.sum().clamp(min=1)


def eyelid_term(projected: torch.Tensor, detected: torch.Tensor) -> torch.Tensor:
    """NHA's eye-lid energy: L1 between the avatar's and the detections' 2D offsets from each
    upper to its lower eyelid landmark (EYELID_PAIRS), in pixels, over pairs detected in full.
    The landmark term barely sees a blink (a few landmarks move a few pixels); this term
    measures the eye opening itself. ``projected``/``detected``: (B, 478, 2) pixels."""
    opening = projected[:, EYELID_UPPER] - projected[:, EYELID_LOWER]
    target = detected[:, EYELID_UPPER] - detected[:, EYELID_LOWER]
    ok = torch.isfinite(target).all(-1)
    diff = (opening - torch.nan_to_num(target)).abs().sum(-1)
    return (diff * ok).sum() / ok.sum().clamp(min=1)


def normal_abs_term(normals: torch.Tensor, gt_normals: torch.Tensor, covered: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """L1 between the rendered and the ground-truth camera-space normals themselves (B, H, W, 3),
    summed over the channels, mean over the pixels of ``area`` (B, H, W) bool that both maps cover
    (``covered`` (B, H, W) bool: the render's). Beyond NHA and PointAvatar: unlike NHA's E_normal
    on image-space Laplacians it is not zero on a smooth surface of the wrong orientation."""
    valid = covered & (gt_normals.norm(dim=-1) > 0.5) & area
    diff = (normals - gt_normals).abs().sum(-1)
    return (diff * valid).sum() / valid.sum().clamp(min=1)


def point_normal_term(pixels: torch.Tensor, normals: torch.Tensor, visible: torch.Tensor, gt_normals: torch.Tensor,
                      area: torch.Tensor) -> torch.Tensor:
    """L1 between each visible point's own camera-space unit normal and the ground-truth normal at
    the pixel it projects to, summed over the channels, mean over the points that count: visible
    (``visible`` (B, N) bool) and on a pixel of ``area`` (B, H, W) bool that the GT covers.
    ``pixels`` (B, N, 2) projected positions (centres at integers), ``normals`` (B, N, 3),
    ``gt_normals`` (B, H, W, 3). Beyond PointAvatar: a per-pixel term on composited normals
    (:func:`normal_abs_term`) lets the normals of the points a pixel blends scatter about the
    right mean; this one asks it of every point the images show."""
    B, H, W, _ = gt_normals.shape
    x = pixels[..., 0].round().long().clamp(0, W - 1)
    y = pixels[..., 1].round().long().clamp(0, H - 1)
    b = torch.arange(B, device=pixels.device)[:, None]
    target = gt_normals[b, y, x]  # (B, N, 3)
    inside = (pixels[..., 0] >= -0.5) & (pixels[..., 0] < W - 0.5) & (pixels[..., 1] >= -0.5) & (pixels[..., 1] < H - 0.5)
    valid = visible & inside & area[b, y, x] & (target.norm(dim=-1) > 0.5)
    diff = (normals - target).abs().sum(-1)
    return (diff * valid).sum() / valid.sum().clamp(min=1)
