"""HeadCraft displacement maps (A.1, A.2): bake, store as uint16 PNG, seam post-process, apply.

- :class:`DenseUV` -- the HeadCraft layout (:func:`headforge.head.uv.craft_layout`) carried
  through the same consistent subdivision as the geometry (per face corner, so seams stay exact).
- :func:`bake` -- per-vertex displacements (Vd, 3) rendered into UV space with headforge's
  rasterizer (the mesh path, with screen = UV texels and constant depth), plus a coverage mask.
- :func:`encode` / :func:`decode` -- clip to [-20, 20] paper units (+-167 mm; see
  :mod:`headforge.craft.register`) and renormalise linearly to [0, 65535]: one step is 5.1 um.
- :func:`postprocess_seams` -- A.2: copy values across the face/scalp seam (and every other
  chart seam), blend within 10 texels by distance transform, fill empty texels from the nearest
  valid texel (a Voronoi fill of the empty space).
- :func:`lookup` / :func:`apply_map` -- bilinear per-corner UV lookup, averaged per vertex,
  added to any identity/expression of the head model after consistent subdivision and
  HeadCraft's per-region Laplacian smoothing.

Map images: (H, W, 3), row 0 is v = 1 (image convention), channel order x, y, z (canonical axes).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError

CLIP_UNITS = 20.0
PAPER_UNITS_PER_M = 120.0
CLIP_M = CLIP_UNITS / PAPER_UNITS_PER_M
BLEND_TEXELS = 10


@dataclass
class DenseUV:
    uvs: np.ndarray  # (Td, 2)
    uv_faces: np.ndarray  # (Fd, 3), aligned with the dense geometry faces
    uv_vertex: np.ndarray  # (Td,) dense geometry vertex of each dense uv
    island: np.ndarray  # (Fd,) 0 scalp side, 1 face


def dense_uv(layout, subdivision_levels: int, geometry_faces: np.ndarray, dense_faces: np.ndarray) -> DenseUV:
    """Subdivide the layout's UV topology like the geometry (same child order, so dense uv faces
    line up with dense geometry faces)."""
    from headforge.head.topology import ConsistentSubdivision

    sub = ConsistentSubdivision(layout.uv_faces, len(layout.uvs), subdivision_levels).bind(layout.uv_faces)
    uvs = sub.apply(torch.as_tensor(layout.uvs)).numpy()
    uv_faces = sub.faces
    if uv_faces.shape != dense_faces.shape:
        raise HeadforgeError("UV and geometry subdivisions disagree")
    uv_vertex = np.zeros(len(uvs), np.int64)
    uv_vertex[uv_faces.ravel()] = dense_faces.ravel()
    island = np.repeat(layout.island, 4 ** subdivision_levels)
    return DenseUV(uvs, uv_faces, uv_vertex, island)


def _texel_xyz(uvs: np.ndarray, size: int) -> np.ndarray:
    """UV -> rasterizer screen space (pixel centres at integers, y down, depth 1)."""
    x = uvs[:, 0] * size - 0.5
    y = (1.0 - uvs[:, 1]) * size - 0.5
    return np.stack([x, y, np.ones(len(uvs))], 1)


def bake(values: np.ndarray | torch.Tensor, duv: DenseUV, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex values (Vd, C) -> (size, size, C) map and (size, size) bool coverage."""
    from headforge.render.kernels import rasterize_numba

    values = np.asarray(values.detach().cpu() if isinstance(values, torch.Tensor) else values, np.float64)
    face_id, bary, _ = rasterize_numba(_texel_xyz(duv.uvs, size)[None], duv.uv_faces, size, size)
    face_id, bary = face_id[0], bary[0]
    mask = face_id >= 0
    corner_vals = values[duv.uv_vertex[duv.uv_faces[np.maximum(face_id, 0)]]]  # (H, W, 3, C)
    out = (corner_vals * bary[..., None]).sum(-2)
    out[~mask] = 0.0
    return out, mask


def encode(displacement_map: np.ndarray) -> np.ndarray:
    """Metres -> uint16, linear over [-CLIP_M, CLIP_M] (values beyond are clipped)."""
    x = np.clip(np.asarray(displacement_map, np.float64), -CLIP_M, CLIP_M)
    return np.round((x + CLIP_M) / (2 * CLIP_M) * 65535).astype(np.uint16)


