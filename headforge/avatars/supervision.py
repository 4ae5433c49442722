"""Energies on a synthetic subject's ground-truth maps (``--supervision gt``) that every avatar
method can use, whatever its representation: they compare rendered maps with the maps of
:class:`headforge.avatars.frames.FrameData`, not the geometry that produced them."""

from __future__ import annotations

import torch


def normal_abs_term(normals: torch.Tensor, gt_normals: torch.Tensor, covered: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """L1 between the rendered and the ground-truth camera-space normals themselves (B, H, W, 3),
    summed over the channels, mean over the pixels of ``area`` (B, H, W) bool that both maps cover
    (``covered`` (B, H, W) bool: the render's). Beyond NHA and PointAvatar: unlike NHA's E_normal
    on image-space Laplacians it is not zero on a smooth surface of the wrong orientation."""
    valid = covered & (gt_normals.norm(dim=-1) > 0.5) & area
    diff = (normals - gt_normals).abs().sum(-1)
    return (diff * valid).sum() / valid.sum().clamp(min=1)
