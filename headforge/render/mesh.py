"""Differentiable mesh rendering, split like nvdiffrast:

1. :func:`rasterize` -- visibility (not differentiable): per pixel triangle id, barycentrics,
   depth, returned as :class:`Fragments`, the only interface between the stages;
2. :func:`barycentrics` -- the same barycentrics recomputed in torch from the projected
   vertices, so gradients reach vertex positions; :func:`interpolate` any per-vertex or
   per-face-corner attribute with them;
3. :func:`texture` -- bilinear sampling of UV maps / feature grids;
4. :func:`antialias` -- analytic coverage at silhouette edges, which gives colour and mask
   losses gradients with respect to vertex positions.

Images are (B, H, W, C). Screen space: pixel centres at integers, x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from headforge.render.camera import Cameras
from headforge.render.kernels import rasterize_numba, rasterize_torch


@dataclass
class Fragments:
    """Visibility of a batch of meshes (no gradients).

    face_id: (B, H, W) long, -1 on background; bary: (B, H, W, 3) perspective-correct
    barycentrics; depth: (B, H, W) camera depth in metres, inf on background.
    """

    face_id: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        return self.face_id >= 0


def _check_mesh(vertices: torch.Tensor, faces: torch.Tensor, cameras: Cameras) -> None:
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must be (B, V, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if vertices.shape[0] != cameras.batch_size:
        raise ValueError(f"{vertices.shape[0]} meshes but {cameras.batch_size} cameras")
    if faces.numel() and (faces.min() < 0 or faces.max() >= vertices.shape[1]):
        raise ValueError("faces index outside the vertices")


def rasterize(cameras: Cameras, vertices: torch.Tensor, faces: torch.Tensor, near: float = 1e-3,
              backend: str = "auto") -> Fragments:
    """Visibility of ``vertices`` (B, V, 3, world) with ``faces`` (F, 3) from ``cameras``.

    Triangles with a vertex closer than ``near`` metres, NaN vertices, and degenerate triangles
    are skipped (no clipping). ``backend``: "numba" (the CPU kernel), "torch" (the same z-buffer
    vectorised in PyTorch, run on the vertices' device) or "auto": numba for CPU tensors, torch
    for any other device, so a CUDA run never copies meshes to the host. Both give identical
    fragments (tests/test_render.py).
    """
    _check_mesh(vertices, faces, cameras)
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"backend must be auto, numba or torch, got {backend!r}")
    with torch.no_grad():
        xyz = cameras.project(vertices.detach())
    device, dtype = vertices.device, vertices.dtype
    if backend == "torch" or (backend == "auto" and device.type != "cpu"):
        face_id, bary, depth = rasterize_torch(xyz, faces, cameras.height, cameras.width, near)
        return Fragments(face_id, bary.to(dtype), depth.to(dtype))
    face_id, bary, depth = rasterize_numba(xyz.double().cpu().numpy(), faces.cpu().numpy(),
                                           cameras.height, cameras.width, near)
    return Fragments(torch.from_numpy(face_id).to(device), torch.from_numpy(bary).to(device, dtype),
                     torch.from_numpy(depth).to(device, dtype))


def _edge(a: torch.Tensor, b: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """2D edge function (twice the signed area of a, b, p), (..., 2) inputs."""
    return (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])


def _pixel_grid(fragments: Fragments) -> torch.Tensor:
    B, H, W = fragments.face_id.shape
    ys, xs = torch.meshgrid(torch.arange(H, device=fragments.depth.device), torch.arange(W, device=fragments.depth.device), indexing="ij")
    return torch.stack([xs, ys], -1).to(fragments.depth.dtype)  # (H, W, 2)


def barycentrics(fragments: Fragments, cameras: Cameras, vertices: torch.Tensor, faces: torch.Tensor,
                 pixels: torch.Tensor | None = None) -> torch.Tensor:
    """Perspective-correct barycentrics (B, H, W, 3), differentiable w.r.t. ``vertices``.

    Equal to ``fragments.bary`` in value; zero on the background. With ``pixels`` (B, H, W) bool
    (covered pixels only), just those pixels' barycentrics, (N, 3) in ``pixels.nonzero()`` order:
    the backward pass then costs N pixels instead of the whole image.
    """
    xyz = cameras.project_finite(vertices)  # (B, V, 3)
    if pixels is not None:
        b, y, x = pixels.nonzero(as_tuple=True)
        corner = faces[fragments.face_id[b, y, x]]  # (N, 3)
        return _perspective_barycentrics(xyz[b[:, None], corner], torch.stack([x, y], -1).to(xyz.dtype))
    B, H, W = fragments.face_id.shape
    fid = fragments.face_id.clamp(min=0)
    corner = faces[fid]  # (B, H, W, 3)
    pts = torch.gather(xyz, 1, corner.reshape(B, -1, 1).expand(-1, -1, 3).reshape(B, -1, 3)).reshape(B, H, W, 3, 3)
    bary = _perspective_barycentrics(pts, _pixel_grid(fragments).to(xyz.dtype).expand(B, H, W, 2))
    return torch.where(fragments.mask[..., None], bary, torch.zeros_like(bary))


def _perspective_barycentrics(pts: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """(..., 3) perspective-correct barycentrics of pixel positions ``p`` (..., 2) in the
    triangles ``pts`` (..., 3 corners, 3) of projected (x, y pixels, z depth) corners."""
    v0, v1, v2 = pts[..., 0, :2], pts[..., 1, :2], pts[..., 2, :2]
    area = _edge(v0, v1, v2)
    safe_area = torch.where(area.abs() > 1e-12, area, torch.ones_like(area))
    l0 = _edge(v1, v2, p) / safe_area
    l1 = _edge(v2, v0, p) / safe_area
    l2 = 1 - l0 - l1
    z = pts[..., 2].clamp(min=1e-9)
    q = torch.stack([l0, l1, l2], -1) / z
    return q / q.sum(-1, keepdim=True).where(q.sum(-1, keepdim=True).abs() > 1e-12, torch.ones_like(q[..., :1]))


def interpolate(attributes: torch.Tensor, fragments: Fragments, faces: torch.Tensor,
                bary: torch.Tensor | None = None, per_corner: bool = False) -> torch.Tensor:
    """Interpolate attributes at every covered pixel -> (B, H, W, C), zero on the background.

    Args:
        attributes: per vertex (V, C) or (B, V, C); with ``per_corner=True``, per face corner
            (F, 3, C) or (B, F, 3, C) (UVs with seams, per-corner features).
        bary: (B, H, W, 3) barycentrics; pass :func:`barycentrics` for gradients w.r.t. vertex
            positions, or leave None to use the rasterizer's (gradients to attributes only).
    """
    B, H, W = fragments.face_id.shape
    bary = fragments.bary if bary is None else bary
    fid = fragments.face_id.clamp(min=0)
    if per_corner:
        corners = attributes.expand(B, -1, -1, -1) if attributes.ndim == 3 else attributes  # (B, F, 3, C)
        C = corners.shape[-1]
        vals = torch.gather(corners, 1, fid.reshape(B, -1, 1, 1).expand(-1, -1, 3, C)).reshape(B, H, W, 3, C)
    else:
        per_vertex = attributes.expand(B, -1, -1) if attributes.ndim == 2 else attributes  # (B, V, C)
        C = per_vertex.shape[-1]
        idx = faces[fid].reshape(B, -1)
        vals = torch.gather(per_vertex, 1, idx[..., None].expand(-1, -1, C)).reshape(B, H, W, 3, C)
    out = (bary[..., None].to(vals.dtype) * vals).sum(-2)
    return torch.where(fragments.mask[..., None], out, torch.zeros_like(out))


def texture(uv: torch.Tensor, texture_map: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear lookup of ``texture_map`` (B or 1, Ht, Wt, C) at ``uv`` (B, H, W, 2) in [0, 1],
    v up (OpenGL/FLAME UV convention). Returns (B, H, W, C); zero where ``mask`` is False."""
    B = uv.shape[0]
    tex = texture_map.permute(0, 3, 1, 2).expand(B, -1, -1, -1)
    grid = torch.stack([2 * uv[..., 0] - 1, 1 - 2 * uv[..., 1]], -1).to(tex.dtype)
    out = F.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=False).permute(0, 2, 3, 1)
    return out if mask is None else torch.where(mask[..., None], out, torch.zeros_like(out))


