"""What the browser viewer shows, built in memory from a run folder, a tracked dataset or a
HeadCraft map folder: a ``scene.json`` manifest and the binary files it names.

Every scene is in glTF world: the OpenGL frame of the clip's camera (x right, y up, the camera
looking down -z; :func:`headforge.export.gltf.camera_to_gltf`), metres. ``scene.json``::

    kind            "mesh" (an animatable .glb) or "points" (a point sequence)
    title, fps, frames, resolution, K (3x3 px, the clip's camera, or null)
    expressions     expression names (mesh: the glb's morph targets, in order)
    relightable     the light-direction controls apply (point avatars: Lambert on the albedo)
    files           {"glb": "avatar.glb"} or {"points": "points.bin", "pose": "pose"} (:class:`PointPoser`)

``points.bin`` (little endian): positions (T, N, 3) float32, normals (T, N, 3) float32, albedo
(N, 3) uint8, radius (N,) float32 metres; with ``points`` = N in the manifest.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

MAX_FRAMES = 600  # frames of a driving sequence the page receives (points: T x N x 24 bytes)


@dataclass
class Scene:
    """The manifest (``scene.json`` content) and the files it names (name -> bytes)."""

    manifest: dict
    files: dict[str, bytes] = field(default_factory=dict)
    # URL name -> answer(query: {name: value}) -> bytes, computed on GET (point avatars' poses);
    # raises ValueError for a bad query
    handlers: dict = field(default_factory=dict)


class PointPoser:
    """The viewer's sliders on a point avatar: ``pose?frame=F&expression=i:v,j:w&jaw=x,y,z&neck=
    x,y,z&eyes=x,y,z`` poses frame F of the driving ``sequence`` with expression i set to v (...) and
    joint rotations (Euler angles in radians, applied R_y R_x R_z as the page's sliders; eyes: both)
    through the avatar's ``geometry``, and answers positions (N, 3) then normals (N, 3), float32,
    glTF world. Missing fields keep the frame's values."""

    JOINTS = {"jaw": ("jaw_pose",), "neck": ("neck_pose",), "eyes": ("eye_left_pose", "eye_right_pose")}

    def __init__(self, avatar, sequence: dict):
        import threading

        self.avatar, self.sequence = avatar, sequence
        self.lock = threading.Lock()  # one pose at a time: the server answers on several threads

    def __call__(self, query: dict[str, str]) -> bytes:
        import torch
        from scipy.spatial.transform import Rotation

        from headforge.export.gltf import OPENGL_FROM_OPENCV

        T = int(self.sequence["translation"].shape[0])
        frame = int(query.get("frame", "0"))
        if not 0 <= frame < T:
            raise ValueError(f"frame must be in 0..{T - 1}")
        params = {k: v[frame:frame + 1].clone() for k, v in self.sequence.items()}

        def floats(name: str, count: int) -> torch.Tensor:
            values = [float(x) for x in query[name].split(",")]
            if len(values) != count or not all(np.isfinite(values)):
                raise ValueError(f"{name} needs {count} finite numbers")
            return torch.tensor([values], dtype=torch.float32)

        if query.get("expression"):
            E = params["expression"].shape[1]
            for pair in query["expression"].split(","):
                index, value = pair.split(":")
                if not 0 <= int(index) < E or not np.isfinite(float(value)):
                    raise ValueError(f"expression entries are index:value with index in 0..{E - 1}")
                params["expression"][0, int(index)] = float(value)
        tracked = {}
        for name, keys in self.JOINTS.items():
            if name in query:
                x, y, z = floats(name, 3)[0].tolist()
                rotvec = torch.tensor(Rotation.from_euler("YXZ", [y, x, z]).as_rotvec()[None], dtype=torch.float32)
                tracked.update({k: rotvec for k in keys})
        if tracked:  # slider angles are the rotations the skinning sees: the avatar's raw parameters of them
            raw = self.avatar.params_from_tracking({**params, **tracked})
            params.update({k: raw[k] for k in tracked})
        with self.lock, torch.no_grad():
            g = self.avatar.geometry(params)
        pos = g.vertices[0].numpy() @ OPENGL_FROM_OPENCV
        nrm = g.normals[0].numpy() @ OPENGL_FROM_OPENCV
        return pos.astype("<f4").tobytes() + nrm.astype("<f4").tobytes()


def build_scene(path: str | Path, texture_size: int = 512, max_frames: int = MAX_FRAMES) -> Scene:
    """The scene of ``path``: a run folder (``run.json``), a tracked dataset (``dataset.json``)
    or a HeadCraft map folder (``map.png`` and ``registered.ply``)."""
    path = Path(path)
    if not path.exists():
        raise HeadforgeError(f"{path} does not exist")
    if not path.is_dir():
        raise HeadforgeError(f"{path} is not a folder: give a run folder, a tracked dataset or a HeadCraft map folder")
    if (path / "run.json").is_file() or (path / "config.json").is_file():
        return run_scene(path, texture_size, max_frames)
    if (path / "dataset.json").is_file():
        return dataset_scene(path, max_frames)
    if (path / "registered.ply").is_file():
        return map_scene(path)
    raise HeadforgeError(f"{path} is neither a run folder (run.json), a tracked dataset (dataset.json) nor a "
                         f"HeadCraft map folder (registered.ply)")


def _base(title: str, fps: float, frames: int, K, resolution: int | None, expressions: list[str]) -> dict:
    return {"title": title, "fps": float(fps), "frames": int(frames),
            "K": None if K is None else np.asarray(K, float).tolist(), "resolution": resolution,
            "expressions": list(expressions), "relightable": False}


def run_scene(run: Path, texture_size: int, max_frames: int) -> Scene:
    """A trained avatar driven by its own frames: a mesh avatar as its animatable glb, a point
    avatar as its PLY sequence (both through the avatar's ``export``)."""
    from headforge.avatars.base import Clip
    from headforge.avatars.reenact import driving_clip, truncate
    from headforge.avatars.run import load_run

    r = load_run(run)
    formats = r.avatar.export_formats()
    seq, fps = driving_clip(r.avatar, r.assets, None, "all")
    seq = truncate(seq, max_frames)
    T = int(seq["translation"].shape[0])
    K = r.assets.intrinsics(r.config.resolution)
    clip = Clip(seq, fps, K, r.config.resolution)
    names = list(r.assets.meta.get("expression_names") or [])
    manifest = _base(f"{run.name} ({r.method.name})", fps, T, K, r.config.resolution, names)
    with tempfile.TemporaryDirectory(prefix="headforge-view-") as tmp:
        if "glb" in formats:
            r.avatar.export(Path(tmp), "glb", None, texture_size, clip=clip)
            return Scene({**manifest, "kind": "mesh", "files": {"glb": "avatar.glb"}},
                         {"avatar.glb": (Path(tmp) / "avatar.glb").read_bytes()})
        if "ply" in formats and getattr(r.avatar, "relightable", False):
            written = r.avatar.export(Path(tmp), "ply", None, texture_size, clip=clip)
            frames = sorted(p for p in written if p.parent.name == "sequence")
            clouds = [read_point_ply(p) for p in frames]
            blob, n = _points_blob(clouds)
            return Scene({**manifest, "kind": "points", "relightable": True, "points": n,
                          "files": {"points": "points.bin", "pose": "pose"}}, {"points.bin": blob},
                         {"pose": PointPoser(r.avatar, seq)})
    raise HeadforgeError(f"the viewer cannot show {r.method.name} avatars: they export {', '.join(formats) or 'nothing'}"
                         f" (it needs an animatable glb or a relightable PLY sequence)")


def dataset_scene(root: Path, max_frames: int) -> Scene:
    """A tracked dataset: its head model with the tracked identity, animated by the tracked
    expressions and poses of its valid frames (a lit grey mesh: a dataset has no texture)."""
    from headforge.avatars.run import RunAssets
    from headforge.export import gltf
    from headforge.head.model import POSE_ARGS, HeadModel
    from headforge.head.pose import POSE_KEYS

    assets = RunAssets.from_dataset(root)
    data = assets.head_data()
    head = HeadModel(data)
    import torch

    rows = assets.rows("all")[:max_frames]
    if not rows:
        raise HeadforgeError(f"{root} has no valid frames to show")
    track = {k: v[rows].float() for k, v in assets.tracking.items() if k in (*POSE_KEYS, "expression", "translation")}
    shape = assets.tracking["shape"].float()[:, :head.n_shape]
    with torch.no_grad():
        out = head(shape=shape)
    rest, joints = out.vertices[0].numpy(), out.joints[0].numpy()
    from headforge.head.topology import vertex_normals

    normals = vertex_normals(out.vertices, head.faces)[0].numpy()
    exprdirs = head.blenddirs[head.n_shape:].reshape(head.n_expr, -1, 3).numpy()
    fps = float(assets.meta.get("fps", 25.0))
    animation = gltf.Animation(fps, torch.stack([track[k] for k in POSE_ARGS], 1).numpy(),
                               gltf.camera_to_gltf(track["translation"].numpy()), track["expression"].numpy())
    names = list(data.expression_names) or [f"expression_{i}" for i in range(head.n_expr)]
    resolution = int(assets.meta["resolution"])
    K = assets.intrinsics(resolution)
    with tempfile.TemporaryDirectory(prefix="headforge-view-") as tmp:
        path = gltf.write_glb(Path(tmp) / "dataset.glb", rest, head.faces.numpy(), normals=normals,
                              skin=gltf.Skin(list(head.joint_names), head.parents.numpy(), joints, head.weights.numpy()),
                              morph_targets=exprdirs, target_names=names, animation=animation,
                              camera=gltf.Camera(K.numpy(), resolution, resolution))
        blob = path.read_bytes()
    manifest = _base(f"{root.name} (tracked {data.name})", fps, len(rows), K, resolution, names)
    return Scene({**manifest, "kind": "mesh", "files": {"glb": "avatar.glb"}}, {"avatar.glb": blob})


def map_scene(folder: Path) -> Scene:
    """A HeadCraft map folder: its registered mesh (``registered.ply``, the template with the
    map's displacements, head space), static and lit."""
    import trimesh

    from headforge.export import gltf
    from headforge.head.topology import vertex_normals

    try:
        mesh = trimesh.load(folder / "registered.ply", process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for broken files
        raise HeadforgeError(f"cannot read {folder / 'registered.ply'}: {exc}") from None
    import torch

    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if len(v) == 0 or len(f) == 0:
        raise HeadforgeError(f"{folder / 'registered.ply'} has no triangles")
    normals = vertex_normals(torch.as_tensor(v, dtype=torch.float32)[None], torch.as_tensor(f))[0].numpy()
    with tempfile.TemporaryDirectory(prefix="headforge-view-") as tmp:
        blob = gltf.write_glb(Path(tmp) / "map.glb", v, f, normals=normals).read_bytes()
    manifest = _base(f"{folder.name} (HeadCraft map)", 25.0, 0, None, None, [])
    return Scene({**manifest, "kind": "mesh", "files": {"glb": "avatar.glb"}}, {"avatar.glb": blob})


def read_point_ply(path: Path) -> dict[str, np.ndarray]:
    """A binary little-endian PLY of vertices with float/uchar properties -> {property: (N,)}."""
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "uint8": "u1", "int": "<i4",
             "int32": "<i4"}
    with path.open("rb") as f:
        if f.readline().strip() != b"ply":
            raise HeadforgeError(f"{path} is not a PLY file")
        fields, count = [], 0
        while True:
            line = f.readline()
            if not line:
                raise HeadforgeError(f"{path}: the PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if words[:1] == ["format"] and words[1] != "binary_little_endian":
                raise HeadforgeError(f"{path}: only binary little-endian PLY is read, not {words[1]}")
            if words[:2] == ["element", "vertex"]:
                count = int(words[2])
            elif words[:1] == ["property"] and words[1] in types:
                fields.append((words[2], types[words[1]]))
            elif words[:1] == ["end_header"]:
                break
        rows = np.frombuffer(f.read(), dtype=np.dtype(fields), count=count)
    return {name: rows[name] for name, _ in fields}


def _points_blob(clouds: list[dict[str, np.ndarray]]) -> tuple[bytes, int]:
    """points.bin of a sequence of camera-space (OpenCV) clouds with the same points."""
    from headforge.export.gltf import OPENGL_FROM_OPENCV

    n = len(clouds[0]["x"])
    if any(len(c["x"]) != n for c in clouds):
        raise HeadforgeError("the point sequence changes its number of points")
    pos = np.stack([np.stack([c["x"], c["y"], c["z"]], 1) for c in clouds]) @ OPENGL_FROM_OPENCV
    nrm = np.stack([np.stack([c["nx"], c["ny"], c["nz"]], 1) for c in clouds]) @ OPENGL_FROM_OPENCV
    first = clouds[0]
    albedo = np.stack([first["red"], first["green"], first["blue"]], 1).astype("u1")
    radius = first["radius"].astype("<f4")
    blob = pos.astype("<f4").tobytes() + nrm.astype("<f4").tobytes() + albedo.tobytes()
    blob += b"\0" * (-len(blob) % 4) + radius.tobytes()
    return blob, n


def manifest_json(scene: Scene) -> bytes:
    return json.dumps(scene.manifest).encode()
