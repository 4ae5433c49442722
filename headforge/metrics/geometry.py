"""Geometry metrics: NHA Table 1 (per-pixel normal angle error, one-sided Hausdorff from
prediction to ground truth on the full head and the face), normal consistency (PointAvatar),
Chamfer distance. Lengths in the meshes' units (metres in headforge; reported in mm)."""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from headforge.errors import HeadforgeError


def normal_angle_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean angle in degrees between normal maps (B, H, W, 3) over ``mask`` (B, H, W) -> (B,).
    Normals need not be unit length (they are normalised); NHA's per-pixel protocol."""
    if pred.shape != gt.shape or pred.shape[-1] != 3 or mask.shape != pred.shape[:3]:
        raise HeadforgeError(f"normal maps (B, H, W, 3) and mask (B, H, W) must agree, got {tuple(pred.shape)}, "
                             f"{tuple(gt.shape)}, {tuple(mask.shape)}")
    m = mask.bool()
    if not m.flatten(1).any(1).all():
        raise HeadforgeError("a mask is empty: no pixels to evaluate")
    cos = (torch.nn.functional.normalize(pred, dim=-1) * torch.nn.functional.normalize(gt, dim=-1)).sum(-1)
    angle = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
    return (angle * m).flatten(1).sum(1) / m.flatten(1).sum(1)


def _mesh(vertices, faces) -> trimesh.Trimesh:
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(faces) == 0:
        raise HeadforgeError("a mesh has no faces")
    return trimesh.Trimesh(vertices, faces, process=False)


def points_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Exact distance from each point (N, 3) to the surface of the mesh."""
    mesh = _mesh(vertices, faces)
    _, distance, _ = trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))
    return distance


def one_sided_hausdorff(pred_vertices, pred_faces, gt_vertices, gt_faces, samples: int = 20000,
                        seed: int = 0, region_mask: np.ndarray | None = None) -> dict:
    """Distances from the predicted surface (area-uniform samples; or only the faces selected by
    ``region_mask`` (F_pred,) bool, e.g. the face region) to the ground-truth surface.

    Returns {"mean": NHA's "average mesh alignment error", "max": the classical one-sided
    Hausdorff distance, "median"}.
    """
    pred = _mesh(pred_vertices, pred_faces)
    if region_mask is not None:
        pred = trimesh.Trimesh(pred.vertices, pred.faces[np.asarray(region_mask, bool)], process=False)
        if len(pred.faces) == 0:
            raise HeadforgeError("the region selects no faces of the prediction")
    pts, _ = trimesh.sample.sample_surface(pred, samples, seed=seed)
    d = points_to_mesh(pts, gt_vertices, gt_faces)
    return {"mean": float(d.mean()), "max": float(d.max()), "median": float(np.median(d))}


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """PointFlow's Chamfer distance: mean squared NN distance a->b plus b->a."""
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return float((da ** 2).mean() + (db ** 2).mean())


def directed_normal_consistency(points_a, normals_a, points_b, normals_b) -> float:
    """Mean |n_a . n_b| of each point of ``points_a`` (P, 3) and its nearest neighbour in
    ``points_b`` (Q, 3); the normals (P, 3) / (Q, 3) need not be unit."""
    na = normals_a / np.linalg.norm(normals_a, axis=1, keepdims=True)
    nb = normals_b / np.linalg.norm(normals_b, axis=1, keepdims=True)
    _, nearest = cKDTree(points_b).query(points_a)
    return float(np.abs((na * nb[nearest]).sum(1)).mean())


def normal_consistency(points_a, normals_a, points_b, normals_b) -> float:
    """Mean |n_a . n_b| between each point and its nearest neighbour in the other set, both
    directions averaged (Occupancy Networks / PointAvatar)."""
    return 0.5 * (directed_normal_consistency(points_a, normals_a, points_b, normals_b)
                  + directed_normal_consistency(points_b, normals_b, points_a, normals_a))
