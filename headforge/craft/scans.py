"""Head scans for HeadCraft: generated sets with exact ground truth, and a reader for real ones.

Generated scans (``headforge craft scans``): an anny head (the topology `open-head` is built
from, so ground truth lives on the template's own vertices) with a sampled phenotype and head
local changes, mostly neutral with some ARKit expressions, a small random rigid motion, and a
procedural hair volume the head model lacks (bald, short, bob, long straight, bun, ponytail,
curly; ``headforge synth``'s hair extended). The clean scan is the union of the skin and the
hair surfaces (skin under the hair and hair inside the skin removed; mouth and eye cavities
removed: a scanner does not see them). Harder variants, as real scans are:

- ``remeshed``: the union re-extracted by marching cubes from a signed distance grid -- another
  topology and density, watertight;
- ``noisy``: remeshed + scanner noise along the normals;
- ``holes``: remeshed with holes under the chin and at the crown;
- ``out_of_span``: smooth bumps (nose, cheeks, brow, skull) added to the head before the hair,
  outside the head model's PCA span.

Every identity has a neutral scan (``<id>``); some also an expression scan (``<id>_expr``).

Each scan folder holds ``scan.ply`` and ``gt.json`` (generating parameters, variant, hair style,
rigid motion) and ``gt.npz``: ``landmarks`` (478, 3) MediaPipe points on the skin, ``labels``
(Vs,) per scan vertex (:data:`LABELS`), ``hair`` (Vs,) bool, ``head`` (V, 3) the skin surface in
template topology (scan frame). Coordinates: metres, y up, face toward +z; a scan is the
canonical head moved by ``x_scan = R x + t`` (gt.json ``rotation``, ``translation``).

External scans: :func:`read_scan` (OBJ/PLY/GLB/STL, units and up/forward axes, optional
landmark file: JSON list of 478 points, or menpo LJSON with 68 points); scans without
landmarks get them as HeadCraft's did: rendered views, MediaPipe 2D landmarks, lifted onto the
scan by ray casting (:func:`detect_scan_landmarks`).
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError

HAIR_STYLES = ("bald", "short", "bob", "long", "bun", "ponytail", "curly")
VARIANTS = ("clean", "remeshed", "noisy", "holes", "out_of_span")
LABELS = {"face": 1, "scalp": 2, "hair": 3, "eyes": 4, "ears": 5, "neck": 6, "other": 7}
LABEL_COLOURS = {1: (0.92, 0.75, 0.65), 2: (0.8, 0.62, 0.55), 3: (0.35, 0.25, 0.18), 4: (0.95, 0.95, 0.95),
                 5: (0.85, 0.55, 0.5), 6: (0.7, 0.6, 0.55), 7: (0.5, 0.5, 0.5)}
HEAD_CENTRE = np.array([0.0, 0.03, -0.03])  # rough skull centre in head space (synth's)
EXPRESSIONS = (  # ARKit action combinations for the expression scans
    {"jawOpen": 0.45},
    {"mouthSmileLeft": 0.7, "mouthSmileRight": 0.7},
    {"browInnerUp": 0.8, "eyeWideLeft": 0.5, "eyeWideRight": 0.5},
    {"jawOpen": 0.25, "mouthFunnel": 0.6},
    {"mouthPressLeft": 0.5, "mouthPressRight": 0.5, "browDownLeft": 0.6, "browDownRight": 0.6},
)
MAX_SCAN_VERTICES = 2_000_000  # external scans above this are refused (memory and time)


# ---------------------------------------------------------------- configuration
@dataclass
class ScanSetConfig:
    n: int = 8  # identities
    seed: int = 0
    expression_every: int = 3  # every k-th identity also gets an expression scan
    harder: bool = True  # cycle the variants over the identities (False: all clean)
    hair_voxel_m: float = 0.003
    remesh_voxel_m: float = 0.0025
    noise_m: float = 0.0004  # std of the normal noise of ``noisy``
    max_rotation_deg: float = 8.0
    max_translation_m: float = 0.02
    sheet_px: int = 200
    source: str = "anny"  # identities from anny ("anny") or the head model's own PCA ("open-head": fast, in span)

    @classmethod
    def quick(cls) -> ScanSetConfig:
        return cls(n=2, hair_voxel_m=0.004, remesh_voxel_m=0.003, sheet_px=160)

    def validate(self) -> None:
        if self.n < 1:
            raise HeadforgeError(f"--n must be >= 1, got {self.n}")
        if not (0.001 <= self.hair_voxel_m <= 0.01 and 0.001 <= self.remesh_voxel_m <= 0.01):
            raise HeadforgeError("voxel sizes must be within 1-10 mm")
        if self.source not in ("anny", "open-head"):
            raise HeadforgeError(f"scan source must be anny or open-head, got {self.source!r}")


@dataclass
class ScanSpec:
    """Everything random about one generated scan (gt.json)."""

    key: str
    identity: int
    hair_style: str
    variant: str
    phenotype: dict[str, float]
    local_changes: list[float]
    expression: dict[str, float] = field(default_factory=dict)
    rotation: list[list[float]] = field(default_factory=lambda: np.eye(3).tolist())
    translation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    bumps: list[dict] = field(default_factory=list)  # out_of_span: centre vertex, amplitude, radius
    seed: int = 0
    source: str = "anny"
    shape: list[float] = field(default_factory=list)  # source "open-head": identity coefficients


def scan_specs(model, config: ScanSetConfig) -> list[ScanSpec]:
    """The scans of a set: identity i has style HAIR_STYLES[(i + seed) % 7], variant
    VARIANTS[i % 5]. ``model``: the anny head (source anny) or None (source open-head)."""
    from scipy.spatial.transform import Rotation

    specs = []
    labels = list(model.phenotype_labels) if model is not None else []
    local_labels = list(model.local_change_labels) if model is not None else []
    head_like = [i for i, name in enumerate(local_labels)
                 if any(p in name for p in ("head", "nose", "mouth", "chin", "cheek", "eyes", "ears", "forehead", "eyebrows", "jaw", "neck"))]
    for i in range(config.n):
        rng = np.random.default_rng([config.seed, i, 41])
        phen = {"gender": float(rng.random()), "age": float(rng.uniform(0.4, 0.95)),
                "muscle": float(rng.uniform(0.2, 0.8)), "weight": float(rng.uniform(0.2, 0.8)),
                "height": float(rng.uniform(0.35, 0.65)), "proportions": float(rng.uniform(0.35, 0.65))}
        phen = {k: phen.get(k, 0.5) for k in labels}
        local = np.zeros(len(local_labels))
        local[head_like] = np.clip(0.4 * rng.standard_normal(len(head_like)), -1, 1)
        style = HAIR_STYLES[(i + config.seed) % len(HAIR_STYLES)]
        variant = VARIANTS[i % len(VARIANTS)] if config.harder else "clean"
        for expr in (False, True):
            if expr and i % config.expression_every != config.expression_every - 1:
                continue
            r = Rotation.from_rotvec(rng.normal(size=3) / math.sqrt(3) * math.radians(config.max_rotation_deg) * rng.random())
            spec = ScanSpec(key=f"id{i:03d}" + ("_expr" if expr else ""), identity=i, hair_style=style,
                            variant=variant, phenotype=phen, local_changes=local.tolist(),
                            expression=dict(EXPRESSIONS[int(rng.integers(len(EXPRESSIONS)))]) if expr else {},
                            rotation=r.as_matrix().tolist(),
                            translation=(rng.uniform(-1, 1, 3) * config.max_translation_m).tolist(),
                            seed=config.seed, source=config.source,
                            shape=(0.8 * np.random.default_rng([config.seed, i, 43]).standard_normal(30)).tolist()
                            if config.source == "open-head" else [])
            if config.source == "open-head":
                spec.phenotype, spec.local_changes = {}, []
            if variant == "out_of_span":
                spec.bumps = [{"vertex": int(rng.integers(1 << 30)), "amplitude_m": float(rng.choice([-1, 1]) * rng.uniform(0.003, 0.007)),
                               "radius_m": float(rng.uniform(0.012, 0.03))} for _ in range(6)]
            specs.append(spec)
    return specs


# ---------------------------------------------------------------- geometry helpers
def _surface_samples(vertices, faces, n, seed):
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    pts, fid = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return pts, mesh.face_normals[fid], fid


def signed_distance_grid(points: np.ndarray, samples: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Approximate signed distance of ``points`` to a surface given by dense samples with
    outward normals (sign of the offset along the nearest sample's normal)."""
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(samples).query(points, workers=torch.get_num_threads())
    sign = np.sign(((points - samples[nearest]) * normals[nearest]).sum(1))
    return dist * np.where(sign == 0, 1.0, sign)


