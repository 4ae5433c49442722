"""A glTF 2.0 binary (.glb) writer for skinned, morphing, animated head meshes, from numpy arrays.

glTF's axes are the canonical head space's (metres, right-handed, y up, the face toward +z), so
head-space arrays go in unchanged. The node tree::

    scene "avatar"
      node "head"           translation animated (glTF world = the OpenGL camera frame of the
                            clip, see :func:`camera_to_gltf`; zero when not animated)
        node "root" ... the joints, each with its rest offset from its parent and an animated
                        rotation (LBS of :mod:`headforge.head.lbs`: rest joints, axis-angle poses)
      node "mesh"           the mesh, its skin and its morph weights (animated); glTF ignores a
                            skinned node's own transform, the joints place it
      node "camera"         (with ``camera``) an OpenGL camera at the origin looking down -z

Vertex positions are the rest pose (identity and static offsets included); morph targets are
per-vertex offsets (E, V, 3) applied before skinning, exactly as the head model's expression
blendshapes; skinning keeps each vertex's four largest joint weights (renormalised). What glTF
cannot hold: pose correctives and joints that move with the expression (the head model's
``j_blenddirs`` for expressions: the rest joints here are those of the zero expression).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])  # camera axes: OpenCV (y down, z forward) -> OpenGL


@dataclass
class Skin:
    """joint_names (J,), parents (J,) int with -1 for the root and parents before children,
    rest_joints (J, 3) metres in head space, weights (V, J) rows summing to one."""

    joint_names: list[str]
    parents: np.ndarray
    rest_joints: np.ndarray
    weights: np.ndarray


@dataclass
class Animation:
    """fps; rotations (T, J, 3) local axis-angle per joint (radians, the head model's poses);
    translation (T, 3) of the "head" node in glTF world (metres); morph_weights (T, E)."""

    fps: float
    rotations: np.ndarray
    translation: np.ndarray
    morph_weights: np.ndarray | None = None
    name: str = "driving"


@dataclass
class Camera:
    """A pinhole camera: K (3, 3) pixels, width and height in pixels (principal point assumed
    at the centre: glTF's perspective camera has none)."""

    K: np.ndarray
    width: int
    height: int


def camera_to_gltf(translation: np.ndarray) -> np.ndarray:
    """(T, 3) head translations in the OpenCV camera frame (:mod:`headforge.head.pose`) -> the
    "head" node's translations in glTF world, taken as the OpenGL frame of the same camera:
    x_gl = diag(1, -1, -1) x_cv, so a head point x lands at x + diag(1, -1, -1) t."""
    return np.asarray(translation, np.float64) @ OPENGL_FROM_OPENCV


class _Builder:
    """Accumulates buffer views and accessors into one binary chunk."""

    def __init__(self):
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        entry = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        self.blob += data
        self.views.append(entry)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None = None,
                 bounds: bool = False, normalized: bool = False) -> int:
        dtype = {FLOAT: "<f4", UBYTE: "u1", USHORT: "<u2", UINT: "<u4"}[component]
        array = np.ascontiguousarray(array, dtype=dtype)
        count = array.shape[0]
        entry = {"bufferView": self.view(array.tobytes(), target), "componentType": component, "count": count,
                 "type": kind}
        if normalized:
            entry["normalized"] = True
        if bounds:
            flat = array.reshape(count, -1)
            entry["min"] = flat.min(0).astype(float).tolist()
            entry["max"] = flat.max(0).astype(float).tolist()
        self.accessors.append(entry)
        return len(self.accessors) - 1


def _top4(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, J) weights -> joint ids (V, 4) and weights (V, 4) of each vertex's four largest,
    renormalised to sum to one (unused slots: joint 0, weight 0)."""
    V, J = weights.shape
    padded = np.concatenate([weights, np.zeros((V, max(0, 4 - J)))], 1)
    ids = np.argsort(-padded, axis=1)[:, :4]
    w = np.take_along_axis(padded, ids, 1)
    ids = np.where(ids < J, ids, 0)
    w = np.where(w > 0, w, 0)
    total = w.sum(1, keepdims=True)
    if (total <= 0).any():
        raise HeadforgeError("every vertex needs a positive skinning weight")
    return ids, w / total


def _quaternions(rotvecs: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 4) unit quaternions x, y, z, w (glTF's order)."""
    from scipy.spatial.transform import Rotation

    shape = rotvecs.shape[:-1]
    return Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_quat().reshape(*shape, 4)


def write_glb(path: str | Path, positions: np.ndarray, faces: np.ndarray, *, normals: np.ndarray | None = None,
              uvs: np.ndarray | None = None, texture_png: bytes | None = None, unlit: bool = False,
              colour: tuple[float, float, float] = (0.8, 0.8, 0.8), skin: Skin | None = None,
              morph_targets: np.ndarray | None = None, target_names: list[str] | None = None,
              animation: Animation | None = None, camera: Camera | None = None, extras: dict | None = None) -> Path:
    """Write a .glb (atomically) and return its path.

    positions (V, 3) and normals (V, 3) head space, metres; faces (F, 3) int; uvs (V, 2) with
    v up (headforge's layout; flipped to glTF's v down here); texture_png: the PNG of the base
    colour (rows top to bottom = v from 1 to 0); unlit: KHR_materials_unlit (the texture is the
    colour as seen, lighting baked in); morph_targets (E, V, 3) offsets named ``target_names``;
    animation needs ``skin`` (and ``morph_targets`` for its weights); extras: JSON put on the asset.
    """
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces)
    V = len(positions)
    if positions.ndim != 2 or positions.shape[1] != 3 or V == 0:
        raise HeadforgeError(f"positions must be (V, 3) with V > 0, got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and (faces.min() < 0 or faces.max() >= V)):
        raise HeadforgeError("faces must be (F, 3) indices into the positions")
    if texture_png is not None and uvs is None:
        raise HeadforgeError("a texture needs uvs")
    if animation is not None and skin is None:
        raise HeadforgeError("an animation needs a skin")
    b = _Builder()
    attributes = {"POSITION": b.accessor(positions, "VEC3", FLOAT, ARRAY_BUFFER, bounds=True)}
    if normals is not None:
        attributes["NORMAL"] = b.accessor(normals, "VEC3", FLOAT, ARRAY_BUFFER)
    if uvs is not None:
        uv = np.asarray(uvs, np.float64)
        attributes["TEXCOORD_0"] = b.accessor(np.stack([uv[:, 0], 1 - uv[:, 1]], 1), "VEC2", FLOAT, ARRAY_BUFFER)
    index_type = USHORT if V < 65536 else UINT
    primitive = {"attributes": attributes, "mode": 4, "material": 0,
                 "indices": b.accessor(faces.reshape(-1), "SCALAR", index_type, ELEMENT_ARRAY_BUFFER)}
    mesh = {"name": "head", "primitives": [primitive]}
    if morph_targets is not None:
        morph_targets = np.asarray(morph_targets, np.float64)
        if morph_targets.ndim != 3 or morph_targets.shape[1:] != (V, 3):
            raise HeadforgeError(f"morph_targets must be (E, {V}, 3), got {morph_targets.shape}")
        names = list(target_names or [f"target_{i}" for i in range(len(morph_targets))])
        if len(names) != len(morph_targets):
            raise HeadforgeError(f"{len(names)} target names for {len(morph_targets)} morph targets")
        primitive["targets"] = [{"POSITION": b.accessor(d, "VEC3", FLOAT, ARRAY_BUFFER, bounds=True)}
                                for d in morph_targets]
        mesh["weights"] = [0.0] * len(morph_targets)
        mesh["extras"] = {"targetNames": names}
    material = {"name": "avatar", "doubleSided": True,
                "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0}}
    gltf: dict = {"asset": {"version": "2.0", "generator": "headforge"}, "scene": 0, "meshes": [mesh],
                  "materials": [material]}
    if extras:
        gltf["asset"]["extras"] = extras
    if texture_png is not None:
        gltf["images"] = [{"bufferView": b.view(texture_png), "mimeType": "image/png", "name": "texture"}]
        gltf["samplers"] = [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}]
        gltf["textures"] = [{"source": 0, "sampler": 0}]
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
    else:
        material["pbrMetallicRoughness"]["baseColorFactor"] = [*map(float, colour), 1.0]
    if unlit:
        material["extensions"] = {"KHR_materials_unlit": {}}
        gltf["extensionsUsed"] = ["KHR_materials_unlit"]

    nodes: list[dict] = [{"name": "avatar", "children": []}]
    mesh_node = {"name": "mesh", "mesh": 0}
    if skin is not None:
        parents = np.asarray(skin.parents)
        rest = np.asarray(skin.rest_joints, np.float64)
        J = len(parents)
        if skin.weights.shape != (V, J) or rest.shape != (J, 3) or len(skin.joint_names) != J:
            raise HeadforgeError(f"skin: weights must be ({V}, {J}), rest_joints ({J}, 3), {J} joint names")
        if parents[0] != -1 or any(not 0 <= p < i for i, p in enumerate(parents[1:], 1)):
            raise HeadforgeError("skin: parents must be a tree with parents before children")
        nodes.append({"name": "head", "children": []})
        head_node = 1
        nodes[0]["children"].append(head_node)
        first = len(nodes)
        for j in range(J):
            offset = rest[j] - (rest[parents[j]] if parents[j] >= 0 else 0)
            nodes.append({"name": skin.joint_names[j], "translation": offset.tolist()})
            parent = head_node if parents[j] < 0 else first + int(parents[j])
            nodes[parent].setdefault("children", []).append(first + j)
        ids, w = _top4(np.asarray(skin.weights, np.float64))
        attributes["JOINTS_0"] = b.accessor(ids, "VEC4", UBYTE if J < 256 else USHORT, ARRAY_BUFFER)
        attributes["WEIGHTS_0"] = b.accessor(w, "VEC4", FLOAT, ARRAY_BUFFER)
        inverse_bind = np.tile(np.eye(4), (J, 1, 1))
        inverse_bind[:, :3, 3] = -rest  # the rest joints are pure translations in the bind pose
        gltf["skins"] = [{"name": "head", "joints": list(range(first, first + J)), "skeleton": head_node,
                          "inverseBindMatrices": b.accessor(inverse_bind.transpose(0, 2, 1).reshape(J, 16), "MAT4",
                                                            FLOAT)}]
        mesh_node["skin"] = 0
    nodes.append(mesh_node)
    mesh_index = len(nodes) - 1
    nodes[0]["children"].append(mesh_index)
    if camera is not None:
        fy = float(camera.K[1, 1])
        gltf["cameras"] = [{"type": "perspective", "name": "clip", "perspective": {
            "yfov": float(2 * np.arctan(camera.height / (2 * fy))), "aspectRatio": camera.width / camera.height,
            "znear": 0.01, "zfar": 100.0}}]
        nodes.append({"name": "camera", "camera": 0})
        nodes[0]["children"].append(len(nodes) - 1)
    if animation is not None:
        gltf["animations"] = [_animation(b, animation, first, head_node, mesh_index, skin, mesh.get("weights"))]
    gltf["nodes"] = nodes
    gltf["scenes"] = [{"name": "avatar", "nodes": [0]}]
    gltf["accessors"], gltf["bufferViews"] = b.accessors, b.views
    gltf["buffers"] = [{"byteLength": len(b.blob)}]
    return _write(Path(path), gltf, bytes(b.blob))


def _animation(b: _Builder, anim: Animation, first_joint: int, head_node: int, mesh_node: int, skin: Skin,
               default_weights: list[float] | None) -> dict:
    rotations = np.asarray(anim.rotations, np.float64)
    T = rotations.shape[0]
    J = len(skin.parents)
    if T == 0 or rotations.shape != (T, J, 3) or np.shape(anim.translation) != (T, 3):
        raise HeadforgeError(f"animation: rotations must be (T > 0, {J}, 3) and translation (T, 3)")
    if not anim.fps > 0:
        raise HeadforgeError(f"animation: fps must be > 0, got {anim.fps}")
    times = b.accessor(np.arange(T) / anim.fps, "SCALAR", FLOAT, bounds=True)
    samplers, channels = [], []

    def channel(node: int, path: str, values: np.ndarray, kind: str) -> None:
        samplers.append({"input": times, "output": b.accessor(values, kind, FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})

    quats = _quaternions(rotations)
    # keep consecutive quaternions in one hemisphere so linear interpolation takes the short way
    for t in range(1, T):
        flip = (quats[t] * quats[t - 1]).sum(-1) < 0
        quats[t][flip] *= -1
    for j in range(J):
        channel(first_joint + j, "rotation", quats[:, j], "VEC4")
    channel(head_node, "translation", np.asarray(anim.translation), "VEC3")
    if anim.morph_weights is not None:
        weights = np.asarray(anim.morph_weights, np.float64)
        if default_weights is None or weights.shape != (T, len(default_weights)):
            raise HeadforgeError(f"animation: morph_weights must be (T, E) for the mesh's morph targets, got {weights.shape}")
        channel(mesh_node, "weights", weights.reshape(-1), "SCALAR")
    return {"name": anim.name, "samplers": samplers, "channels": channels, "extras": {"fps": float(anim.fps)}}


def _write(path: Path, gltf: dict, blob: bytes) -> Path:
    """GLB container: a 12-byte header, the JSON chunk (space-padded) and the BIN chunk."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    data = (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(blob), 0x004E4942) + blob)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path