def decode(image: np.ndarray) -> np.ndarray:
    if image.dtype != np.uint16:
        raise HeadforgeError(f"a displacement map must be uint16, got {image.dtype}")
    return image.astype(np.float64) / 65535 * (2 * CLIP_M) - CLIP_M


QUANTUM_M = 2 * CLIP_M / 65535


def write_map(path: Path, displacement_map: np.ndarray, mask: np.ndarray | None = None) -> None:
    """``path`` (RGB uint16 PNG) and, with ``mask``, ``<stem>_mask.png`` (uint8 0/255); atomic."""
    import cv2

    img = encode(displacement_map)
    tmp = path.with_name(path.stem + ".partial.png")
    if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise HeadforgeError(f"cannot write {path}")
    if mask is not None:
        mtmp = path.with_name(path.stem + "_mask.partial.png")
        cv2.imwrite(str(mtmp), mask.astype(np.uint8) * 255)
        mtmp.replace(path.with_name(path.stem + "_mask.png"))
    tmp.replace(path)


def read_map(path: str | Path, size: int | None = None) -> np.ndarray:
    """(H, W, 3) displacement map in metres from a uint16 RGB PNG; checks size and dtype."""
    import cv2

    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise HeadforgeError(f"cannot read displacement map {path}")
    if img.ndim != 3 or img.shape[2] != 3:
        raise HeadforgeError(f"{path.name}: a displacement map must have 3 channels, got shape {img.shape}")
    if img.dtype != np.uint16:
        raise HeadforgeError(f"{path.name}: a displacement map must be a uint16 PNG, got {img.dtype}")
    if img.shape[0] != img.shape[1] or (size is not None and img.shape[0] != size):
        raise HeadforgeError(f"{path.name}: map is {img.shape[1]}x{img.shape[0]}, expected {size or 'square'}")
    return decode(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))


# ---------------------------------------------------------------- seams (A.2)
def texel_islands(duv: DenseUV, size: int) -> np.ndarray:
    """(size, size) island of each covered texel (0 scalp, 1 face, 2 inner parts), -1 empty."""
    from headforge.render.kernels import rasterize_numba

    face_id = rasterize_numba(_texel_xyz(duv.uvs, size)[None], duv.uv_faces, size, size)[0][0]
    return np.where(face_id >= 0, duv.island[np.maximum(face_id, 0)], -1)


def seam_pairs(duv: DenseUV, size: int, islands: tuple[int, ...] = (0, 1)) -> tuple[np.ndarray, np.ndarray]:
    """Texel pairs (K, 2, 2) (row, col) of the same geometry vertex on the two sides of a seam
    between charts of ``islands`` (default the face/scalp seam), and the seam texel mask."""
    on = np.zeros(len(duv.uvs), bool)
    for isl in islands:
        on[duv.uv_faces[duv.island == isl].ravel()] = True
    ids_all = np.nonzero(on)[0]
    order = ids_all[np.argsort(duv.uv_vertex[ids_all], kind="stable")]
    verts = duv.uv_vertex[order]
    starts = np.r_[0, np.nonzero(np.diff(verts))[0] + 1] if len(verts) else np.zeros(0, np.int64)
    counts = np.diff(np.r_[starts, len(verts)])
    pix = np.clip(np.round(_texel_xyz(duv.uvs, size)[:, [1, 0]]).astype(np.int64), 0, size - 1)
    pairs = []
    for s, c in zip(starts[counts > 1], counts[counts > 1]):
        ids = order[s:s + c]
        for k in range(1, c):
            pairs.append((pix[ids[0]], pix[ids[k]]))
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2, 2)
    seam = np.zeros((size, size), bool)
    if len(pairs):
        seam[pairs[:, :, 0].ravel(), pairs[:, :, 1].ravel()] = True
    return pairs, seam