def _style_sdf(style: str, points: np.ndarray, dist: np.ndarray, scalp_w: np.ndarray) -> np.ndarray:
    """Signed distance of a hair volume (``headforge synth``'s four styles, plus long and ponytail)."""
    from headforge.bench.synthetic import _hair_sdf

    if style in ("short", "bob", "bun", "curly"):
        return _hair_sdf(style, points, dist, scalp_w, HEAD_CENTRE)
    rel = points - HEAD_CENTRE
    thickness = {"long": 0.011, "ponytail": 0.006}[style]
    sdf = np.maximum(dist - thickness * scalp_w + 0.004 * (1 - scalp_w), -dist - 0.002)
    if style == "long":  # straight hair falling behind the ears down to the shoulders
        radii = np.array([0.098, 0.19, 0.125])
        q = (rel - np.array([0.0, -0.05, -0.035])) / radii
        shell = (np.linalg.norm(q, axis=1) - 1.0) * radii.min()
        shell = np.maximum(np.maximum(shell, rel[:, 2] + 0.01), -0.2 - rel[:, 1])
        sdf = np.minimum(sdf, np.maximum(shell, -dist + 0.001))
    if style == "ponytail":  # a tapered tail from the back of the head, hanging down and back
        a, b = np.array([0.0, 0.045, -0.105]), np.array([0.0, -0.13, -0.165])
        ab = b - a
        s = np.clip(((rel - a) @ ab) / (ab @ ab), 0, 1)
        radius = 0.024 - 0.012 * s
        tail = np.linalg.norm(rel - (a + s[:, None] * ab), axis=1) - radius
        sdf = np.minimum(sdf, tail)
    return sdf


