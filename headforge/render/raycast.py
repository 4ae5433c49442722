"""Reference renderer by ray casting (Embree through trimesh): exact visibility, numpy only.

Not differentiable and not meant for training loops; used to build the landmark embedding,
for pictures a person looks at, and as the independent reference for faster rasterizers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from headforge.render.camera import PinholeCamera


@dataclass
class RayHits:
    """Per-pixel visibility of a mesh. face_id is -1 where no triangle is hit."""

    face_id: np.ndarray  # (H, W) int64
    bary: np.ndarray  # (H, W, 3) float64, zero where not hit
    depth: np.ndarray  # (H, W) float64 distance along the ray (metres), inf where not hit

    @property
    def mask(self) -> np.ndarray:
        return self.face_id >= 0


def intersector(vertices: np.ndarray, faces: np.ndarray):
    """An Embree-backed (or pure-numpy fallback) ray intersector for one mesh."""
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces), process=False)
    return mesh, mesh.ray


def cast(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray, dirs: np.ndarray):
    """First hits of rays: (face_id (N,) with -1 for misses, bary (N, 3), distance (N,))."""
    mesh, ray = intersector(vertices, faces)
    n = len(origins)
    face_id = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 3))
    dist = np.full(n, np.inf)
    tri, ray_idx, loc = ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    if len(tri):
        face_id[ray_idx] = tri
        bary[ray_idx] = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], loc)
        dist[ray_idx] = np.linalg.norm(loc - origins[ray_idx], axis=1)
    return face_id, bary, dist


def raycast(vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera) -> RayHits:
    """Visibility of every pixel centre of ``camera``."""
    origins, dirs = camera.rays()
    face_id, bary, dist = cast(vertices, faces, origins, dirs)
    shape = (camera.height, camera.width)
    return RayHits(face_id.reshape(shape), bary.reshape(shape + (3,)), dist.reshape(shape))


def interpolate(hits: RayHits, faces: np.ndarray, attribute: np.ndarray) -> np.ndarray:
    """Interpolate a per-vertex attribute (V, C) at the hits -> (H, W, C), zero off the mesh."""
    fid = np.where(hits.mask, hits.face_id, 0)
    corners = attribute[faces[fid]]  # (H, W, 3, C)
    out = (corners * hits.bary[..., None]).sum(axis=2)
    return np.where(hits.mask[..., None], out, 0.0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3), numpy in and out."""
    import torch

    from headforge.geometry import vertex_normals as torch_vertex_normals

    return torch_vertex_normals(torch.from_numpy(np.asarray(vertices, np.float64)),
                                torch.from_numpy(np.asarray(faces, np.int64))).numpy()


def shade_lambert(hits: RayHits, faces: np.ndarray, vertices: np.ndarray, albedo: np.ndarray,
                  camera: PinholeCamera, background=(1.0, 1.0, 1.0), ambient: float = 0.45,
                  light_dir=(0.3, 0.4, 1.0)) -> np.ndarray:
    """Image (H, W, 3) in [0, 1]: per-pixel albedo (H, W, 3) times ambient + Lambert light.

    ``light_dir`` points from the surface toward the light, in world space.
    """
    normals = interpolate(hits, faces, vertex_normals(vertices, faces))
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    light = np.asarray(light_dir, np.float64)
    light /= np.linalg.norm(light)
    # Two-sided: back-facing interior faces (mouth, eye sockets) are lit like front faces.
    _, dirs = camera.rays()
    facing = np.sign(-(normals * dirs.reshape(normals.shape)).sum(-1, keepdims=True))
    diffuse = np.clip((normals * facing * light).sum(-1, keepdims=True), 0.0, 1.0)
    image = albedo * (ambient + (1.0 - ambient) * diffuse)
    return np.where(hits.mask[..., None], np.clip(image, 0, 1), np.asarray(background, np.float64))
