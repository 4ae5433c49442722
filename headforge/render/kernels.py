"""Fast visibility kernels (numba, multithreaded over image row bands), vectorised PyTorch
versions of them for CUDA tensors (``rasterize_torch``, ``splat_torch``: the same results), and
pure-PyTorch references (every pixel against every primitive, tests only). Visibility is not
differentiable; gradients come from recomputing barycentrics and point alphas in torch from the
ids these kernels return (see mesh.py and points.py).

Screen space: x right, y down in pixels, pixel centres at integer coordinates; z is the
camera depth (metres, > 0 in front of the camera).
"""

from __future__ import annotations

import numba
import numpy as np
import torch

BAND = 8  # rows per parallel work item
SPLAT_KEY_LIMIT = 2 ** 62  # splat_torch sorts one int64 (pixel, depth rank) key below this, else two sorts


@numba.njit(cache=True)
def _bands(ymin, ymax, height):
    """Row bands of the image and the primitives overlapping each (offsets, items)."""
    n_bands = (height + BAND - 1) // BAND
    offsets, items = _bin_rows(ymin, ymax, n_bands, BAND)
    return n_bands, offsets, items


@numba.njit(cache=True)
def _bin_rows(ymin, ymax, n_bands, band):
    """Lists of primitive ids per row band, for primitives covering rows [ymin, ymax]."""
    counts = np.zeros(n_bands + 1, np.int64)
    for i in range(ymin.shape[0]):
        if ymax[i] < ymin[i]:
            continue
        for b in range(ymin[i] // band, ymax[i] // band + 1):
            counts[b + 1] += 1
    offsets = np.cumsum(counts)
    items = np.empty(offsets[-1], np.int64)
    fill = offsets[:-1].copy()
    for i in range(ymin.shape[0]):
        if ymax[i] < ymin[i]:
            continue
        for b in range(ymin[i] // band, ymax[i] // band + 1):
            items[fill[b]] = i
            fill[b] += 1
    return offsets, items


@numba.njit(parallel=True, cache=True)
def _rasterize(xyz, faces, height, width, near, face_out, bary_out, depth_out):
    """Z-buffer rasterization of one image. xyz: (V, 3) screen x, y and depth z."""
    F = faces.shape[0]
    ymin = np.empty(F, np.int64)
    ymax = np.empty(F, np.int64)
    for f in range(F):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        za, zb, zc = xyz[a, 2], xyz[b, 2], xyz[c, 2]
        ok = za > near and zb > near and zc > near
        lo = min(xyz[a, 1], xyz[b, 1], xyz[c, 1])
        hi = max(xyz[a, 1], xyz[b, 1], xyz[c, 1])
        if not ok or not (np.isfinite(lo) and np.isfinite(hi)) or hi < 0 or lo > height - 1:
            ymin[f], ymax[f] = 1, 0  # skipped: behind the near plane, NaN, or off-screen
        else:
            ymin[f] = max(0, int(np.ceil(lo)))
            ymax[f] = min(height - 1, int(np.floor(hi)))
    n_bands, offsets, items = _bands(ymin, ymax, height)
    for band in numba.prange(n_bands):
        r0 = band * BAND
        r1 = min(r0 + BAND, height) - 1
        for k in range(offsets[band], offsets[band + 1]):
            f = items[k]
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            x0, y0, z0 = xyz[a, 0], xyz[a, 1], xyz[a, 2]
            x1, y1, z1 = xyz[b, 0], xyz[b, 1], xyz[b, 2]
            x2, y2, z2 = xyz[c, 0], xyz[c, 1], xyz[c, 2]
            area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
            if area == 0.0 or not np.isfinite(area):
                continue
            xs = max(0, int(np.ceil(min(x0, x1, x2))))
            xe = min(width - 1, int(np.floor(max(x0, x1, x2))))
            ys = max(r0, ymin[f])
            ye = min(r1, ymax[f])
            inv = 1.0 / area
            for py in range(ys, ye + 1):
                for px in range(xs, xe + 1):
                    l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
                    l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
                    l2 = 1.0 - l0 - l1
                    if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                        continue
                    q0, q1, q2 = l0 / z0, l1 / z1, l2 / z2
                    s = q0 + q1 + q2
                    depth = 1.0 / s
                    if depth < depth_out[py, px]:
                        depth_out[py, px] = depth
                        face_out[py, px] = f
                        bary_out[py, px, 0] = q0 / s
                        bary_out[py, px, 1] = q1 / s
                        bary_out[py, px, 2] = q2 / s


def rasterize_numba(xyz: np.ndarray, faces: np.ndarray, height: int, width: int, near: float = 1e-3):
    """Visibility of a batch of meshes.

    Args:
        xyz: (B, V, 3) screen-space vertices (pixel x, pixel y, depth); faces: (F, 3) int.
    Returns:
        face_id (B, H, W) int64 (-1 = background), bary (B, H, W, 3) perspective-correct,
        depth (B, H, W) (inf = background).
    """
    B = xyz.shape[0]
    face_id = np.full((B, height, width), -1, np.int64)
    bary = np.zeros((B, height, width, 3))
    depth = np.full((B, height, width), np.inf)
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    for b in range(B):
        _rasterize(xyz[b], faces, height, width, near, face_id[b], bary[b], depth[b])
    return face_id, bary, depth


def _pair_chunks(xs, xe, ys, ye, todo: torch.Tensor, chunk_pairs: int):
    """The (primitive, pixel) pairs of the pixel boxes [xs, xe] x [ys, ye] of primitives ``todo``,
    cut into runs of about ``chunk_pairs`` pairs: box widths, pair counts and their running sums
    (each (len(todo),)), and the cut points into ``todo`` (a list, first 0, last len(todo))."""
    box_w = (xe - xs + 1)[todo]
    counts = box_w * (ye - ys + 1)[todo]
    ends = torch.cumsum(counts, 0)
    total = int(ends[-1])
    cuts = torch.searchsorted(ends, torch.arange(chunk_pairs, max(total, chunk_pairs), chunk_pairs, device=todo.device),
                              right=True)
    return box_w, counts, ends, [0, *sorted(set(cuts.tolist()) - {0, len(todo)}), len(todo)]


def rasterize_torch(xyz: torch.Tensor, faces: torch.Tensor, height: int, width: int, near: float = 1e-3,
                    chunk_pairs: int = 1 << 22):
    """The numba kernel's z-buffer as vectorised PyTorch on ``xyz``'s device (the CUDA path).

    Every drawable triangle enumerates the pixel centres of its image-clipped bounding box; the
    (triangle, pixel) pairs are tested in chunks of about ``chunk_pairs`` with the numba kernel's
    float64 arithmetic, and per pixel the nearest hit wins, ties to the lowest face id (the numba
    kernel's order). Cost grows with the triangles' bounding-box areas, so it suits the small
    projected triangles of a head mesh; ``rasterize_reference`` tests every pixel instead.

    Args:
        xyz: (B, V, 3) screen-space vertices (pixel x, pixel y, depth); faces: (F, 3) long.
    Returns:
        face_id (B, H, W) int64, bary (B, H, W, 3) float64, depth (B, H, W) float64 on xyz's device.
    """
    B, dev, HW = xyz.shape[0], xyz.device, height * width
    F = faces.shape[0]
    face_id = torch.full((B * HW,), -1, dtype=torch.int64, device=dev)
    depth = torch.full((B * HW,), float("inf"), dtype=torch.float64, device=dev)
    bary = torch.zeros(B * HW, 3, dtype=torch.float64, device=dev)
    if F == 0 or B == 0:
        return face_id.view(B, height, width), bary.view(B, height, width, 3), depth.view(B, height, width)
    faces = faces.to(dev)
    tri = xyz.double()[:, faces].reshape(B * F, 3, 3)  # batch-major: b * F + f
    x, y, z = tri[..., 0], tri[..., 1], tri[..., 2]
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    ok = (z > near).all(-1) & torch.isfinite(area) & (area != 0)
    # bounding boxes of pixel centres, clamped as floats first so huge coordinates cannot overflow
    xs = torch.ceil(x.amin(-1).clamp(-1, width)).long().clamp(min=0)
    xe = torch.floor(x.amax(-1).clamp(-1, width)).long().clamp(max=width - 1)
    ys = torch.ceil(y.amin(-1).clamp(-1, height)).long().clamp(min=0)
    ye = torch.floor(y.amax(-1).clamp(-1, height)).long().clamp(max=height - 1)
    ok &= (xe >= xs) & (ye >= ys)
    todo = torch.nonzero(ok)[:, 0]  # ascending, so chunks visit faces in the kernel's order
    if len(todo) == 0:
        return face_id.view(B, height, width), bary.view(B, height, width, 3), depth.view(B, height, width)
    box_w, counts, ends, bounds = _pair_chunks(xs, xe, ys, ye, todo, chunk_pairs)
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        t = todo[lo:hi]
        n = counts[lo:hi]
        P = int(ends[hi - 1] - (ends[lo - 1] if lo else 0))
        owner = torch.repeat_interleave(torch.arange(hi - lo, device=dev), n, output_size=P)
        local = torch.arange(P, device=dev) - (torch.cumsum(n, 0) - n)[owner]
        w = box_w[lo:hi][owner]
        f = t[owner]
        px = (xs[f] + local % w).double()
        py = (ys[f] + local // w).double()
        x0, x1, x2 = x[f, 0], x[f, 1], x[f, 2]
        y0, y1, y2 = y[f, 0], y[f, 1], y[f, 2]
        inv = 1.0 / area[f]
        l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
        l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
        l2 = 1.0 - l0 - l1
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        f, px, py = f[inside], px[inside].long(), py[inside].long()
        q = torch.stack([l0[inside] / z[f, 0], l1[inside] / z[f, 1], l2[inside] / z[f, 2]], -1)
        s = q.sum(-1)
        d = 1.0 / s
        pixel = torch.div(f, F, rounding_mode="floor") * HW + py * width + px
        # nearest per pixel in this chunk, then the lowest face among equally near ones
        best = torch.full_like(depth, float("inf")).scatter_reduce(0, pixel, d, "amin")
        tie = d == best[pixel]
        first = torch.full_like(face_id, torch.iinfo(torch.int64).max).scatter_reduce(0, pixel[tie], f[tie], "amin")
        win = tie.clone()
        win[tie] = f[tie] == first[pixel[tie]]
        win &= d < depth[pixel]  # strictly nearer than earlier chunks (lower face ids win ties)
        pw = pixel[win]
        depth[pw] = d[win]
        face_id[pw] = f[win] % F
        bary[pw] = q[win] / s[win, None]
    return face_id.view(B, height, width), bary.view(B, height, width, 3), depth.view(B, height, width)


def rasterize_reference(xyz: torch.Tensor, faces: torch.Tensor, height: int, width: int, near: float = 1e-3):
    """Pure-PyTorch z-buffer, every pixel against every triangle (small inputs only)."""
    B = xyz.shape[0]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    p = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # (P, 2)
    out_f = torch.full((B, height * width), -1, dtype=torch.int64)
    out_b = torch.zeros(B, height * width, 3, dtype=torch.float64)
    out_d = torch.full((B, height * width), float("inf"), dtype=torch.float64)
    for b in range(B):
        tri = xyz[b].double()[faces]  # (F, 3, 3)
        v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
        area = (v1[:, 0] - v0[:, 0]) * (v2[:, 1] - v0[:, 1]) - (v2[:, 0] - v0[:, 0]) * (v1[:, 1] - v0[:, 1])
        edge = lambda a, c: (a[None, :, 0] - p[:, None, 0]) * (c[None, :, 1] - p[:, None, 1]) - (c[None, :, 0] - p[:, None, 0]) * (a[None, :, 1] - p[:, None, 1])  # noqa: E731
        l0 = edge(v1, v2) / area
        l1 = edge(v2, v0) / area
        l2 = 1 - l0 - l1
        ok = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (area != 0) & (tri[:, :, 2] > near).all(-1)
        q = torch.stack([l0 / v0[:, 2], l1 / v1[:, 2], l2 / v2[:, 2]], -1)
        depth = torch.where(ok, 1 / q.sum(-1), torch.full_like(l0, float("inf")))
        best_depth, best = depth.min(dim=1)
        hit = torch.isfinite(best_depth)
        out_f[b] = torch.where(hit, best, torch.full_like(best, -1))
        qb = q[torch.arange(len(p)), best]
        out_b[b] = torch.where(hit[:, None], qb / qb.sum(-1, keepdim=True), torch.zeros_like(qb))
        out_d[b] = best_depth
    return (out_f.reshape(B, height, width), out_b.reshape(B, height, width, 3), out_d.reshape(B, height, width))


@numba.njit(parallel=True, cache=True)
def _splat(xyz, radius, squash, height, width, near, idx_out, depth_out):
    """K nearest (in depth) points whose footprint covers each pixel centre, one image: the disc
    (px - x)^2 + (py - y)^2 < r^2, narrowed to an ellipse by ``squash`` (N, 3) = (ux, uy, s):
    (px - x)^2 + (py - y)^2 + s ((px - x) ux + (py - y) uy)^2 < r^2 (s = 0: the disc)."""
    N = xyz.shape[0]
    K = idx_out.shape[2]
    ymin = np.empty(N, np.int64)
    ymax = np.empty(N, np.int64)
    for i in range(N):
        x, y, z, r = xyz[i, 0], xyz[i, 1], xyz[i, 2], radius[i]
        if not (z > near and np.isfinite(x) and np.isfinite(y) and r > 0) or y + r < 0 or y - r > height - 1:
            ymin[i], ymax[i] = 1, 0
        else:
            ymin[i] = max(0, int(np.ceil(y - r)))
            ymax[i] = min(height - 1, int(np.floor(y + r)))
    n_bands, offsets, items = _bands(ymin, ymax, height)
    for band in numba.prange(n_bands):
        r0 = band * BAND
        r1 = min(r0 + BAND, height) - 1
        for k in range(offsets[band], offsets[band + 1]):
            i = items[k]
            x, y, z, r = xyz[i, 0], xyz[i, 1], xyz[i, 2], radius[i]
            ux, uy, s = squash[i, 0], squash[i, 1], squash[i, 2]
            r2 = r * r
            xs = max(0, int(np.ceil(x - r)))
            xe = min(width - 1, int(np.floor(x + r)))
            for py in range(max(r0, ymin[i]), min(r1, ymax[i]) + 1):
                for px in range(xs, xe + 1):
                    d2 = (px - x) * (px - x) + (py - y) * (py - y)
                    if s != 0.0:
                        e = (px - x) * ux + (py - y) * uy
                        d2 = d2 + s * (e * e)
                    if d2 >= r2 or z >= depth_out[py, px, K - 1]:
                        continue
                    j = K - 1  # insertion into the sorted list, nearest first
                    while j > 0 and depth_out[py, px, j - 1] > z:
                        depth_out[py, px, j] = depth_out[py, px, j - 1]
                        idx_out[py, px, j] = idx_out[py, px, j - 1]
                        j -= 1
                    depth_out[py, px, j] = z
                    idx_out[py, px, j] = i


def splat_numba(xyz: np.ndarray, radius: np.ndarray, height: int, width: int, K: int, near: float = 1e-3,
                squash: np.ndarray | None = None):
    """Per pixel, the K nearest points (front to back) whose disc of ``radius`` pixels covers it.

    Args:
        xyz: (B, N, 3) screen-space points; radius: (B, N) pixels; squash: None (discs) or
            (B, N, 3) (ux, uy, s) per point: the footprint is the ellipse
            d^2 + s (d . u)^2 < r^2 around the point (d its pixel offset), its axis along the unit
            image direction u shortened by 1 / sqrt(1 + s) (an oriented disc seen at an angle).
    Returns:
        idx (B, H, W, K) int64 (-1 = empty), depth (B, H, W, K) (inf = empty).
    """
    B = xyz.shape[0]
    idx = np.full((B, height, width, K), -1, np.int64)
    depth = np.full((B, height, width, K), np.inf)
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    radius = np.ascontiguousarray(radius, dtype=np.float64)
    squash = np.zeros(xyz.shape, np.float64) if squash is None else np.ascontiguousarray(squash, dtype=np.float64)
    for b in range(B):
        _splat(xyz[b], radius[b], squash[b], height, width, near, idx[b], depth[b])
    return idx, depth


def splat_torch(xyz: torch.Tensor, radius: torch.Tensor, height: int, width: int, K: int, near: float = 1e-3,
                chunk_pairs: int = 1 << 20, squash: torch.Tensor | None = None):
    """The numba kernel's K-nearest splatting as vectorised PyTorch on ``xyz``'s device (the CUDA path).

    Every drawable point (z > near and finite, finite x and y, radius > 0) enumerates the pixel
    centres of its image-clipped bounding box; the (point, pixel) pairs are tested in chunks of
    about ``chunk_pairs`` with the numba kernel's float64 arithmetic ((px - x)² + (py - y)² < r²).
    The hits of a chunk, together with the lists already held at the pixels it touches, are
    sorted by (pixel, depth, point id) -- one sort of the int64 key pixel * M + the point's rank
    in (depth, id) order, or two stable sorts where that key could overflow -- so equal depths
    keep the lower point id first (the numba kernel's insertion order), and the first K of each
    pixel's run are kept. Memory is bounded by ``chunk_pairs`` plus the (B, H, W, K) output, not by
    the points' total coverage (measured on the CPU: 280 MB peak at the default, 8M pairs in 8
    chunks). ``splat_reference`` tests every pixel against every point instead.

    Args:
        xyz: (B, N, 3) screen-space points (pixel x, pixel y, depth); radius: (B, N) pixels
            (anything broadcastable to it), on any device (moved to xyz's); squash: None or
            (B, N, 3) elliptical footprints, as :func:`splat_numba`'s.
    Returns:
        idx (B, H, W, K) int64 point ids front to back (-1 = empty), depth (B, H, W, K) float64
        (inf = empty), on xyz's device.
    """
    if K < 1:
        raise ValueError(f"K must be >= 1, got {K}")
    B, N, dev, HW = xyz.shape[0], xyz.shape[1], xyz.device, height * width
    idx = torch.full((B * HW, K), -1, dtype=torch.int64, device=dev)
    depth = torch.full((B * HW, K), float("inf"), dtype=torch.float64, device=dev)
    shaped = lambda: (idx.view(B, height, width, K), depth.view(B, height, width, K))  # noqa: E731
    if B == 0 or N == 0 or HW == 0:
        return shaped()
    p = xyz.detach().to(torch.float64).reshape(B * N, 3)  # batch-major: b * N + i
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = torch.broadcast_to(radius.detach().to(dev, torch.float64), (B, N)).reshape(B * N)
    # z < inf: the kernel never inserts an infinite depth (it is not nearer than an empty slot)
    ok = (z > near) & (z < float("inf")) & torch.isfinite(x) & torch.isfinite(y) & (r > 0)
    # bounding boxes of covered pixel centres, clamped as floats first so huge values cannot overflow
    xs = torch.ceil((x - r).clamp(-1, width)).nan_to_num(0).long().clamp(min=0)
    xe = torch.floor((x + r).clamp(-1, width)).nan_to_num(-1).long().clamp(max=width - 1)
    ys = torch.ceil((y - r).clamp(-1, height)).nan_to_num(0).long().clamp(min=0)
    ye = torch.floor((y + r).clamp(-1, height)).nan_to_num(-1).long().clamp(max=height - 1)
    ok &= (xe >= xs) & (ye >= ys)
    todo = torch.nonzero(ok)[:, 0]  # ascending, so chunks visit points in the kernel's order
    if len(todo) == 0:
        return shaped()
    box_w, counts, ends, bounds = _pair_chunks(xs, xe, ys, ye, todo, chunk_pairs)
    # per drawable point, gathered once per pair: box origin and width, image offset; x, y, r², z
    ints = torch.stack([xs[todo], ys[todo], box_w, torch.div(todo, N, rounding_mode="floor") * HW], -1)
    floats = torch.stack([x[todo], y[todo], r[todo] * r[todo], z[todo]], -1)  # r * r: the kernel's r2
    if squash is not None:
        sq = squash.detach().to(dev, torch.float64).reshape(B * N, 3)[todo]
        floats = torch.cat([floats, sq], -1)
    # (pixel, depth, point id) order as one int64 key: pixel * M + the point's rank in (depth, id)
    M = len(todo)
    one_key = (B * HW + 1) * M < SPLAT_KEY_LIMIT
    if one_key:
        by_depth = torch.sort(z[todo], stable=True).indices
        depth_rank = torch.empty(B * N, dtype=torch.int64, device=dev)
        depth_rank[todo[by_depth]] = torch.arange(M, device=dev)
    flat_idx, flat_depth = idx.view(-1), depth.view(-1)
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        n = counts[lo:hi]
        P = int(ends[hi - 1] - (ends[lo - 1] if lo else 0))
        owner = torch.repeat_interleave(torch.arange(lo, hi, device=dev), n, output_size=P)
        first_pair = (ends[lo:hi] - n - (ends[lo - 1] if lo else 0)).index_select(0, owner - lo)
        local = torch.arange(P, device=dev).sub_(first_pair)
        del first_pair
        pi = ints.index_select(0, owner)
        row = torch.div(local, pi[:, 2], rounding_mode="floor")
        px = local.sub_(row * pi[:, 2]).add_(pi[:, 0])
        py = row.add_(pi[:, 1])
        pixel = py * width + px
        pixel += pi[:, 3]
        del pi
        pf = floats.index_select(0, owner)
        dx = px.double().sub_(pf[:, 0])
        dy = py.double().sub_(pf[:, 1])
        del px, py
        if squash is not None:  # e = (px - x) ux + (py - y) uy, before dx, dy are squared in place
            e = dx * pf[:, 4] + dy * pf[:, 5]
        d2 = dx.mul_(dx).add_(dy.mul_(dy))  # (px - x)² + (py - y)², rounded as the kernel does
        del dy
        if squash is not None:
            d2 = torch.where(pf[:, 6] != 0, d2 + pf[:, 6] * (e * e), d2)
            del e
        hit = d2 < pf[:, 2]  # the kernel's two tests: inside the disc, nearer than the K-th
        del d2
        if lo:  # (nothing is held before the first chunk)
            hit &= pf[:, 3] < depth[:, K - 1].contiguous().index_select(0, pixel)
        sel = torch.nonzero(hit)[:, 0]
        del hit
        if len(sel) == 0:
            continue
        pixel, zq = pixel.index_select(0, sel), pf[:, 3].index_select(0, sel)
        del pf
        q = todo.index_select(0, owner.index_select(0, sel))  # batch-major point ids
        if lo:  # merge with the lists held at the touched pixels (earlier points: first among equal depths)
            touched = torch.zeros(B * HW, dtype=torch.bool, device=dev)
            touched[pixel] = True
            held = torch.nonzero((touched[:, None] & (idx >= 0)).view(-1))[:, 0]
            held_pixel = torch.div(held, K, rounding_mode="floor")
            held_q = torch.div(held_pixel, HW, rounding_mode="floor") * N + flat_idx.index_select(0, held)
            pixel = torch.cat([held_pixel, pixel])
            zq = torch.cat([flat_depth.index_select(0, held), zq])
            q = torch.cat([held_q, q])
        if one_key:
            key, order = torch.sort(pixel * M + depth_rank.index_select(0, q))  # keys are unique
            ps = torch.div(key, M, rounding_mode="floor")
        else:  # two stable sorts: by depth, then by pixel (held entries come first among equal depths)
            order = torch.sort(zq, stable=True).indices
            order = order.index_select(0, torch.sort(pixel.index_select(0, order), stable=True).indices)
            ps = pixel.index_select(0, order)
        pos = torch.arange(len(ps), device=dev)
        first = torch.ones_like(ps, dtype=torch.bool)
        first[1:] = ps[1:] != ps[:-1]
        rank = pos - torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
        keep = torch.nonzero(rank < K)[:, 0]
        slot = ps.index_select(0, keep) * K + rank.index_select(0, keep)
        order = order.index_select(0, keep)
        flat_idx[slot] = q.index_select(0, order) % N  # every held entry is a candidate: ranks 0..m-1 replace them
        flat_depth[slot] = zq.index_select(0, order)
    return shaped()


def splat_reference(xyz: torch.Tensor, radius: torch.Tensor, height: int, width: int, K: int, near: float = 1e-3,
                    squash: torch.Tensor | None = None):
    """Pure-PyTorch K-nearest splatting, every pixel against every point (small inputs only);
    ``squash`` as :func:`splat_numba`'s."""
    B = xyz.shape[0]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    p = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    idx_out = torch.full((B, height * width, K), -1, dtype=torch.int64)
    depth_out = torch.full((B, height * width, K), float("inf"), dtype=torch.float64)
    for b in range(B):
        pts = xyz[b].double()
        d = p[:, None, :] - pts[None, :, :2]
        d2 = (d ** 2).sum(-1)
        if squash is not None:
            sq = squash[b].double()
            d2 = d2 + sq[None, :, 2] * ((d * sq[None, :, :2]).sum(-1)) ** 2
        ok = (d2 < radius[b].double()[None] ** 2) & (pts[None, :, 2] > near)
        depth = torch.where(ok, pts[None, :, 2].expand_as(d2), torch.full_like(d2, float("inf")))
        k = min(K, depth.shape[1])
        best_depth, best = torch.topk(depth, k, dim=1, largest=False)
        hit = torch.isfinite(best_depth)
        idx_out[b, :, :k] = torch.where(hit, best, torch.full_like(best, -1))
        depth_out[b, :, :k] = best_depth
    return idx_out.reshape(B, height, width, K), depth_out.reshape(B, height, width, K)