def antialias(image: torch.Tensor, fragments: Fragments, cameras: Cameras, vertices: torch.Tensor,
              faces: torch.Tensor) -> torch.Tensor:
    """Blend colours across silhouette edges by the analytic edge position (nvdiffrast-style).

    For every pair of neighbouring pixels where one is covered by triangle T and the other is
    background, the segment between the pixel centres crosses an edge of T at t in [0, 1]
    (from the foreground centre). If t > 1/2 the background pixel is covered by t - 1/2 of the
    foreground colour; otherwise the foreground pixel gives up 1/2 - t to the background. t is a
    differentiable function of T's projected vertices, so a mask or colour loss moves the
    silhouette. Occlusion edges between two triangles are not antialiased.

    Args:
        image: (B, H, W, C) shaded image (include the mask as a channel to antialias it too).
    """
    B, H, W, C = image.shape
    xyz = cameras.project_finite(vertices)
    grid = _pixel_grid(fragments)
    delta = torch.zeros_like(image)
    fid = fragments.face_id
    for dy, dx in ((0, 1), (1, 0)):
        a_f, b_f = fid[:, : H - dy, : W - dx], fid[:, dy:, dx:]
        edge = (a_f >= 0) != (b_f >= 0)
        if not edge.any():
            continue
        bi, yi, xi = torch.nonzero(edge, as_tuple=True)
        fg_is_a = a_f[bi, yi, xi] >= 0
        fy = torch.where(fg_is_a, yi, yi + dy)
        fx = torch.where(fg_is_a, xi, xi + dx)
        gy = torch.where(fg_is_a, yi + dy, yi)
        gx = torch.where(fg_is_a, xi + dx, xi)
        tri = fid[bi, fy, fx]
        pts = xyz[bi[:, None], faces[tri], :2]  # (M, 3, 2)
        p_fg, p_bg = grid[fy, fx], grid[gy, gx]
        area = _edge(pts[:, 0], pts[:, 1], pts[:, 2])
        sign = torch.sign(area).detach()[:, None]
        e_fg = torch.stack([_edge(pts[:, i], pts[:, (i + 1) % 3], p_fg) for i in range(3)], -1) * sign
        e_bg = torch.stack([_edge(pts[:, i], pts[:, (i + 1) % 3], p_bg) for i in range(3)], -1) * sign
        # The crossed edge: the one most negative at the background centre.
        k = torch.argmin((e_bg / (e_fg - e_bg).abs().clamp(min=1e-12)).detach(), dim=-1, keepdim=True)
        ef, eb = e_fg.gather(-1, k)[:, 0], e_bg.gather(-1, k)[:, 0]
        t = (ef / (ef - eb).where((ef - eb).abs() > 1e-12, torch.ones_like(ef))).clamp(0, 1)
        c_fg, c_bg = image[bi, fy, fx], image[bi, gy, gx]
        to_bg = (t - 0.5).clamp(min=0)[:, None]
        to_fg = (0.5 - t).clamp(min=0)[:, None]
        delta = delta.index_put((bi, gy, gx), to_bg * (c_fg - c_bg), accumulate=True)
        delta = delta.index_put((bi, fy, fx), to_fg * (c_bg - c_fg), accumulate=True)
    return image + delta
