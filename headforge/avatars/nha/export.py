"""Export a trained NHA: baked UV texture, neutral mesh and per-frame meshes (OBJ/PLY via
trimesh), the animatable glTF (GLB: skin, 52 expression morph targets, animation; written by
:mod:`headforge.export.gltf`), and videos for reenactment (driving expressions/poses from another
dataset) and novel views (orbit)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.pose import flip_matrix
from headforge.render import mesh
from headforge.render.camera import Cameras

FORMATS = ("obj", "ply", "glb")


@torch.no_grad()
def bake_texture(avatar, size: int = 512) -> np.ndarray:
    """(size, size, 3) float texture: T evaluated at every texel's surface point (static
    texture, zero mouth condition; the normal head sees the neutral head's normal as seen by a
    frontal camera, as a flat patch); texels outside the UV islands are dilated from inside."""
    from headforge.head.pose import FRAME_KEYS
    from headforge.head.topology import vertex_normals
    from headforge.render.shading import sh_shading
    import cv2

    faces_uv = avatar.uv_corners  # (F, 3, 2)
    F = len(faces_uv)
    verts = torch.cat([faces_uv[..., 0:1] * size - 0.5, (1 - faces_uv[..., 1:2]) * size - 0.5,
                       torch.ones(F, 3, 1)], -1).reshape(1, F * 3, 3)
    tri = torch.arange(F * 3).reshape(F, 3)
    cams = Cameras(torch.eye(3)[None], torch.eye(3)[None], torch.zeros(1, 3), size, size)
    frags = mesh.rasterize(cams, verts, tri)
    hit = frags.face_id[0] >= 0
    fid = frags.face_id[0][hit]
    b = frags.bary[0][hit]
    faces = avatar.head.faces
    canon = (avatar.positions[faces[fid]] * b[..., None]).sum(1)
    uv = (faces_uv[fid] * b[..., None]).sum(1)
    neutral = {k: torch.zeros_like(avatar.frames[k][:1]) for k in FRAME_KEYS}
    vn = vertex_normals(avatar.pose(neutral)[0][0], faces)  # camera space, frontal
    normal = torch.nn.functional.normalize((vn[faces[fid]] * b[..., None]).sum(1), dim=-1)
    inner = avatar.inner_mouth_faces[fid]
    net = avatar.texture_net
    colour = torch.cat([net(c, u, torch.zeros(len(c), net.cond_dim), torch.zeros(len(c), dtype=torch.bool),
                            net.encode_uniform_normals(n), m)
                        for c, u, n, m in zip(canon.split(65536), uv.split(65536), normal.split(65536),
                                              inner.split(65536))])
    if avatar.sh is not None:  # a shading avatar: bake the albedo as lit in the training frames
        colour = colour * sh_shading(normal, avatar.sh).clamp(min=0)
    image = np.zeros((size, size, 3), np.float32)
    image[hit.numpy()] = colour.numpy()
    # dilate into the gutters so bilinear lookups at island borders stay clean
    filled = hit.numpy().astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(8):
        grown, grown_mask = cv2.dilate(image, kernel), cv2.dilate(filled, kernel)
        new = (grown_mask > 0) & (filled == 0)
        image[new] = grown[new]
        filled = grown_mask
    return image


def split_seams(faces: np.ndarray, uv_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """UV seams: one output vertex per (vertex, uv) corner pair. faces, uv_faces (F, 3) ->
    vertex ids (N,), uv ids (N,) of the output vertices and the output faces (F, 3)."""
    pairs = np.stack([faces.ravel(), uv_faces.ravel()], 1)
    uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uniq[:, 1], inverse.reshape(-1, 3)


def _trimesh(vertices: np.ndarray, avatar, texture: np.ndarray | None):
    import trimesh
    from PIL import Image

    faces = avatar.head.faces.numpy()
    if texture is None:
        return trimesh.Trimesh(vertices, faces, process=False)
    vertex_ids, uv_ids, new_faces = split_seams(faces, avatar.head.uv_faces.numpy())
    uniq = np.stack([vertex_ids, uv_ids], 1)
    uvs = avatar.head.uvs.numpy()[uv_ids]
    image = Image.fromarray((np.clip(texture, 0, 1) * 255).round().astype(np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uvs, image=image)
    return trimesh.Trimesh(vertices[uniq[:, 0]], new_faces, visual=visual, process=False)


@torch.no_grad()
def write_animated_glb(avatar, path: Path, texture: np.ndarray, clip=None) -> Path:
    """The animatable glTF of ``avatar``: the neutral mesh with its identity and static offsets
    (NHA's neck-pose dependent offsets at zero neck pose), split at UV seams; the head model's
    skin (root, neck, jaw, eyes) at the avatar's rest joints; one morph target per expression
    (named as the head model names them); the baked ``texture`` (H, W, 3 in [0, 1]) as an unlit
    base colour; and, with a ``clip`` (:class:`headforge.avatars.base.Clip`: frame parameters with
    the avatar's raw poses, fps, camera), an animation: joint rotations (the poses the skinning
    sees), the expressions as morph weights and the head's translation (camera -> glTF world,
    :func:`gltf.camera_to_gltf`), and the clip's camera."""
    import io

    from PIL import Image

    from headforge.export import gltf
    from headforge.head.model import POSE_ARGS
    from headforge.head.topology import vertex_normals

    head = avatar.head
    out = head(shape=avatar.shape, offsets=avatar.offsets(torch.zeros(1, 3))[:1])
    rest, joints = out.vertices[0], out.joints[0]  # zero pose: the rest pose
    vertex_ids, uv_ids, faces = split_seams(head.faces.numpy(), head.uv_faces.numpy())
    normals = vertex_normals(rest[None], head.faces)[0].numpy()
    exprdirs = head.blenddirs[head.n_shape:].reshape(head.n_expr, -1, 3).numpy()
    png = io.BytesIO()
    Image.fromarray((np.clip(texture, 0, 1) * 255).round().astype(np.uint8)).save(png, format="PNG")
    skin = gltf.Skin(list(head.joint_names), head.parents.numpy(), joints.numpy(), head.weights.numpy()[vertex_ids])
    animation = camera = None
    if clip is not None:
        seq = {k: v.detach().cpu() for k, v in clip.sequence.items()}
        poses = head.effective_poses({k: seq[k] for k in POSE_ARGS})
        animation = gltf.Animation(clip.fps, torch.stack([poses[k] for k in POSE_ARGS], 1).numpy(),
                                   gltf.camera_to_gltf(seq["translation"].numpy()), seq["expression"].numpy())
        camera = gltf.Camera(clip.K.numpy(), clip.resolution, clip.resolution)
    names = head.expression_names or [f"expression_{i}" for i in range(head.n_expr)]
    return gltf.write_glb(path, rest.numpy()[vertex_ids], faces, normals=normals[vertex_ids],
                          uvs=head.uvs.numpy()[uv_ids], texture_png=png.getvalue(), unlit=True, skin=skin,
                          morph_targets=exprdirs[:, vertex_ids], target_names=list(names), animation=animation,
                          camera=camera, extras={"method": "nha", "head_model": head.name})


