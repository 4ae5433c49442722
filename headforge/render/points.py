"""Differentiable point splatting (PyTorch3D-style) for point avatars.

Each point is a screen-space disc of radius r pixels (per point or global) or, given its normal,
its tangent disc seen in perspective (a surfel): the ellipse whose axis along the projected normal
is shortened by |cos| of the normal and the view ray. Per pixel the K nearest points in depth
whose footprint covers the pixel centre are found by a numba kernel on the CPU or the same search
vectorised in PyTorch on CUDA (not differentiable); then in torch, alpha_i = 1 - d_i^2 / r_i^2
(d_i the pixel's footprint distance: its offset, stretched along the projected normal by
1 / |cos| for a surfel) and front-to-back compositing
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
    max_weight: (B, N) each point's largest compositing weight; front: (B, N) bool, the point is
    the nearest on at least one pixel (PyTorch3D's first fragment; PointAvatar keeps the points
    that are either, and prunes the rest); fragments: the visibility used."""

    features: torch.Tensor
    mask: torch.Tensor
    max_weight: torch.Tensor
    fragments: PointFragments
    front: torch.Tensor


def _radius(radius: torch.Tensor | float, B: int, N: int, like: torch.Tensor) -> torch.Tensor:
    r = torch.as_tensor(radius, dtype=like.dtype, device=like.device)
    if r.ndim == 0:
        return r.expand(B, N)
    if r.shape == (N,):
        return r[None].expand(B, N)
    if r.shape != (B, N):
        raise ValueError(f"radius must be a scalar, (N,) or (B, N); got {tuple(r.shape)}")
    return r


def surfel_squash(cameras: Cameras, points: torch.Tensor, normals: torch.Tensor, min_cos: float) -> torch.Tensor:
    """(B, N, 3) elliptical footprints (ux, uy, s) of the tangent discs of ``points`` (B, N, 3,
    world) with unit ``normals`` (B, N, 3, world): u the unit image direction of the normal at the
    point, s = 1 / c^2 - 1 with c = |cos(normal, view ray)| clamped to [min_cos, 1], so a disc seen
    edge-on keeps min_cos of its width across the silhouette (the kernels' ``squash``)."""
    cam = cameras.world_to_camera(points)
    n = normals @ cameras.R.transpose(1, 2).to(normals.dtype)
    cos = (torch.nn.functional.normalize(cam, dim=-1) * torch.nn.functional.normalize(n, dim=-1)).sum(-1)
    c = cos.abs().clamp(min=min_cos, max=1.0)
    fx, fy = cameras.K[:, 0, 0, None].to(points.dtype), cameras.K[:, 1, 1, None].to(points.dtype)
    x, y, z = cam.unbind(-1)
    # d/dt of the projection of points + t * normals (up to the common 1 / z^2)
    g = torch.stack([fx * (n[..., 0] * z - n[..., 2] * x), fy * (n[..., 1] * z - n[..., 2] * y)], -1)
    length = g.norm(dim=-1, keepdim=True)
    u = torch.where(length > 1e-12, g / length.clamp(min=1e-12), torch.tensor([1.0, 0.0], dtype=g.dtype, device=g.device))
    return torch.cat([u, (1 / c ** 2 - 1)[..., None]], -1)


def splat(cameras: Cameras, points: torch.Tensor, features: torch.Tensor, radius: torch.Tensor | float,
          K: int = 8, background: torch.Tensor | None = None, near: float = 1e-3,
          backend: str = "auto", normals: torch.Tensor | None = None, min_cos: float = 0.3) -> PointImage:
    """Render points (B, N, 3, world) with features (B, N, C) as discs of ``radius`` pixels.

    ``normals`` (B, N, 3, world) draws each point as its tangent disc instead (a surfel: an
    ellipse, :func:`surfel_squash`, ``min_cos`` its least width across the silhouette), so the
    outline of a curved surface falls at the points on it rather than a radius beyond them;
    the footprint is differentiable w.r.t. the normals too.

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
    squash = None
    if normals is not None:
        if normals.shape != points.shape:
            raise ValueError(f"normals must be (B, N, 3) as the points, got {tuple(normals.shape)}")
        if not 0 < min_cos <= 1:
            raise ValueError(f"min_cos must be in (0, 1], got {min_cos}")
        finite = lambda t: torch.where(torch.isfinite(t), t, torch.zeros_like(t))  # noqa: E731  (NaN-free gradients)
        squash = surfel_squash(cameras, finite(points), finite(normals), min_cos)
    if backend == "torch" or (backend == "auto" and points.device.type != "cpu"):
        idx, frag_depth = splat_torch(xyz.detach(), r.detach(), H, W, K, near,
                                      squash=None if squash is None else squash.detach())
    else:
        idx_np, depth_np = splat_numba(xyz.detach().double().cpu().numpy(), r.detach().double().cpu().numpy(), H, W, K, near,
                                       squash=None if squash is None else squash.detach().double().cpu().numpy())
        idx, frag_depth = torch.from_numpy(idx_np).to(points.device), torch.from_numpy(depth_np).to(points.device)
    valid = idx >= 0
    safe = idx.clamp(min=0).reshape(B, -1)
    gather = lambda t: torch.gather(t, 1, safe[..., None].expand(-1, -1, t.shape[-1])).reshape(B, H, W, K, t.shape[-1])  # noqa: E731
    ys, xs = torch.meshgrid(torch.arange(H, device=points.device), torch.arange(W, device=points.device), indexing="ij")
    pix = torch.stack([xs, ys], -1).to(xyz.dtype)[None, :, :, None, :]
    offset = gather(xyz[..., :2]) - pix
    d2 = (offset ** 2).sum(-1)
    if squash is not None:
        sq = gather(squash)
        d2 = d2 + sq[..., 2] * ((offset * sq[..., :2]).sum(-1)) ** 2
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
    first = torch.where(valid[..., 0], idx[..., 0], N).reshape(B, -1)  # N: an empty pixel's slot
    front = torch.zeros(B, N + 1, dtype=torch.bool, device=idx.device).scatter_(1, first, True)[:, :N]
    return PointImage(out, mask, max_weight, PointFragments(idx, frag_depth.to(xyz.dtype)), front)


def close_mask(mask: torch.Tensor) -> torch.Tensor:
    """(B, H, W) the 3x3 morphological closing (dilation, then erosion) of a coverage ``mask``
    (B, H, W) in [0, 1]: holes up to two pixels wide between splatted points are filled, the
    outline of a convex region is kept (PointAvatar's hole filling, supp. 2.3, on the mask)."""
    pool = torch.nn.functional.max_pool2d
    return -pool(-pool(mask[:, None], 3, 1, 1), 3, 1, 1)[:, 0]


def close_holes(values: torch.Tensor, covered: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill the holes of a splatted map: ``values`` (B, H, W, C) meaningful where ``covered``
    (B, H, W) bool. Returns (values, covered) with ``covered`` closed (:func:`close_mask`) and
    each newly covered pixel set to the mean of its covered 3x3 neighbours (every pixel the
    closing adds has one); covered pixels keep their values."""
    cov = covered.to(values.dtype)
    closed = close_mask(cov) > 0.5
    pool = lambda t: torch.nn.functional.avg_pool2d(t, 3, 1, 1, count_include_pad=False)  # noqa: E731
    total = pool((values * cov[..., None]).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
    count = pool(cov[:, None])[:, 0]
    mean = total / count.clamp(min=1e-12)[..., None]
    filled = torch.where((closed & ~covered)[..., None], mean, torch.where(covered[..., None], values, torch.zeros_like(values)))
    return filled, closed
