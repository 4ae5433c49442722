"""Turntable renders of a head model: the mesh path (SH-shaded, antialiased) next to the point
path (surface points coloured by their normal), camera orbiting the head."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import torch

from headforge.head.model import HeadModel
from headforge.geometry import vertex_normals
from headforge.render import mesh, points, shading
from headforge.render.camera import Cameras, look_at_head

SKIN = (0.82, 0.64, 0.55)
BACKGROUND = (0.93, 0.93, 0.95)


def _sh_light() -> torch.Tensor:
    """A soft key light from the upper front-left plus ambient, as (9, 3) SH coefficients."""
    coeffs = shading.constant_sh(0.7)
    coeffs[1:4] = torch.tensor([0.25, 0.35, -0.2])[:, None]  # y, z, x bands: up, front, left
    return coeffs


def surface_samples(faces: torch.Tensor, vertices: torch.Tensor, n: int, seed: int = 0):
    """(face id, barycentric) of ``n`` area-uniform samples on the rest mesh (B=1)."""
    gen = torch.Generator().manual_seed(seed)
    tri = vertices[0][faces]
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    face_ids = torch.multinomial(area / area.sum(), n, replacement=True, generator=gen)
    u, v = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
    flip = u + v > 1
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    return face_ids, torch.stack([1 - u - v, u, v], -1)


def turntable_frames(head: HeadModel, n_frames: int = 60, resolution: int = 256, n_points: int = 100_000,
                     K: int = 8) -> Iterator[np.ndarray]:
    """Yield (resolution, 2 * resolution, 3) float frames: mesh | points."""
    faces = head.faces
    with torch.no_grad():
        rest = head().vertices
    face_ids, bary = surface_samples(faces, rest, n_points)
    jaw_id = head.expression_names.index("jawOpen") if "jawOpen" in head.expression_names else None
    light = _sh_light()
    background = torch.tensor(BACKGROUND)
    for i in range(n_frames):
        phase = 2 * math.pi * i / n_frames
        expr = torch.zeros(1, head.n_expr)
        if jaw_id is not None:
            expr[0, jaw_id] = 0.25 * (1 - math.cos(2 * phase))
        with torch.no_grad():
            verts = head(expression=expr, jaw_pose=torch.tensor([[0.08 * (1 - math.cos(2 * phase)), 0.0, 0.0]])).vertices
            cams = Cameras.from_pinhole([look_at_head(resolution, resolution, distance=0.62, yaw_deg=math.degrees(phase),
                                                      pitch_deg=8.0, target=(0.0, -0.02, 0.0))])
            normals = vertex_normals(verts, faces)
            frags = mesh.rasterize(cams, verts, faces)
            n_img = torch.nn.functional.normalize(mesh.interpolate(normals, frags, faces), dim=-1)
            rgb = torch.tensor(SKIN) * shading.sh_shading(n_img, light)
            rgb = torch.where(frags.mask[..., None], rgb, background)
            left = mesh.antialias(rgb, frags, cams, verts, faces)[0]
            corners = verts[0][faces[face_ids]]  # (N, 3, 3)
            pts = (bary[..., None] * corners).sum(1)[None]
            pn = torch.nn.functional.normalize((bary[..., None] * normals[0][faces[face_ids]]).sum(1), dim=-1)[None]
            # Back-face culling: points facing away would show through gaps between discs.
            centre = torch.as_tensor(cams.pinhole().centre, dtype=pts.dtype)
            front = ((centre - pts[0]) * pn[0]).sum(-1) > 0
            # Display: normalise by the accumulated alpha so random-sampling gaps don't speckle.
            splat = points.splat(cams, pts[:, front], 0.5 * (pn[:, front] + 1), radius=1.6 * resolution / 256, K=K)
            mask = splat.mask[0, ..., None]
            right = torch.where(mask > 0.05, splat.features[0] / mask.clamp(min=1e-6), background)
        yield torch.cat([left, right], dim=1).clamp(0, 1).numpy()


def write_turntable(head: HeadModel, output, n_frames: int = 60, resolution: int = 256, n_points: int = 100_000,
                    fps: float = 30.0):
    """Write the turntable as an MP4 at ``output`` and its first frame as a PNG beside it;
    returns the PNG's path."""
    from headforge.render.io import write_mp4, write_png

    first = {}

    def frames():
        for frame in turntable_frames(head, n_frames, resolution, n_points):
            first.setdefault("frame", frame)
            yield frame

    write_mp4(output, frames(), fps=fps, total=n_frames, description=f"rendering {n_frames} frames")
    return write_png(output.with_suffix(".png"), first["frame"])