def full_grid_values(axes: list[np.ndarray], evaluate) -> np.ndarray:
    """``evaluate`` (P, 3) points -> (P,) at every point of the grid of ``axes``, shaped as the grid."""
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return evaluate(grid).reshape([len(a) for a in axes])


def banded_grid_values(axes: list[np.ndarray], evaluate, margin: float) -> np.ndarray:
    """(len(axes[0]), len(axes[1]), len(axes[2])) values of a signed-distance-like field on the
    grid of ``axes`` (metres), evaluated exactly only near its zero level: ``evaluate`` (P, 3)
    points -> (P,) runs on every second grid point first, then on the fine points of each coarse
    cell that has a corner within ``margin`` of zero or corners of both signs; the others get
    the coarse values' trilinear interpolation. Marching cubes reads values only at the ends of
    sign-changing edges, so its surface is the full evaluation's wherever the field changes by
    less than ``margin`` over a coarse cell (tests/test_craft_scans.py compares the two); the
    k-d tree queries far from the surface are the slow ones, and they are the ones skipped."""
    from scipy.interpolate import RegularGridInterpolator

    coarse_ix = [np.unique(np.r_[np.arange(0, len(a), 2), len(a) - 1]) for a in axes]
    if min(len(i) for i in coarse_ix) < 2:
        return full_grid_values(axes, evaluate)
    coarse = full_grid_values([a[i] for a, i in zip(axes, coarse_ix)], evaluate)
    corners = np.stack([coarse[a:coarse.shape[0] - 1 + a, b:coarse.shape[1] - 1 + b, c:coarse.shape[2] - 1 + c]
                        for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    near = (np.abs(corners).min(0) < margin) | ((corners.min(0) < 0) & (corners.max(0) > 0))
    # the coarse cell of each fine index along each axis
    cell = [np.clip(np.searchsorted(ci, np.arange(len(a)), side="right") - 1, 0, len(ci) - 2)
            for a, ci in zip(axes, coarse_ix)]
    exact = near[np.ix_(*cell)]
    full_shape = [len(a) for a in axes]
    fine = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    values = np.empty(full_shape)
    if exact.any():
        values[exact] = evaluate(fine[exact])
    far = ~exact
    if far.any():
        values[far] = RegularGridInterpolator([a[i] for a, i in zip(axes, coarse_ix)], coarse)(fine[far])
    return values


def build_hair_volume(style: str, vertices: np.ndarray, faces: np.ndarray, scalp: np.ndarray, voxel: float,
                      seed: int):
    """Hair for a rest head (headforge axes): (hair vertices, hair faces, sdf sampler) or
    (None, None, None) for bald. The sampler evaluates the hair SDF at points (trilinear)."""
    import trimesh
    from scipy.ndimage import map_coordinates
    from skimage.measure import marching_cubes

    from headforge.head.topology import laplacian_smooth

    if style == "bald":
        return None, None, None
    if style not in HAIR_STYLES:
        raise HeadforgeError(f"unknown hair style {style!r}; choose one of {', '.join(HAIR_STYLES)}")
    samples, normals, fid = _surface_samples(vertices, faces, 120_000, seed)
    mask = np.zeros(len(vertices))
    mask[scalp] = 1.0
    w = laplacian_smooth(torch.from_numpy(mask)[None, :, None].expand(1, -1, 3).contiguous(),
                         torch.from_numpy(faces), 0.5, iterations=8)[0, :, 0].numpy()
    sample_w = w[faces[fid]].mean(1)
    low_margin = 0.24 if style in ("long", "ponytail") else 0.12
    lo = vertices[scalp].min(0) - np.array([0.05, low_margin, 0.09])
    hi = vertices[scalp].max(0) + np.array([0.05, 0.05, 0.06])
    shape = np.ceil((hi - lo) / voxel).astype(int) + 1
    axes = [lo[k] + voxel * np.arange(shape[k]) for k in range(3)]
    from scipy.spatial import cKDTree

    tree = cKDTree(samples)

    def style_sdf_at(points: np.ndarray) -> np.ndarray:
        dist, nearest = tree.query(points, workers=torch.get_num_threads())
        sign = np.sign(((points - samples[nearest]) * normals[nearest]).sum(1))
        return _style_sdf(style, points, dist * sign, sample_w[nearest])

    sdf = banded_grid_values(axes, style_sdf_at, margin=6 * voxel)
    sdf = np.pad(sdf, 1, constant_values=1.0)
    verts, tris, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3)
    verts = verts + lo - voxel
    hair = trimesh.Trimesh(verts, tris, process=True)
    parts = hair.split(only_watertight=False)
    if len(parts):
        hair = max(parts, key=lambda m: len(m.faces))

    def sampler(points: np.ndarray) -> np.ndarray:
        idx = (np.asarray(points) - lo) / voxel + 1.0  # +1: the padding
        return map_coordinates(sdf, idx.T, order=1, mode="nearest")

    return np.asarray(hair.vertices), np.asarray(hair.faces, np.int64), sampler


def vertex_labels(regions: dict[str, np.ndarray], V: int) -> np.ndarray:
    """(V,) :data:`LABELS` of the template vertices from the head model's regions."""
    labels = np.full(V, LABELS["other"], np.int64)
    for name, label in (("scalp", "scalp"), ("neck", "neck"), ("face", "face"), ("ears", "ears"), ("eyeballs", "eyes")):
        labels[regions[name]] = LABELS[label]
    return labels


def apply_bumps(vertices: np.ndarray, faces: np.ndarray, movable: np.ndarray, bumps: list[dict]) -> np.ndarray:
    """Smooth radial bumps along the normals (out of the PCA span), centred on ``movable`` vertices."""
    from headforge.head.topology import vertex_normals

    n = vertex_normals(torch.from_numpy(vertices), torch.from_numpy(faces)).numpy()
    out = vertices.copy()
    for b in bumps:
        c = vertices[movable[b["vertex"] % len(movable)]]
        w = np.exp(-0.5 * (np.linalg.norm(vertices - c, axis=1) / b["radius_m"]) ** 2)
        out += (b["amplitude_m"] * w)[:, None] * n
    return out


def _drop_faces(vertices, faces, drop_face):
    keep = faces[~drop_face]
    used = np.unique(keep)
    remap = np.full(len(vertices), -1)
    remap[used] = np.arange(len(used))
    return used, remap[keep]


def compose_scan(head: np.ndarray, faces: np.ndarray, labels: np.ndarray, hair_v, hair_f, hair_sdf):
    """Union surface of skin and hair: (vertices, faces, labels). Skin inside the hair and hair
    inside the skin are removed, and the mouth/eye cavities (``other``) too."""
    drop = (labels[faces] == LABELS["other"]).all(1)
    if hair_v is not None:
        inside = hair_sdf(head) < -5e-4
        drop |= inside[faces].all(1)
    used, skin_faces = _drop_faces(head, faces, drop)
    verts, tris, labs = head[used], skin_faces, labels[used]
    if hair_v is not None:
        samples, normals, _ = _surface_samples(head, faces, 120_000, 0)
        below = signed_distance_grid(hair_v, samples, normals) < 0.0
        used_h, hair_faces = _drop_faces(hair_v, hair_f, below[hair_f].any(1))
        tris = np.concatenate([tris, hair_faces + len(verts)])
        verts = np.concatenate([verts, hair_v[used_h]])
        labs = np.concatenate([labs, np.full(len(used_h), LABELS["hair"])])
    return verts, tris, labs


def cap_lowest_hole(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces with the lowest boundary loop (the neck cut) closed by a fan to its first vertex."""
    from headforge.head.topology import boundary_loops

    loops = boundary_loops(faces)
    if not loops:
        return faces
    loop = min(loops, key=lambda lp: vertices[lp, 1].mean())
    if len(loop) < 3:
        return faces
    fan = np.stack([np.full(len(loop) - 2, loop[0]), loop[2:], loop[1:-1]], 1)
    return np.concatenate([faces, fan])


def remesh(vertices: np.ndarray, faces: np.ndarray, voxel: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Re-extract the outer surface by marching cubes (watertight, isotropic, another topology).

    Inside/outside comes from a flood fill of the space outside a band of one voxel around the
    surface, so cavities, interior surfaces and gaps narrower than a voxel are closed as a
    scanner would; within the band the sign is the nearest sample's normal side."""
    import trimesh
    from scipy import ndimage
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    samples, normals, _ = _surface_samples(vertices, faces, 300_000, seed)
    lo, hi = vertices.min(0) - 4 * voxel, vertices.max(0) + 4 * voxel
    shape = np.ceil((hi - lo) / voxel).astype(int) + 1
    grid = np.stack(np.meshgrid(*[lo[k] + voxel * np.arange(shape[k]) for k in range(3)], indexing="ij"), -1).reshape(-1, 3)
    dist, nearest = cKDTree(samples).query(grid, workers=1)
    side = np.sign(((grid - samples[nearest]) * normals[nearest]).sum(1))
    dist, side = dist.reshape(*shape), side.reshape(*shape)
    band = dist < voxel
    labels, _ = ndimage.label(~band)
    outside = labels == labels[0, 0, 0]
    outside_near = ndimage.binary_dilation(outside, iterations=2)
    sdf = np.where(outside, dist, np.where(band & outside_near, np.where(side > 0, dist, -dist), -dist))
    v, f, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3)
    mesh = trimesh.Trimesh(v + lo, f, process=True)
    parts = mesh.split(only_watertight=False)
    mesh = max(parts, key=lambda m: len(m.faces)) if len(parts) else mesh
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)


