"""Differentiable point splatting (PyTorch3D-style) for point avatars.

Each point is a screen-space disc of radius r pixels (per point or global). Per pixel the K
nearest points in depth whose disc covers the pixel centre are found by a numba kernel on the CPU
or the same search vectorised in PyTorch on CUDA (not differentiable); then in torch,
alpha_i = 1 - d_i^2 / r_i^2 and front-to-back compositing
C = sum_i alpha_i T_i c_i, M = sum_i alpha_i T_i with T_i = prod_{j<i} (1 - alpha_j), which is
differentiable w.r.t. positions, features and radii.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from headforge.render.camera import Cameras
from headforge.render.kernels import splat_numba, splat_torch


@dataclass
class PointFragments:
    """idx: (B, H, W, K) long, point ids front to back, -1 = empty; depth: (B, H, W, K)."""

    idx: torch.Tensor
    depth: torch.Tensor


@dataclass
class PointImage:
    """features: (B, H, W, C) composited features; mask: (B, H, W) accumulated alpha;
    max_weight: (B, N) each point's largest compositing weight (PointAvatar prunes points
    whose weight never exceeds 0.5); fragments: the visibility used."""

    features: torch.Tensor
    mask: torch.Tensor
    max_weight: torch.Tensor
    fragments: PointFragments


def _radius(radius: torch.Tensor | float, B: int, N: int, like: torch.Tensor) -> torch.Tensor:
    r = torch.as_tensor(radius, dtype=like.dtype, device=like.device)
    if r.ndim == 0:
        return r.expand(B, N)
    if r.shape == (N,):
        return r[None].expand(B, N)
    if r.shape != (B, N):
        raise ValueError(f"radius must be a scalar, (N,) or (B, N); got {tuple(r.shape)}")
    return r


def splat(cameras: Cameras, points: torch.Tensor, features: torch.Tensor, radius: torch.Tensor | float,
          K: int = 8, background: torch.Tensor | None = None, near: float = 1e-3,
          backend: str = "auto") -> PointImage:
    """Render points (B, N, 3, world) with features (B, N, C) as discs of ``radius`` pixels.

    Points behind ``near`` or with NaN coordinates are ignored. ``background`` (C,) or
    (B, H, W, C) is composited behind (weight 1 - mask). ``backend`` picks the visibility search:
    "numba" (the CPU kernel), "torch" (the same search vectorised in PyTorch, run on the points'
    device) or "auto": numba for CPU tensors, torch for any other device, so a CUDA run never
    copies points to the host. Both give identical fragments (tests/test_render.py).
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be (B, N, 3), got {tuple(points.shape)}")
    B, N = points.shape[:2]
    if features.shape[:2] != (B, N):
        raise ValueError(f"features must be (B, {N}, C), got {tuple(features.shape)}")
    if points.shape[0] != cameras.batch_size:
        raise ValueError(f"{B} point clouds but {cameras.batch_size} cameras")
    if K < 1:
        raise ValueError(f"K must be >= 1, got {K}")
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"backend must be auto, numba or torch, got {backend!r}")
    H, W = cameras.height, cameras.width
    xyz = cameras.project_finite(points)  # NaN points: invisible (the kernel skips z <= near)
    r = _radius(radius, B, N, xyz)
    if backend == "torch" or (backend == "auto" and points.device.type != "cpu"):
        idx, frag_depth = splat_torch(xyz.detach(), r.detach(), H, W, K, near)
    else:
        idx_np, depth_np = splat_numba(xyz.detach().double().cpu().numpy(), r.detach().double().cpu().numpy(), H, W, K, near)
        idx, frag_depth = torch.from_numpy(idx_np).to(points.device), torch.from_numpy(depth_np).to(points.device)
    valid = idx >= 0
    safe = idx.clamp(min=0).reshape(B, -1)
    gather = lambda t: torch.gather(t, 1, safe[..., None].expand(-1, -1, t.shape[-1])).reshape(B, H, W, K, t.shape[-1])  # noqa: E731
    ys, xs = torch.meshgrid(torch.arange(H, device=points.device), torch.arange(W, device=points.device), indexing="ij")
    pix = torch.stack([xs, ys], -1).to(xyz.dtype)[None, :, :, None, :]
    d2 = ((gather(xyz[..., :2]) - pix) ** 2).sum(-1)
    r2 = gather(r[..., None])[..., 0] ** 2
    alpha = torch.where(valid, (1 - d2 / r2.clamp(min=1e-12)).clamp(0, 1), torch.zeros_like(d2))
    transmit = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha[..., :-1]], -1), -1)
    weight = alpha * transmit  # (B, H, W, K)
    out = (weight[..., None] * gather(features)).sum(-2)
    mask = weight.sum(-1)
    if background is not None:
        out = out + (1 - mask[..., None]) * background.to(out.dtype)
    max_weight = torch.zeros(B, N, dtype=weight.dtype, device=weight.device)
    max_weight = max_weight.scatter_reduce(1, safe, torch.where(valid, weight, torch.zeros_like(weight)).reshape(B, -1).detach(), reduce="amax")
    return PointImage(out, mask, max_weight, PointFragments(idx, frag_depth.to(xyz.dtype)))
