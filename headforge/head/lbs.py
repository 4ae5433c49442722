"""Linear blend skinning as pure functions (FLAME / SMPL-X formulation).

Shapes use B = batch, V = vertices, J = joints, K = blendshape coefficients,
L = landmarks. Positions are in metres, in the canonical head space (y up, face toward +z).
"""

from __future__ import annotations

from collections.abc import Sequence

import roma
import torch


def blend_shapes(coeffs: torch.Tensor, dirs: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
    """Linear blendshapes: ``base + coeffs @ dirs``.

    Args:
        coeffs: (B, K) coefficients.
        dirs: (K, N*3) directions, each row flattened point-major (p0x, p0y, p0z, p1x, ...).
        base: optional (N, 3) points the offsets are added to (fused into one addmm).
    Returns:
        (B, N, 3).
    """
    if base is None:
        return (coeffs @ dirs).reshape(coeffs.shape[0], -1, 3)
    return torch.addmm(base.reshape(1, -1), coeffs, dirs).reshape(coeffs.shape[0], -1, 3)


def pose_to_rotmats(pose: torch.Tensor) -> torch.Tensor:
    """Axis-angle (B, J, 3) -> rotation matrices (B, J, 3, 3). Differentiable at zero."""
    return roma.rotvec_to_rotmat(pose)


def limit_joint_rotations(pose: torch.Tensor, half_range: torch.Tensor) -> torch.Tensor:
    """Soft joint limits with tanh (NHA App. A.1): theta = r * tanh(theta_raw / r).

    Args:
        pose: (B, J, 3) raw axis-angle per joint.
        half_range: (J, 3) positive limits in radians; ``inf`` leaves an axis free.
    Returns:
        (B, J, 3) limited axis-angles; zero maps to zero and small angles are unchanged.
    """
    finite = torch.isfinite(half_range)
    safe = torch.where(finite, half_range, torch.ones_like(half_range))
    limited = safe * torch.tanh(pose / safe)
    return torch.where(finite, limited, pose)


def unlimit_joint_rotations(pose: torch.Tensor, half_range: torch.Tensor, margin: float = 1e-3) -> torch.Tensor:
    """Inverse of :func:`limit_joint_rotations`: the raw axis-angles (B, J, 3) whose limited
    values are ``pose`` (angles at or beyond a limit map to ``1 - margin`` of it)."""
    finite = torch.isfinite(half_range)
    safe = torch.where(finite, half_range, torch.ones_like(half_range))
    raw = safe * torch.atanh((pose / safe).clamp(-1 + margin, 1 - margin))
    return torch.where(finite, raw, pose)


def rigid_transforms(
    rotmats: torch.Tensor, joints: torch.Tensor, parents: Sequence[int] | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics.

    Args:
        rotmats: (B, J, 3, 3) local joint rotations.
        joints: (B, J, 3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root; parents precede children.
            Python ints are best: the tree is static, and torch.compile sees no tensor reads.
    Returns:
        posed_joints (B, J, 3) and the relative transforms (B, J, 4, 4) that map rest-pose
        points to posed points (the skinning matrices).
    """
    B, J = joints.shape[:2]
    parents = [int(p) for p in parents]
    rel_joints = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, parents[1:]]], dim=1)
    local = torch.zeros(B, J, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rotmats
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    chain = [local[:, 0]]
    for j in range(1, J):
        chain.append(chain[parents[j]] @ local[:, j])
    world = torch.stack(chain, dim=1)
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint location so the transform acts on rest-pose vertices.
    offset = torch.einsum("bjik,bjk->bji", world[..., :3, :3], joints)
    skinning = world.clone()
    skinning[..., :3, 3] = world[..., :3, 3] - offset
    return posed_joints, skinning


def skin_vertices(
    vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor
) -> torch.Tensor:
    """Apply blended rigid transforms.

    Args:
        vertices: (B, V, 3) rest-pose vertices (after blendshapes and pose correctives).
        weights: (V, J) skinning weights, rows sum to one.
        transforms: (B, J, 4, 4) skinning matrices from :func:`rigid_transforms`.
    Returns:
        (B, V, 3) posed vertices.
    """
    B, J = transforms.shape[:2]
    # Blend the 3x4 matrices column by column: (B, V, 12) = [c0 | c1 | c2 | t], so the
    # product with (x, y, z, 1) is three broadcast multiply-adds on contiguous slices.
    columns = transforms[..., :3, :].transpose(-1, -2).reshape(B, J, 12)
    blended = weights @ columns
    x, y, z = vertices[..., 0:1], vertices[..., 1:2], vertices[..., 2:3]
    return blended[..., 0:3] * x + blended[..., 3:6] * y + blended[..., 6:9] * z + blended[..., 9:12]


def regress_joints(j_regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """(J, V) regressor, (B, V, 3) vertices -> (B, J, 3) joints."""
    return torch.einsum("jv,bvc->bjc", j_regressor, vertices)


def lbs(
    shaped: torch.Tensor,
    pose: torch.Tensor,
    joints: torch.Tensor,
    parents: Sequence[int] | torch.Tensor,
    weights: torch.Tensor,
    posedirs: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Skin shaped vertices with per-joint axis-angle rotations.

    Args:
        shaped: (B, V, 3) template + identity + expression offsets.
        pose: (B, J, 3) axis-angle rotations, joint order as ``parents``.
        joints: (B, J, 3) rest joint locations of ``shaped`` (see :func:`regress_joints`).
        parents: (J,) kinematic tree.
        weights: (V, J) skinning weights.
        posedirs: optional (9*(J-1), V*3) pose-corrective directions (FLAME/SMPL layout,
            driven by the flattened ``R - I`` of every non-root joint).
    Returns:
        vertices (B, V, 3) and joints (B, J, 3), both posed.
    """
    rotmats = pose_to_rotmats(pose)
    if posedirs is not None:
        eye = torch.eye(3, dtype=shaped.dtype, device=shaped.device)
        pose_feature = (rotmats[:, 1:] - eye).reshape(shaped.shape[0], -1)
        shaped = shaped + (pose_feature @ posedirs).reshape(shaped.shape)
    posed_joints, transforms = rigid_transforms(rotmats, joints, parents)
    return skin_vertices(shaped, weights, transforms), posed_joints


def surface_points(
    vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor
) -> torch.Tensor:
    """Points given as (face, barycentric) on a batch of meshes.

    Args:
        vertices: (B, V, 3); faces: (F, 3) long; face_ids: (L,) long; bary: (L, 3).
    Returns:
        (B, L, 3).
    """
    corners = vertices.index_select(1, faces[face_ids].reshape(-1)).view(vertices.shape[0], -1, 3, 3)
    return (bary.to(vertices.dtype)[None, :, None, :] @ corners).squeeze(2)  # (1,3) @ (3,3) per point