@torch.no_grad()
def export_run(avatar, output: Path, fmt: str = "obj", frames: list[int] | None = None, texture_size: int = 512,
               clip=None) -> list[Path]:
    """Write ``avatar.<fmt>`` (neutral: zero expression and pose, canonical axes, metres) with its
    baked texture, and ``frames/<index>.<fmt>`` for the given tracked frames (canonical head axes,
    posed). GLB: ``avatar.glb`` is the animatable glTF (:func:`write_animated_glb`), animated by
    ``clip`` when given."""
    if fmt not in FORMATS:
        raise HeadforgeError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    output.mkdir(parents=True, exist_ok=True)
    texture = bake_texture(avatar, texture_size)
    written = []
    offsets = avatar.offsets(torch.zeros(1, 3))
    neutral = avatar.head(shape=avatar.shape, offsets=offsets).vertices[0].numpy()
    if fmt == "glb":
        written.append(write_animated_glb(avatar, output / "avatar.glb", texture, clip))

    def save(vertices: np.ndarray, path: Path) -> None:
        m = _trimesh(vertices, avatar, texture if fmt != "ply" else None)
        if fmt == "ply":  # vertex colours from the texture at each vertex's first UV
            from headforge.render.mesh import texture as sample

            uv = torch.zeros(avatar.head.num_vertices, 2)
            uv[avatar.head.faces.reshape(-1)] = avatar.uv_corners.reshape(-1, 2)
            rgb = sample(uv[None, None], torch.from_numpy(texture)[None])[0, 0].numpy()
            m.visual.vertex_colors = np.concatenate([rgb, np.ones((len(rgb), 1))], 1) * 255
        tmp = path.with_name(path.stem + ".tmp" + path.suffix)
        m.export(tmp)
        tmp.replace(path)
        written.append(path)

    if fmt != "glb":
        save(neutral, output / f"avatar.{fmt}")
    if frames:
        (output / "frames").mkdir(exist_ok=True)
        T = avatar.frames["translation"].shape[0]
        bad = [f for f in frames if not 0 <= f < T]
        if bad:
            raise HeadforgeError(f"frame {bad[0]} is outside the run's {T} frames")
        for f in frames:
            params = avatar.frame_params(torch.tensor([f]))
            params = {**params, "translation": torch.zeros_like(params["translation"])}
            verts, _, _ = avatar.pose(params)
            save(verts[0].numpy() @ flip_matrix(), output / "frames" / f"{f:05d}.{fmt}")  # camera -> head axes
    from headforge.render.io import write_png

    write_png(output / "texture.png", texture)
    return written


@torch.no_grad()
def render_frames(avatar, K: torch.Tensor, resolution: int, params_seq: dict[str, torch.Tensor], orbit: bool = False,
                  orbit_degrees: float = 30.0):
    """Yield (R, R, 3) frames for a sequence of frame parameters (reenactment), optionally with
    the camera orbiting the head (novel views)."""
    from scipy.spatial.transform import Rotation

    T = params_seq["translation"].shape[0]
    for t in range(T):
        params = {k: v[t:t + 1] for k, v in params_seq.items()}
        if orbit:
            yaw = orbit_degrees * math.sin(2 * math.pi * t / max(T, 1))
            R = torch.tensor(Rotation.from_euler("y", yaw, degrees=True).as_matrix(), dtype=torch.float32)
            params["root_pose"] = torch.tensor(
                (Rotation.from_matrix(R.numpy()) * Rotation.from_rotvec(params["root_pose"][0].numpy())).as_rotvec(),
                dtype=torch.float32)[None]
        cams = Cameras.at_origin(K, 1, resolution)
        yield avatar.render(params, cams, background=1.0).rgb[0].clamp(0, 1).numpy()
