"""The parametric head model interface shared by FLAME and the open default (`open-head`).

A head model is static data (:class:`HeadModelData`) plus one readable ``nn.Module``
(:class:`HeadModel`) that turns parameters into a posed mesh, smplx-style.

Conventions: metres; canonical head space is right-handed with y up and the face looking
toward +z (FLAME's). Poses are axis-angle (radians). Joint order is FLAME's:
``root, neck, jaw, eye_left, eye_right`` ("left" is the subject's left, at +x).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from safetensors.numpy import load_file, save_file

from headforge.errors import HeadforgeError
from headforge.head import lbs as lbs_fn

JOINT_NAMES = ("root", "neck", "jaw", "eye_left", "eye_right")
POSE_ARGS = ("root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose")
# Regions of surfaces inside the head, never on its outer surface (open-head has all three; a
# model may lack some: callers check ``regions``)
INNER_REGIONS = ("eyeballs", "eye_cavities", "mouth_interior")

# Soft joint limits (half ranges, radians) used when ``joint_limits=True`` (NHA App. A.1):
# physiologically plausible ranges per axis (x: pitch, y: yaw, z: roll).
DEFAULT_JOINT_LIMITS = {
    "root": (float("inf"),) * 3,
    "neck": (1.0, 1.2, 0.6),
    "jaw": (0.6, 0.15, 0.15),
    "eye_left": (0.5, 0.6, 0.05),
    "eye_right": (0.5, 0.6, 0.05),
}


@dataclass
class HeadModelData:
    """Everything that defines a head model, as numpy arrays (saved with safetensors).

    Shapes: V vertices, F triangles, T uv coordinates, J=5 joints, S shape and E
    expression components, L landmarks, P=9*(J-1) pose-corrective features.
    """

    name: str
    v_template: np.ndarray  # (V, 3) float, metres
    faces: np.ndarray  # (F, 3) int
    uvs: np.ndarray  # (T, 2) float in [0, 1], v up
    uv_faces: np.ndarray  # (F, 3) int into uvs: per-face-corner UVs are uvs[uv_faces]
    shapedirs: np.ndarray  # (V, 3, S)
    exprdirs: np.ndarray  # (V, 3, E)
    j_regressor: np.ndarray  # (J, V)
    weights: np.ndarray  # (V, J), rows sum to 1
    parents: np.ndarray  # (J,) int, -1 for the root
    posedirs: np.ndarray | None = None  # (V, 3, P) or None
    landmark_faces: np.ndarray | None = None  # (L,) int
    landmark_bary: np.ndarray | None = None  # (L, 3)
    regions: dict[str, np.ndarray] = field(default_factory=dict)  # name -> vertex ids
    expression_names: list[str] = field(default_factory=list)
    joint_names: list[str] = field(default_factory=lambda: list(JOINT_NAMES))
    meta: dict = field(default_factory=dict)  # provenance, variance explained, ...

    def validate(self) -> None:
        """Check shapes and index ranges; raise HeadforgeError naming the first problem."""
        V = self.v_template.shape[0]
        J = len(self.parents)
        checks = [
            (self.v_template.ndim == 2 and self.v_template.shape[1] == 3, "v_template must be (V, 3)"),
            (self.faces.ndim == 2 and self.faces.shape[1] == 3, "faces must be (F, 3)"),
            (self.faces.size == 0 or (self.faces.min() >= 0 and self.faces.max() < V), "faces index outside the vertices"),
            (self.shapedirs.shape[:2] == (V, 3), f"shapedirs must be ({V}, 3, S), got {self.shapedirs.shape}"),
            (self.exprdirs.shape[:2] == (V, 3), f"exprdirs must be ({V}, 3, E), got {self.exprdirs.shape}"),
            (self.j_regressor.shape == (J, V), f"j_regressor must be ({J}, {V}), got {self.j_regressor.shape}"),
            (self.weights.shape == (V, J), f"weights must be ({V}, {J}), got {self.weights.shape}"),
            (self.uv_faces.shape == self.faces.shape, "uv_faces must match faces"),
            (self.posedirs is None or self.posedirs.shape[:2] == (V, 3), "posedirs must be (V, 3, P)"),
            (len(self.expression_names) in (0, self.exprdirs.shape[2]), "expression_names must name every expression"),
            (self.parents[0] == -1 and all(0 <= p < i for i, p in enumerate(self.parents[1:], 1)), "parents must be a tree with parents before children"),
        ]
        if self.landmark_faces is not None:
            checks.append((self.landmark_bary is not None and self.landmark_bary.shape == (len(self.landmark_faces), 3), "landmark_bary must be (L, 3)"))
            checks.append((self.landmark_faces.size == 0 or self.landmark_faces.max() < len(self.faces), "landmark_faces index outside the faces"))
        for name, ids in self.regions.items():
            checks.append((ids.size == 0 or (ids.min() >= 0 and ids.max() < V), f"region {name!r} indexes outside the vertices"))
        for ok, message in checks:
            if not ok:
                raise HeadforgeError(f"invalid head model {self.name!r}: {message}")

    # ---- persistence -------------------------------------------------------------------
    _ARRAYS = ("v_template", "faces", "uvs", "uv_faces", "shapedirs", "exprdirs", "j_regressor",
               "weights", "parents", "posedirs", "landmark_faces", "landmark_bary")

    def save(self, path: str | Path) -> None:
        """Write ``path`` (.safetensors, JSON metadata inside) atomically."""
        path = Path(path)
        tensors = {k: np.ascontiguousarray(getattr(self, k)) for k in self._ARRAYS if getattr(self, k) is not None}
        tensors.update({f"region.{k}": np.ascontiguousarray(v.astype(np.int64)) for k, v in self.regions.items()})
        header = {"name": self.name, "expression_names": json.dumps(self.expression_names),
                  "joint_names": json.dumps(self.joint_names), "meta": json.dumps(self.meta)}
        tmp = path.with_name(path.name + ".partial")
        save_file(tensors, str(tmp), metadata=header)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> "HeadModelData":
        from safetensors import safe_open

        path = Path(path)
        try:
            with safe_open(str(path), framework="numpy") as handle:
                header = handle.metadata() or {}
            arrays = load_file(str(path))
        except Exception as exc:  # safetensors raises several types for corrupt files
            raise HeadforgeError(f"cannot read head model file {path}: {exc}") from None
        regions = {k.split(".", 1)[1]: v for k, v in arrays.items() if k.startswith("region.")}
        data = cls(name=header.get("name", path.stem),
                   **{k: arrays.get(k) for k in cls._ARRAYS},
                   regions=regions,
                   expression_names=json.loads(header.get("expression_names", "[]")),
                   joint_names=json.loads(header.get("joint_names", json.dumps(list(JOINT_NAMES)))),
                   meta=json.loads(header.get("meta", "{}")))
        data.validate()
        return data


def _landmark_subset(data: HeadModelData) -> HeadModelData:
    """The data restricted to the landmark triangles (its joint regressor is unused: HeadModel
    takes the joint bases from the full data)."""
    from dataclasses import replace

    if data.landmark_faces is None:
        raise HeadforgeError(f"head model {data.name!r} has no landmark embedding")
    tri = data.faces[data.landmark_faces]  # (L, 3)
    keep = np.unique(tri)
    remap = np.full(len(data.v_template), -1)
    remap[keep] = np.arange(len(keep))
    return replace(data, v_template=data.v_template[keep], faces=remap[tri], uv_faces=data.uv_faces[data.landmark_faces],
                  shapedirs=data.shapedirs[keep], exprdirs=data.exprdirs[keep],
                  posedirs=None if data.posedirs is None else data.posedirs[keep], weights=data.weights[keep],
                  j_regressor=np.zeros((len(data.parents), len(keep))), landmark_faces=np.arange(len(tri)),
                  regions={}, meta={**data.meta, "landmarks_only": True})


class HeadOutput(NamedTuple):
    """Result of :meth:`HeadModel.forward` (all in metres, canonical space + translation)."""

    vertices: torch.Tensor  # (B, V, 3) posed
    joints: torch.Tensor  # (B, J, 3) posed
    landmarks: torch.Tensor | None  # (B, L, 3) or None when the model has no embedding
    shaped: torch.Tensor  # (B, V, 3) identity + expression, before posing


class HeadModel(torch.nn.Module):
    """A FLAME-style head: template + identity and expression blendshapes + LBS.

    Inputs (all optional, zeros by default; B is taken from the tensors given):
        shape (B, n_shape), expression (B, n_expr), root_pose / neck_pose / jaw_pose /
        eye_left_pose / eye_right_pose (B, 3) axis-angle, translation (B, 3) metres.
    Static data live in buffers, so ``.to(device)``, ``.double()`` work as usual.
    """

    def __init__(self, data: HeadModelData, joint_limits: bool = False,
                 use_pose_correctives: bool = True, landmarks_only: bool = False):
        """``landmarks_only=True`` keeps only the vertices of the landmark triangles (a few
        hundred): ``vertices`` then holds those, ``faces`` the landmark triangles re-indexed,
        and ``landmarks`` are unchanged -- a cheap forward for landmark fitting."""
        super().__init__()
        data.validate()
        # Joints are linear in the blend coefficients: fold the regressor into the bases, from
        # the full mesh (a landmarks-only model keeps the same joints).
        all_dirs = np.concatenate([data.shapedirs, data.exprdirs], axis=2)
        j_template = data.j_regressor @ data.v_template
        j_dirs = np.einsum("jv,vck->jck", data.j_regressor, all_dirs)
        if landmarks_only:
            data = _landmark_subset(data)
        self.name = data.name
        self.expression_names = list(data.expression_names)
        self.joint_names = list(data.joint_names)
        self.meta = dict(data.meta)
        self.region_names = sorted(data.regions)
        self.joint_limits = joint_limits
        f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        i64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.int64)  # noqa: E731
        V = data.v_template.shape[0]
        self.n_shape = data.shapedirs.shape[2]
        self.n_expr = data.exprdirs.shape[2]
        self.register_buffer("v_template", f32(data.v_template))
        self.register_buffer("faces", i64(data.faces))
        self.register_buffer("uvs", f32(data.uvs))
        self.register_buffer("uv_faces", i64(data.uv_faces))
        # Identity and expression directions stacked as one (S+E, V*3) matrix: one addmm.
        dirs = np.concatenate([data.shapedirs, data.exprdirs], axis=2).reshape(V * 3, -1)
        self.register_buffer("blenddirs", f32(np.ascontiguousarray(dirs.T)))
        self.register_buffer("j_regressor", f32(data.j_regressor))
        J = len(data.parents)
        self.register_buffer("j_template", f32(j_template))
        self.register_buffer("j_blenddirs", f32(j_dirs.transpose(2, 0, 1).reshape(-1, J * 3)))
        self.register_buffer("weights", f32(data.weights))
        self.register_buffer("parents", i64(data.parents))
        self.parent_list = tuple(int(p) for p in data.parents)  # static tree for the forward pass
        if data.posedirs is not None and use_pose_correctives:
            self.register_buffer("posedirs", f32(data.posedirs.reshape(V * 3, -1).T))
        else:
            self.posedirs = None
        has_lmk = data.landmark_faces is not None and len(data.landmark_faces) > 0
        self.register_buffer("landmark_faces", i64(data.landmark_faces) if has_lmk else None)
        self.register_buffer("landmark_bary", f32(data.landmark_bary) if has_lmk else None)
        for name, ids in data.regions.items():
            self.register_buffer(f"region_{name}", i64(ids), persistent=False)
        limits = [DEFAULT_JOINT_LIMITS.get(n, (float("inf"),) * 3) for n in self.joint_names]
        self.register_buffer("joint_half_range", torch.tensor(limits, dtype=torch.float32))

    # ---- static data -------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_landmarks(self) -> int:
        return 0 if self.landmark_faces is None else int(self.landmark_faces.shape[0])

    def effective_poses(self, poses: dict[str, torch.Tensor], raw: bool = False) -> dict[str, torch.Tensor]:
        """The joint rotations the skinning uses for ``poses`` ({root_pose: (B, 3), ...}, any
        subset of POSE_ARGS): the tanh-limited values when this model has ``joint_limits``, else
        ``poses`` unchanged. ``raw=True`` inverts it: the raw parameters whose limited values are
        ``poses`` (to start an optimisation with limits from poses tracked without them)."""
        if not self.joint_limits:
            return dict(poses)
        fn = lbs_fn.unlimit_joint_rotations if raw else lbs_fn.limit_joint_rotations
        out = {}
        for name, value in poses.items():
            j = POSE_ARGS.index(name)
            out[name] = fn(value[:, None], self.joint_half_range[j:j + 1].to(value))[:, 0]
        return out

    def region(self, name: str) -> torch.Tensor:
        """Vertex ids (long) of a named region, e.g. 'face', 'scalp', 'eyeballs'."""
        if name not in self.region_names:
            raise HeadforgeError(f"head model {self.name!r} has no region {name!r}; it has {self.region_names}")
        return getattr(self, f"region_{name}")

    def face_corner_uvs(self) -> torch.Tensor:
        """(F, 3, 2) UV coordinates of every face corner (v up)."""
        return self.uvs[self.uv_faces]

    def skinning_transforms(self, shape: torch.Tensor, expression: torch.Tensor,
                            poses: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """What the skinning of :meth:`forward` applies, for points that carry their own
        blendshapes and weights (point avatars): the per-joint transforms (B, J, 4, 4) mapping
        rest-pose points (metres, canonical head space) to posed ones, and the pose feature
        (B, 9 * (J - 1)) that drives pose correctives (flattened ``R - I`` of every non-root joint).
        ``poses``: {root_pose: (B, 3), ...} (missing joints rest); translation is not applied."""
        B = shape.shape[0]
        coeffs = torch.cat([shape, expression], 1).to(self.v_template.dtype)
        rest_joints = lbs_fn.blend_shapes(coeffs, self.j_blenddirs, self.j_template)
        pose = torch.stack([poses[k] if poses.get(k) is not None else shape.new_zeros(B, 3) for k in POSE_ARGS], 1)
        if self.joint_limits:
            pose = lbs_fn.limit_joint_rotations(pose, self.joint_half_range)
        rotmats = lbs_fn.pose_to_rotmats(pose)
        eye = torch.eye(3, dtype=rotmats.dtype, device=rotmats.device)
        _, transforms = lbs_fn.rigid_transforms(rotmats, rest_joints, self.parent_list)
        return transforms, (rotmats[:, 1:] - eye).reshape(B, -1)

    # ---- forward -----------------------------------------------------------------------
    def _batch(self, given: dict[str, torch.Tensor | None], widths: dict[str, int]) -> int:
        sizes = {}
        for name, value in given.items():
            if value is None:
                continue
            if not isinstance(value, torch.Tensor):
                raise HeadforgeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
            if value.ndim != 2 or value.shape[1] != widths[name]:
                raise HeadforgeError(f"{name} must have shape (B, {widths[name]}), got {tuple(value.shape)}")
            sizes[name] = value.shape[0]
        if len(set(sizes.values())) > 1:
            raise HeadforgeError(f"inconsistent batch sizes: {sizes}")
        return next(iter(sizes.values()), 1)

    def forward(
        self,
        shape: torch.Tensor | None = None,
        expression: torch.Tensor | None = None,
        root_pose: torch.Tensor | None = None,
        neck_pose: torch.Tensor | None = None,
        jaw_pose: torch.Tensor | None = None,
        eye_left_pose: torch.Tensor | None = None,
        eye_right_pose: torch.Tensor | None = None,
        translation: torch.Tensor | None = None,
        offsets: torch.Tensor | None = None,
    ) -> HeadOutput:
        """``offsets`` (B or 1, V, 3): canonical per-vertex displacements added after the blend
        shapes and before skinning (NHA's geometry network output)."""
        poses = [root_pose, neck_pose, jaw_pose, eye_left_pose, eye_right_pose]
        given = dict(shape=shape, expression=expression, translation=translation, **dict(zip(POSE_ARGS, poses)))
        widths = dict(shape=self.n_shape, expression=self.n_expr, translation=3, **{k: 3 for k in POSE_ARGS})
        B = self._batch(given, widths)
        dtype, device = self.v_template.dtype, self.v_template.device
        zeros = lambda n: torch.zeros(B, n, dtype=dtype, device=device)  # noqa: E731
        coeffs = torch.cat([shape if shape is not None else zeros(self.n_shape),
                            expression if expression is not None else zeros(self.n_expr)], dim=1)
        coeffs = coeffs.to(dtype)
        shaped = lbs_fn.blend_shapes(coeffs, self.blenddirs, self.v_template)
        if offsets is not None:
            if offsets.ndim != 3 or offsets.shape[1:] != shaped.shape[1:] or offsets.shape[0] not in (1, B):
                raise HeadforgeError(f"offsets must have shape (B or 1, {shaped.shape[1]}, 3), got {tuple(offsets.shape)}")
            shaped = shaped + offsets.to(dtype)
        rest_joints = lbs_fn.blend_shapes(coeffs, self.j_blenddirs, self.j_template)
        pose = torch.stack([p if p is not None else zeros(3) for p in poses], dim=1).to(dtype)
        if self.joint_limits:
            pose = lbs_fn.limit_joint_rotations(pose, self.joint_half_range)
        vertices, joints = lbs_fn.lbs(shaped, pose, rest_joints, self.parent_list, self.weights, self.posedirs)
        if translation is not None:
            vertices = vertices + translation[:, None].to(dtype)
            joints = joints + translation[:, None].to(dtype)
        landmarks = None
        if self.landmark_faces is not None:
            landmarks = lbs_fn.surface_points(vertices, self.faces, self.landmark_faces, self.landmark_bary)
        return HeadOutput(vertices=vertices, joints=joints, landmarks=landmarks, shaped=shaped)