def cut_holes(vertices, faces, head: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove the region under the chin and a disc at the crown (scanners miss both)."""
    centre = vertices[faces].mean(1)
    chin = landmarks[152]
    under_chin = (centre[:, 1] < chin[1] + 0.005) & (centre[:, 1] > chin[1] - 0.05) & \
                 (np.abs(centre[:, 0] - chin[0]) < 0.035) & (centre[:, 2] < chin[2] - 0.012) & (centre[:, 2] > chin[2] - 0.07)
    top = vertices[:, 1].max()
    crown = (centre[:, 1] > top - 0.018) & (np.abs(centre[:, 0]) < 0.05)
    used, new_faces = _drop_faces(vertices, faces, under_chin | crown)
    return vertices[used], new_faces, used


def surface_points(vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    return (vertices[faces[face_ids]] * bary[..., None]).sum(1)


# ---------------------------------------------------------------- generation
class ScanGenerator:
    """Builds the anny head once; :meth:`make` one scan per :class:`ScanSpec`."""

    def __init__(self, config: ScanSetConfig, progress=None):
        from headforge.head.open_head import build_anny_head, load_open_head

        self.config = config
        self.data = load_open_head(progress=progress)
        self.model = build_anny_head() if config.source == "anny" else None
        self.labels = vertex_labels(self.data.regions, len(self.data.v_template))
        self.faces = self.data.faces

    def head_vertices(self, spec: ScanSpec) -> np.ndarray:
        """Skin in template topology, canonical (eye-midpoint origin, headforge axes)."""
        from headforge.head.open_head import JOINT_BONE, _to_hf

        if spec.source == "open-head":
            from headforge.head.model import HeadModel

            model = HeadModel(self.data).double()
            shape = torch.zeros(1, model.n_shape, dtype=torch.float64)
            shape[0, :len(spec.shape)] = torch.tensor(spec.shape, dtype=torch.float64)
            expr = torch.zeros(1, model.n_expr, dtype=torch.float64)
            for k, v in spec.expression.items():
                if k in model.expression_names:
                    expr[0, model.expression_names.index(k)] = v
            with torch.no_grad():
                return model(shape=shape, expression=expr).vertices[0].numpy()
        m = self.model
        phen = {k: torch.tensor([v], dtype=torch.float64) for k, v in spec.phenotype.items()}
        local = torch.tensor([spec.local_changes], dtype=torch.float64)
        actions = torch.zeros(1, len(m.facial_action_labels), dtype=torch.float64)
        names = list(m.facial_action_labels)
        for k, v in spec.expression.items():
            if k in names:
                actions[0, names.index(k)] = v
        with torch.no_grad():
            out = m(phenotype_kwargs=phen, local_changes_kwargs=local, facial_actions=actions)
            neutral = m(phenotype_kwargs=phen, local_changes_kwargs=local)
        verts = _to_hf(out["rest_vertices"][0])
        bones = _to_hf(neutral["rest_bone_heads"][0])
        labels = list(m.bone_labels)
        centre = 0.5 * (bones[labels.index(JOINT_BONE["eye_left"])] + bones[labels.index(JOINT_BONE["eye_right"])])
        return verts - centre

    def make(self, spec: ScanSpec) -> dict:
        """(vertices, faces, labels, landmarks, head) of one scan in the scan frame."""
        cfg, data = self.config, self.data
        head = self.head_vertices(spec)
        if spec.bumps:
            movable = np.union1d(data.regions["face"], data.regions["scalp"])
            head = apply_bumps(head, self.faces, movable, spec.bumps)
        hair_v, hair_f, sampler = build_hair_volume(spec.hair_style, head, self.faces, data.regions["scalp"],
                                                    cfg.hair_voxel_m, seed=spec.identity + 1000 * spec.seed)
        verts, faces, labels = compose_scan(head, self.faces, self.labels, hair_v, hair_f, sampler)
        landmarks = surface_points(head, self.faces, data.landmark_faces, data.landmark_bary)
        if spec.variant in ("remeshed", "noisy", "holes"):
            from scipy.spatial import cKDTree

            rv, rf = remesh(verts, cap_lowest_hole(verts, faces), cfg.remesh_voxel_m, seed=spec.identity)
            labels = labels[cKDTree(verts).query(rv)[1]]
            verts, faces = rv, rf
            if spec.variant == "noisy":
                from headforge.head.topology import vertex_normals

                rng = np.random.default_rng([spec.seed, spec.identity, 5])
                n = vertex_normals(torch.from_numpy(verts), torch.from_numpy(faces)).numpy()
                verts = verts + cfg.noise_m * rng.standard_normal((len(verts), 1)) * n
            if spec.variant == "holes":
                verts, faces, used = cut_holes(verts, faces, head, landmarks)
                labels = labels[used]
        R, t = np.asarray(spec.rotation), np.asarray(spec.translation)
        move = lambda x: x @ R.T + t
        return {"vertices": move(verts), "faces": faces, "labels": labels, "hair": labels == LABELS["hair"],
                "landmarks": move(landmarks), "head": move(head)}


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    import trimesh

    tmp = path.with_name(path.stem + ".partial.ply")
    trimesh.Trimesh(vertices, faces, process=False).export(tmp)
    tmp.replace(path)


def write_scan(folder: Path, spec: ScanSpec, scan: dict) -> None:
    """One scan folder, written to ``<folder>.partial`` and renamed when complete."""
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    write_ply(tmp / "scan.ply", scan["vertices"], scan["faces"])
    np.savez_compressed(tmp / "gt.npz", landmarks=scan["landmarks"].astype(np.float32), labels=scan["labels"].astype(np.uint8),
                        hair=scan["hair"], head=scan["head"].astype(np.float32))
    (tmp / "gt.json").write_text(json.dumps(asdict(spec), indent=1))
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)


# ---------------------------------------------------------------- pictures
def render_mesh(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray, size: int = 256,
                yaw_deg: float = 30.0, target=None, distance: float = 0.75) -> np.ndarray:
    """(size, size, 3) float Lambert-shaded picture of a mesh with per-vertex colours."""
    from headforge.render.camera import look_at_head
    from headforge.render.raycast import raycast, shade_lambert

    target = vertices.mean(0) if target is None else target
    cam = look_at_head(size, size, distance=distance, yaw_deg=yaw_deg, target=target)
    hits = raycast(vertices, faces, cam)
    albedo = (colours[faces[np.maximum(hits.face_id, 0)]] * hits.bary[..., None]).sum(-2)
    light = cam.centre - np.asarray(target) + np.array([0.0, 0.4 * distance, 0.0])  # from the camera, a bit above
    shaded = shade_lambert(hits, faces, vertices, albedo, cam, light_dir=tuple(light))
    return np.where(hits.mask[..., None], shaded, 1.0)


def label_colours(labels: np.ndarray) -> np.ndarray:
    table = np.zeros((max(LABEL_COLOURS) + 1, 3))
    for k, c in LABEL_COLOURS.items():
        table[k] = c
    return table[labels]


def contact_sheet(folders: list[Path], size: int = 200, columns: int = 6) -> np.ndarray:
    """Thumbnails (front and 3/4-back views, coloured by label) of scan folders, with names."""
    import cv2
    import trimesh

    tiles = []
    for folder in folders:
        mesh = trimesh.load(folder / "scan.ply", process=False)
        gt = np.load(folder / "gt.npz")
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        col = label_colours(gt["labels"])
        spec = json.loads((folder / "gt.json").read_text())
        target = gt["landmarks"].mean(0) + np.array([0, -0.02, -0.08])
        pair = np.concatenate([render_mesh(v, f, col, size, 20.0, target), render_mesh(v, f, col, size, 140.0, target)], 1)
        img = (np.clip(pair, 0, 1) * 255).astype(np.uint8).copy()
        text = f"{folder.name} {spec['hair_style']} {spec['variant']}"
        cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (20, 20, 20), 1, cv2.LINE_AA)
        tiles.append(img)
    columns = max(1, min(columns // 2, len(tiles)))
    rows = math.ceil(len(tiles) / columns)
    sheet = np.full((rows * size, columns * 2 * size, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * size:(r + 1) * size, c * 2 * size:(c + 1) * 2 * size] = t
    return sheet


def write_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    tmp = path.with_name(path.stem + ".partial.png")
    Image.fromarray(image).save(tmp)
    tmp.replace(path)


_WORKER_GENERATOR: ScanGenerator | None = None


def _write_one(config: ScanSetConfig, spec: ScanSpec, folder: str) -> int:
    """Worker-process body of :func:`generate_scans`: one scan, with the process's own generator."""
    global _WORKER_GENERATOR
    if _WORKER_GENERATOR is None:
        _WORKER_GENERATOR = ScanGenerator(config)
    scan = _WORKER_GENERATOR.make(spec)
    write_scan(Path(folder), spec, scan)
    return len(scan["vertices"])


def generate_scans(output: str | Path, config: ScanSetConfig, log=print, workers: int = 1) -> list[str]:
    """Write a scan set (resumable: finished scan folders are kept) and its contact sheet.
    ``workers`` > 1 makes the scans in that many processes (one thread each); the set is the same."""
    config.validate()
    if workers < 1:
        raise HeadforgeError(f"--workers must be >= 1, got {workers}")
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    gen = ScanGenerator(config)
    specs = scan_specs(gen.model, config)
    keys = [spec.key for spec in specs]
    todo = [spec for spec in specs if not (output / spec.key / "gt.json").exists()]

    def logged(done: int, spec: ScanSpec, n_vertices: int) -> None:
        log(f"[{done}/{len(todo)}] {spec.key}: {spec.hair_style}, {spec.variant}"
            + (f", {'+'.join(spec.expression)}" if spec.expression else "") + f", {n_vertices} vertices")

    if workers > 1 and len(todo) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        from headforge.batch.runner import cap_threads

        # one thread per worker for every library (the k-d tree queries follow torch's count)
        with ProcessPoolExecutor(min(workers, len(todo)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=cap_threads, initargs=(1,)) as pool:
            futures = {pool.submit(_write_one, config, spec, str(output / spec.key)): spec for spec in todo}
            for done, future in enumerate(as_completed(futures), 1):
                logged(done, futures[future], future.result())
    else:
        for done, spec in enumerate(todo, 1):
            scan = gen.make(spec)
            write_scan(output / spec.key, spec, scan)
            logged(done, spec, len(scan["vertices"]))
    index = {"scans": keys, "config": asdict(config), "labels": LABELS, "hair_styles": list(HAIR_STYLES),
             "variants": list(VARIANTS)}
    tmp = output / "index.json.partial"
    tmp.write_text(json.dumps(index, indent=1))
    tmp.replace(output / "index.json")
    write_png(output / "contact_sheet.png", contact_sheet([output / k for k in keys], config.sheet_px))
    return keys


# ---------------------------------------------------------------- external scans
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclass
class Scan:
    """A scan in headforge head axes (metres, y up, face toward +z)."""

    vertices: np.ndarray  # (N, 3)
    faces: np.ndarray  # (F, 3)
    landmarks: np.ndarray | None = None  # (478, 3) MediaPipe order, NaN where unknown
    name: str = "scan"
    meta: dict = field(default_factory=dict)


def axes_matrix(up: str, forward: str) -> np.ndarray:
    """Rotation taking the file's ``up`` axis to +y and ``forward`` (where the face looks) to +z."""
    if up not in AXES or forward not in AXES:
        raise HeadforgeError(f"axes must be one of {', '.join(AXES)}; got up={up!r}, forward={forward!r}")
    u, f = np.array(AXES[up], float), np.array(AXES[forward], float)
    if abs(u @ f) > 0.5:
        raise HeadforgeError(f"up {up} and forward {forward} must be different axes")
    x = np.cross(u, f)
    return np.stack([x, u, f])  # rows: file axes expressed -> new x, y, z


def guess_units(extent_height: float) -> str | None:
    """Unit whose head-and-neck height (bounding box y extent) lands within 0.12-1.0 m."""
    for unit, scale in UNITS.items():
        if 0.12 <= extent_height * scale <= 1.0:
            return unit
    return None


# MediaPipe face-mesh index of each iBUG-68 point (the common community correspondence);
# the jaw contour (0-16) is ambiguous on meshes and is not used for fitting.
IBUG68_TO_MEDIAPIPE = np.array([
    127, 234, 93, 132, 58, 136, 150, 176, 152, 400, 379, 365, 288, 361, 323, 454, 356,
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300, 168, 197, 5, 4, 75, 97, 2, 326, 305,
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380, 61, 39, 37, 0, 267, 269,
    291, 405, 314, 17, 84, 181, 78, 82, 13, 312, 308, 317, 14, 87])
# menpo LJSON label groups -> iBUG-68 index ranges. "l"/"r" is the image's side: menpo's "leye"
# is the subject's right eye (iBUG 36-41), checked on james.ljson (it lies at -x, outer corner first).
LJSON_GROUPS = {"chin": range(17), "leyebrow": range(17, 22), "reyebrow": range(22, 27), "nose": range(27, 36),
                "leye": range(36, 42), "reye": range(42, 48), "mouth": range(48, 68)}


def read_landmarks(path: str | Path) -> np.ndarray:
    """(478, 3) landmarks in the file's coordinates, NaN where unknown. Accepts a JSON list of
    478 points (MediaPipe order) or menpo LJSON (v1-v3) with iBUG-68 label groups."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise HeadforgeError(f"cannot read landmark file {path}: {exc}") from None
    out = np.full((478, 3), np.nan)
    if isinstance(data, list):
        pts = np.asarray(data, float)
        if pts.shape != (478, 3):
            raise HeadforgeError(f"landmark list {path} must be 478 x 3, got {pts.shape}")
        return pts
    group = data.get("groups", {}).get("LJSON", data) if isinstance(data, dict) else {}
    points = np.asarray(group.get("landmarks", {}).get("points", []), float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) != 68:
        raise HeadforgeError(f"{path}: expected 68 3D LJSON points, got shape {points.shape}")
    ibug = np.full((68, 3), np.nan)
    labels = group.get("labels", [])
    if not labels:
        ibug = points
    for lab in labels:
        name, mask = lab["label"], lab["mask"]
        if name not in LJSON_GROUPS or len(mask) != len(LJSON_GROUPS[name]):
            raise HeadforgeError(f"{path}: unknown LJSON label group {name!r} ({len(mask)} points)")
        ibug[list(LJSON_GROUPS[name])] = points[mask]
    out[IBUG68_TO_MEDIAPIPE[17:]] = ibug[17:]
    return out


def read_scan(path: str | Path, units: str = "auto", up: str = "+y", forward: str = "+z",
              landmarks: str | Path | None = None) -> Scan:
    """Read an OBJ/PLY/GLB/STL scan into headforge axes and metres (see the module doc)."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise HeadforgeError(f"no scan at {path}")
    if path.suffix.lower() not in (".obj", ".ply", ".glb", ".gltf", ".stl", ".off"):
        raise HeadforgeError(f"{path.name}: unsupported scan format {path.suffix!r} (OBJ, PLY, GLB, STL)")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 -- trimesh raises many types for bad files
        raise HeadforgeError(f"cannot read scan {path.name}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if len(faces) == 0 or len(vertices) < 4:
        raise HeadforgeError(f"scan {path.name} is empty (no triangles)")
    if len(vertices) > MAX_SCAN_VERTICES:
        raise HeadforgeError(f"scan {path.name} has {len(vertices):,} vertices; the limit is {MAX_SCAN_VERTICES:,} "
                             "(decimate it first)")
    if not np.isfinite(vertices).all():
        raise HeadforgeError(f"scan {path.name} has NaN or infinite vertices")
    area = trimesh.Trimesh(vertices, faces, process=False).area
    if not area > 0:
        raise HeadforgeError(f"scan {path.name} is degenerate (zero surface area)")
    R = axes_matrix(up, forward)
    vertices = vertices @ R.T
    lmk = None
    if landmarks is not None:
        lmk = read_landmarks(landmarks) @ R.T
    height = float(np.ptp(vertices[:, 1]))
    meta = {"source": str(path), "units": units, "up": up, "forward": forward}
    if units == "auto":
        guess = guess_units(height)
        meta["units"] = guess or "unknown"
        scale = UNITS[guess] if guess else 1.0
    elif units in UNITS:
        scale = UNITS[units]
    else:
        try:
            scale = float(units)  # metres per file unit
        except ValueError:
            raise HeadforgeError(f"units must be auto, m, cm, mm or metres per unit, got {units!r}") from None
    vertices = vertices * scale
    if lmk is not None:
        lmk = lmk * scale
    meta["metres_per_unit"] = scale
    return Scan(vertices, faces, lmk, name=path.stem, meta=meta)


def load_generated(folder: str | Path) -> tuple[Scan, dict, dict]:
    """A generated scan folder -> (Scan with its GT landmarks, gt.json, gt.npz arrays)."""
    import trimesh

    folder = Path(folder)
    if not (folder / "scan.ply").exists():
        raise HeadforgeError(f"{folder} is not a scan folder (no scan.ply)")
    mesh = trimesh.load(folder / "scan.ply", process=False)
    gt = dict(np.load(folder / "gt.npz"))
    spec = json.loads((folder / "gt.json").read_text())
    scan = Scan(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                gt["landmarks"].astype(np.float64), name=folder.name, meta={"source": str(folder), "generated": True})
    return scan, spec, gt


def detect_scan_landmarks(scan: Scan, size: int = 512, yaws=(-20.0, 0.0, 20.0)) -> np.ndarray:
    """MediaPipe landmarks of rendered views, lifted onto the scan (ray casting): (478, 3)
    median over the views that see each point. Raises when no view shows a face."""
    from headforge.head.landmarks import detect_mediapipe
    from headforge.render.camera import look_at_head
    from headforge.render.raycast import cast, raycast, shade_lambert

    v, f = scan.vertices, scan.faces
    # unknown units: render at a provisional scale (35 cm tall); the landmark fit finds the true one
    k = 1.0 if scan.meta.get("units") not in (None, "unknown") else 0.35 / max(float(np.ptp(v[:, 1])), 1e-9)
    v = v * k
    top = v[:, 1].max()
    height = float(np.ptp(v[:, 1]))
    # the head is the top ~25 cm; look at its middle from the front
    sel = v[:, 1] > top - min(0.25, height)
    target = np.array([np.median(v[sel, 0]), top - 0.11, np.median(v[sel, 2])])
    lifted = []
    for yaw in yaws:
        cam = look_at_head(size, size, focal=2.4 * size, distance=0.7, yaw_deg=yaw, target=target)
        hits = raycast(v, f, cam)
        albedo = np.broadcast_to(np.array([0.85, 0.7, 0.62]), hits.bary.shape)
        img = shade_lambert(hits, f, v, albedo, cam, light_dir=tuple(cam.centre - target + np.array([0.0, 0.3, 0.0])))
        img = np.where(hits.mask[..., None], img, 0.6)
        pts = detect_mediapipe((np.clip(img, 0, 1) * 255).astype(np.uint8))
        if pts is None:
            continue
        origins, dirs = cam.rays(np.asarray(pts, np.float64)[:, :2])
        fid, bary, dist = cast(v, f, origins, dirs)
        p = origins + dirs * dist[:, None]
        p[fid < 0] = np.nan
        lifted.append(p)
    if not lifted:
        raise HeadforgeError(f"no face detected on renders of scan {scan.name!r}: check its up/forward axes "
                             "or give a landmark file")
    with np.errstate(all="ignore"):
        return np.nanmedian(np.stack(lifted), axis=0) / k