def postprocess_seams(displacement_map: np.ndarray, mask: np.ndarray, duv: DenseUV, blend: int = BLEND_TEXELS) -> np.ndarray:
    """A.2's post-processing (see the module doc); ``blend=0`` only equalises and fills.
    Returns a new map with every texel filled.

    The blend is a smoothing meant for generated maps (part 2), whose two seam sides need not
    agree; on a registered map it only adds error (the two sides already agree), so
    :func:`headforge.craft.pipeline.register_item` stores maps with ``blend=0``."""
    from scipy.ndimage import distance_transform_edt

    size = displacement_map.shape[0]
    out = _voronoi_fill(displacement_map, mask)  # seam texels may lie just outside the coverage
    pairs, seam = seam_pairs(duv, size)
    if len(pairs):
        # 1. equalise the two sides of the seam: texels linked through seam vertices (a texel
        # may hold several) form groups, each set to its mean
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        flat = pairs[..., 0] * size + pairs[..., 1]  # (K, 2)
        nodes, inv = np.unique(flat, return_inverse=True)
        inv = inv.reshape(-1, 2)
        graph = sp.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
        _, group = connected_components(graph, directed=False)
        vals = out.reshape(-1, out.shape[-1])[nodes]
        sums = np.zeros((group.max() + 1, vals.shape[1]))
        np.add.at(sums, group, vals)
        mean = sums / np.bincount(group)[:, None]
        out.reshape(-1, out.shape[-1])[nodes] = mean[group]
        if blend > 0:
            # 2. blend towards the nearest seam texel within ``blend`` texels, in face and scalp
            islands = texel_islands(duv, size)
            dist, (ni, nj) = distance_transform_edt(~seam, return_indices=True)
            near = mask & (dist < blend) & ~seam & (islands >= 0) & (islands < 2)
            w = (dist[near] / blend)[:, None]
            out[near] = (1 - w) * out[ni[near], nj[near]] + w * out[near]
    # 3. Voronoi fill: every empty texel takes the value of the nearest covered (or seam) texel
    return _voronoi_fill(out, mask | seam)


def _voronoi_fill(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    from scipy.ndimage import distance_transform_edt

    out = values.copy()
    _, (fi, fj) = distance_transform_edt(~valid, return_indices=True)
    empty = ~valid
    out[empty] = out[fi[empty], fj[empty]]
    return out


# ---------------------------------------------------------------- lookup and apply
def lookup(displacement_map: np.ndarray | torch.Tensor, duv: DenseUV, n_vertices: int) -> torch.Tensor:
    """(Vd, C) per-vertex values: bilinear samples at every face corner's UV, averaged per vertex."""
    m = torch.as_tensor(np.asarray(displacement_map), dtype=torch.float64)
    size = m.shape[0]
    grid = torch.as_tensor(duv.uvs, dtype=torch.float64)
    # grid_sample: x = 2u - 1, y = 1 - 2v (row 0 is v = 1), align_corners=False matches texel centres
    g = torch.stack([2 * grid[:, 0] - 1, 1 - 2 * grid[:, 1]], 1)[None, None]
    img = m.permute(2, 0, 1)[None]
    samples = torch.nn.functional.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=False)
    per_uv = samples[0, :, 0].T  # (Td, C)
    total = torch.zeros(n_vertices, per_uv.shape[1], dtype=torch.float64).index_add_(0, torch.as_tensor(duv.uv_vertex), per_uv)
    count = torch.zeros(n_vertices, dtype=torch.float64).index_add_(0, torch.as_tensor(duv.uv_vertex), torch.ones(len(per_uv), dtype=torch.float64))
    if (count == 0).any():
        raise HeadforgeError("some dense vertices have no UV coordinate")
    del size
    return total / count[:, None]


def apply_map(template, displacement_map: np.ndarray, duv: DenseUV, params: dict | None = None,
              smooth_iterations: dict | None = None) -> torch.Tensor:
    """(Vd, 3) dense mesh of ``params`` (any identity/expression; zeros by default) with the map's
    displacements: subdivision + per-region smoothing + per-corner lookup."""
    from headforge.craft.register import RegisterConfig, dense_base

    if smooth_iterations is None:
        smooth_iterations = RegisterConfig().smooth_iterations
    base = dense_base(template, params or {}, smooth_iterations)
    return base + lookup(displacement_map, duv, template.n_vertices)


def map_preview(displacement_map: np.ndarray, mask: np.ndarray | None = None, range_m: float = 0.02) -> np.ndarray:
    """(H, W, 3) uint8 picture of a map: 0.5 + d / (2 range), empty texels grey."""
    img = np.clip(0.5 + displacement_map / (2 * range_m), 0, 1)
    if mask is not None:
        img = np.where(mask[..., None], img, 0.25)
    return (img * 255).astype(np.uint8)
