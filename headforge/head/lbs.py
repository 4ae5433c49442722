"""Linear blend skinning as pure functions (FLAME / SMPL-X formulation).

Shapes use B = batch, V = vertices, J = joints, K = blendshape coefficients,
L = landmarks. Positions are in metres, in the canonical head space (y up, face toward +z).
"""

from __future__ import annotations

import roma
import torch


def blend_shapes(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Linear blendshape offsets.

    Args:
        coeffs: (B, K) coefficients.
        dirs: (V*3, K) blendshape directions, flattened vertex-major (v0x, v0y, v0z, v1x, ...).
    Returns:
        (B, V, 3) offsets.
    """
    return (coeffs @ dirs.T).reshape(coeffs.shape[0], -1, 3)


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


def rigid_transforms(
    rotmats: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics.

    Args:
        rotmats: (B, J, 3, 3) local joint rotations.
        joints: (B, J, 3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root; parents precede children.
    Returns:
        posed_joints (B, J, 3) and the relative transforms (B, J, 4, 4) that map rest-pose
        points to posed points (the skinning matrices).
    """
    B, J = joints.shape[:2]
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, parents[1:]]
    local = torch.zeros(B, J, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rotmats
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    chain = [local[:, 0]]
    for j in range(1, J):
        chain.append(chain[int(parents[j])] @ local[:, j])
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
    blended = (weights @ transforms[..., :3, :].reshape(B, J, 12)).reshape(B, -1, 3, 4)
    return torch.einsum("bvij,bvj->bvi", blended[..., :3], vertices) + blended[..., 3]


def lbs(
    shaped: torch.Tensor,
    pose: torch.Tensor,
    j_regressor: torch.Tensor,
    parents: torch.Tensor,
    weights: torch.Tensor,
    posedirs: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Skin shaped vertices with per-joint axis-angle rotations.

    Args:
        shaped: (B, V, 3) template + identity + expression offsets.
        pose: (B, J, 3) axis-angle rotations, joint order as ``parents``.
        j_regressor: (J, V) joint regressor.
        parents: (J,) kinematic tree.
        weights: (V, J) skinning weights.
        posedirs: optional (9*(J-1), V*3) pose-corrective directions (FLAME/SMPL layout,
            driven by the flattened ``R - I`` of every non-root joint).
    Returns:
        vertices (B, V, 3) and joints (B, J, 3), both posed.
    """
    joints = torch.einsum("jv,bvc->bjc", j_regressor, shaped)
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
    corners = vertices[:, faces[face_ids]]  # (B, L, 3, 3)
    return (corners * bary[None, :, :, None]).sum(dim=2)
