"""Geometry evaluation on a ``headforge synth`` subject (NHA Table 1 protocol).

For every ground-truth frame of the chosen split (``gt/geometry.safetensors`` lists them):

- per-pixel normal angle error (degrees) between the prediction rendered with the GT camera
  and the GT normal map, over the pixels both cover, in the GT face region and on the full
  head (face, head skin, hair, eyes, mouth; neck excluded);
- one-sided distance prediction -> GT surface (mm): NHA's "average mesh alignment error"
  (mean over area-uniform samples) and the max, for the predicted full head and face, after a
  rigid ICP alignment of the predicted face to the GT face (the 3DFAW-video protocol NHA cites:
  a monocular reconstruction is known up to depth; NHA's FLAME row, 1.2-1.4 mm on the face,
  is only possible aligned), and without alignment in camera space (``*_camera_mm``);
  ``*_scaled_mm`` after a similarity alignment instead (rotation, translation and one scale,
  :func:`similarity_to_face`, as the NoW benchmark aligns monocular face reconstructions: a
  monocular clip fixes the head's size only through the head model's prior), with
  ``alignment_scale`` its factor (> 1: the prediction was smaller than the GT) and
  ``normal_consistency_scaled`` the normal consistency after it;
- normal consistency (PointAvatar): mean |cos| between nearest neighbours, both directions:
  each prediction sample against the GT normal at its closest GT surface point, and each sample
  of the GT head surface the frame's camera sees (:func:`seen_gt_samples`: 10,000 area samples of
  the GT head faces in the frame's z-buffer) against its nearest prediction sample;
- two figures beside the protocol, to read it by: ``hausdorff_full_outer_mm``, the aligned
  full-head distance to the GT's *outer* surface only (the GT meshes, like NHA's MakeHuman ones,
  keep the scalp under the hair, and the synthetic hair volume has an inner shell under the
  skin; a bald prediction lies within ~2 mm of those hidden surfaces, so the protocol's
  distance cannot tell a bald head from a reconstructed hair surface), and ``head_coverage``,
  the fraction of the GT full-head pixels the prediction covers (the normal error counts only
  covered pixels, so a prediction that leaves the hair uncovered is not charged for it).

:func:`paired_normal_error` scores two predictions (an avatar and the tracked model) on the
pixels both cover: the like-for-like comparison the per-prediction normal error is not.

A prediction is either a tracked dataset (the head model posed with ``tracking.safetensors``;
the baseline row) or a folder with ``geometry.safetensors`` holding either a mesh: camera-space
``vertices`` (N, V, 3) for ``frames`` (N,), ``faces`` (F, 3) and bool vertex masks
``face_vertices`` / ``head_vertices`` (V,) -- what mesh avatar trainers export; or a point set
(point avatars, PointAvatar): ``frames`` (N,), camera-space ``points`` (N, P, 3) in metres,
``normals`` (N, P, 3) and world-space radii ``radius`` (N, P) in metres, no faces (the file has
``points`` and no ``vertices``). A point set is scored by the same protocol, each figure defined
for points as follows:

- normal map: the points splatted (:func:`headforge.render.points.splat`, K = 8) as discs of
  ``fx * radius / depth`` pixels carrying their normals; the composited normals renormalised; a
  pixel is covered where the splat's accumulated alpha exceeds 0.5; for an avatar whose renders
  fill the holes between splats (``hole_filling`` in the file: PointAvatar's supp. 2.3) the
  covered pixels are closed (3x3, as the avatar's render mask) and each added pixel takes the
  mean normal of its covered neighbours. The normal errors,
  ``head_coverage`` and the paired figures then follow the mesh definitions on those pixels.
- regions: a point set that carries its own per-point masks ``face_points`` / ``head_points``
  (P,) (PointAvatar's export: the region of each point's nearest canonical head-model vertex)
  is scored on them, as a mesh on its template's regions; otherwise each scored point takes the
  GT label of its nearest GT surface point (the label of the closest GT triangle's nearest
  vertex, found in camera space): *head points* have a full-head label (neck and body excluded),
  *face points* the face label. The GT labels only work for a prediction placed in camera space
  within millimetres of the GT: a point avatar inherits its tracking's depth error (6-8 cm on
  the synthetic bob, docs/pointavatar.md), and then its face points are mostly not nearest the
  GT face. All points count, visible or not, as all of a mesh's head region does.
- one-sided distance: mean (NHA's alignment error) and max over the head / face points of their
  exact distance to the GT surface, on at most ``samples`` points (a fixed random subset, the same
  in every frame), a mean over points rather than over area; ``*_camera_mm`` in camera space,
  the others after the rigid ICP alignment of the face points to the GT face samples (the mesh
  protocol's alignment with the points as its source), ``hausdorff_full_outer_mm`` aligned to the
  GT's outer surface, ``*_scaled_mm`` after the similarity alignment of the same face points.
- normal consistency: as for meshes, mean ``|cos|`` between nearest neighbours, both directions,
  of the aligned head points (at most 4000, with their normals turned by the alignment) and the
  GT (its closest surface points; the seen head's samples); a mesh contributes 4000 area samples
  of its head with their face normals. Until 2026-12-06 the second direction was missing (the GT
  side was only the closest points to the prediction's, matched back to them), so a prediction
  that left part of the seen head out was not charged for it. ``|cos|`` ignores orientation: a
  point set with every normal flipped keeps its consistency; the normal error catches it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from safetensors.numpy import load_file
from scipy.spatial import cKDTree

from headforge.errors import HeadforgeError
from headforge.paths import make_folder
from headforge.metrics.geometry import directed_normal_consistency, normal_angle_error, one_sided_hausdorff, points_to_mesh


@dataclass
class PredictedGeometry:
    """A mesh (``faces`` set) or a point set (``faces`` None; ``vertices`` are the points)."""

    frames: np.ndarray  # (N,) frame indices
    vertices: np.ndarray  # (N, V, 3) camera space, metres: mesh vertices or points
    faces: np.ndarray | None  # (F, 3); None for a point set
    face_vertices: np.ndarray | None  # (V,) bool; for a point set its face_points, or None (regions from the GT labels)
    head_vertices: np.ndarray | None  # (V,) bool: the full head (neck excluded); a point set's head_points or None
    source: str
    normals: np.ndarray | None = None  # (N, V, 3) unit point normals of a point set
    radius: np.ndarray | None = None  # (N, V) world-space point radii (metres) of a point set
    surfel_min_cos: float = 0.0  # > 0: the point set is drawn as surfels (render.points.splat's min_cos)
    hole_filling: bool = False  # the point set's renders close the holes between splats (render.points.close_holes)

    @property
    def is_points(self) -> bool:
        return self.faces is None

    @property
    def kind(self) -> str:
        return "points" if self.is_points else "mesh"


def scored_regions(regions, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(face, head) (num_vertices,) bool masks of a head model's vertices that the geometry
    metrics score: its ``face`` region, and every vertex outside its neck regions (``neck``,
    ``lower_neck``). ``regions``: {name: vertex ids} (``HeadModelData.regions``)."""
    face = np.zeros(num_vertices, bool)
    face[np.asarray(regions["face"])] = True
    head = np.ones(num_vertices, bool)
    for region in ("neck", "lower_neck"):
        if region in regions:
            head[np.asarray(regions[region])] = False
    return face, head


def tracked_geometry(dataset: str | Path, frames: np.ndarray) -> PredictedGeometry:
    """The tracked head model of a ``headforge track`` dataset at ``frames`` (camera space)."""
    from headforge.data.dataset import load_tracking, read_meta
    from headforge.head import load_data
    from headforge.head.model import HeadModel
    from headforge.head.pose import FRAME_KEYS, head_to_camera

    dataset = Path(dataset)
    meta = read_meta(dataset)
    tracked = load_tracking(dataset, meta)
    data = load_data(meta["model"], None) if meta["model"] == "open-head" else load_data("flame", None)
    head = HeadModel(data)
    T = tracked["translation"].shape[0]
    if frames.max() >= T:
        raise HeadforgeError(f"{dataset} has {T} frames, the ground truth asks for frame {int(frames.max())}")
    idx = torch.from_numpy(frames)
    with torch.no_grad():
        out = head(shape=tracked["shape"].expand(len(frames), -1), **{k: tracked[k][idx] for k in FRAME_KEYS[:-1]})
        verts = head_to_camera(out.vertices, tracked["translation"][idx])
    face, head_mask = scored_regions(data.regions, verts.shape[1])
    return PredictedGeometry(frames, verts.numpy(), data.faces, face, head_mask, f"tracked {meta['model']} ({dataset})")


def exported_geometry(folder: str | Path) -> PredictedGeometry:
    path = Path(folder) / "geometry.safetensors"
    if not path.is_file():
        raise HeadforgeError(f"{folder} has neither tracking.safetensors nor geometry.safetensors")
    arrays = _load_arrays(path, ("frames",))
    if "points" in arrays and "vertices" not in arrays:
        return _point_geometry(path, arrays, str(folder))
    if "vertices" not in arrays:
        raise HeadforgeError(f"{path} lacks 'vertices' (a mesh) or 'points' (a point set)")
    g = _require(path, arrays, ("vertices", "faces", "face_vertices", "head_vertices"))
    N, V = len(g["frames"]), g["vertices"].shape[1] if g["vertices"].ndim == 3 else -1
    if g["vertices"].shape != (N, V, 3) or g["faces"].ndim != 2 or g["faces"].shape[1:] != (3,):
        raise HeadforgeError(f"{path}: vertices {g['vertices'].shape} and faces {g['faces'].shape} are not "
                             f"(frames={N}, V, 3) and (F, 3)")
    if len(g["faces"]) and not 0 <= g["faces"].min() <= g["faces"].max() < V:
        raise HeadforgeError(f"{path}: faces index vertices outside 0..{V - 1}")
    if g["face_vertices"].shape != (V,) or g["head_vertices"].shape != (V,):
        raise HeadforgeError(f"{path}: face_vertices / head_vertices must be ({V},) vertex masks")
    return PredictedGeometry(g["frames"], g["vertices"], g["faces"], g["face_vertices"].astype(bool),
                             g["head_vertices"].astype(bool), str(folder))


def _load_arrays(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """A safetensors file's arrays; a one-line error when it is unreadable or lacks a key."""
    try:
        arrays = load_file(str(path))
    except Exception as exc:  # SafetensorError, OSError, ...
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise HeadforgeError(f"{path} is unreadable (truncated or not safetensors: {reason})") from None
    return _require(path, arrays, keys)


def _require(path: Path, arrays: dict[str, np.ndarray], keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    missing = [key for key in keys if key not in arrays]
    if missing:
        raise HeadforgeError(f"{path} lacks {', '.join(repr(k) for k in missing)}")
    return arrays


POINT_KEYS = ("frames", "points", "normals", "radius")


def _point_geometry(path: Path, arrays: dict[str, np.ndarray], source: str) -> PredictedGeometry:
    """A point-set prediction from ``geometry.safetensors``'s arrays, its shapes and values checked."""
    g = _require(path, arrays, POINT_KEYS)
    frames, points, normals, radius = (g[k] for k in POINT_KEYS)
    N = len(frames) if frames.ndim == 1 else -1
    P = points.shape[1] if points.ndim == 3 else -1
    if (frames.ndim != 1 or points.shape != (N, P, 3) or P < 1 or normals.shape != (N, P, 3)
            or radius.shape != (N, P)):
        raise HeadforgeError(f"{path}: frames {frames.shape}, points {points.shape}, normals {normals.shape} and "
                             f"radius {radius.shape} are not (T,), (T, P, 3), (T, P, 3) and (T, P) with P >= 1")
    if not np.issubdtype(frames.dtype, np.integer):
        raise HeadforgeError(f"{path}: frames must be integer frame indices, got {frames.dtype}")
    points, normals, radius = (np.asarray(a, np.float32) for a in (points, normals, radius))
    if not (np.isfinite(points).all() and np.isfinite(normals).all() and np.isfinite(radius).all()):
        raise HeadforgeError(f"{path}: points, normals and radius must be finite")
    if (radius <= 0).any():
        raise HeadforgeError(f"{path}: radius must be positive (metres), min {float(radius.min()):g}")
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    if (length < 1e-6).any():
        raise HeadforgeError(f"{path}: {int((length < 1e-6).sum())} normals have zero length")
    face = head = None
    if "face_points" in arrays or "head_points" in arrays:
        g = _require(path, arrays, ("face_points", "head_points"))
        if g["face_points"].shape != (P,) or g["head_points"].shape != (P,):
            raise HeadforgeError(f"{path}: face_points / head_points must be ({P},) point masks")
        face, head = g["face_points"].astype(bool), g["head_points"].astype(bool)
    min_cos = 0.0
    if "surfel_min_cos" in arrays:
        value = np.asarray(arrays["surfel_min_cos"], np.float64).ravel()
        if value.shape != (1,) or not 0 < value[0] <= 1:
            raise HeadforgeError(f"{path}: surfel_min_cos must be one value in (0, 1], got {value}")
        min_cos = float(value[0])
    fill = False
    if "hole_filling" in arrays:
        value = np.asarray(arrays["hole_filling"]).ravel()
        if value.shape != (1,) or value[0] not in (0, 1):
            raise HeadforgeError(f"{path}: hole_filling must be one value, 0 or 1, got {value}")
        fill = bool(value[0])
    return PredictedGeometry(frames.astype(np.int64), points, None, face, head, source,
                             normals=normals / length, radius=radius, surfel_min_cos=min_cos, hole_filling=fill)


SUBJECT_KEYS = ("train_frames", "intrinsics", "resolution", "labels", "head_labels", "subject")


def _read_png(path: Path, flags) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), flags)
    if image is None:
        raise HeadforgeError(f"ground-truth file missing or unreadable: {path}")
    return image


def load_subject_gt(subject: Path) -> tuple[dict, dict]:
    """A ``headforge synth`` subject's ground truth: the arrays of gt/geometry.safetensors
    (camera-space ``vertices`` (N, V, 3) of GT ``frames`` (N,), ``faces``, vertex ``labels``) and
    gt/subject.json (camera, resolution, splits, label ids)."""
    gt_path, info_path = subject / "gt" / "geometry.safetensors", subject / "gt" / "subject.json"
    if not gt_path.is_file() or not info_path.is_file():
        raise HeadforgeError(f"{subject} is not a headforge synth subject (gt/geometry.safetensors or gt/subject.json missing)")
    gt = _load_arrays(gt_path, ("frames", "vertices", "faces", "labels"))
    if len(gt["faces"]) == 0:
        raise HeadforgeError(f"{gt_path}: the ground-truth mesh has no faces")
    if gt["vertices"].ndim != 3 or len(gt["vertices"]) != len(gt["frames"]) or len(gt["labels"]) != gt["vertices"].shape[1]:
        raise HeadforgeError(f"{gt_path}: vertices {gt['vertices'].shape}, frames {gt['frames'].shape} and labels "
                             f"{gt['labels'].shape} do not agree")
    try:
        info = json.loads(info_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise HeadforgeError(f"{info_path} is not valid JSON: {exc}") from None
    missing = [key for key in SUBJECT_KEYS if key not in info]
    if missing:
        raise HeadforgeError(f"{info_path} lacks {', '.join(repr(k) for k in missing)}")
    return gt, info


def prediction_rows(prediction: PredictedGeometry, frames: np.ndarray, source: Path) -> np.ndarray:
    """(len(frames),) the row of each GT frame in ``prediction``; an error names a missing one."""
    lookup = {int(f): i for i, f in enumerate(prediction.frames)}
    missing = [int(f) for f in frames if int(f) not in lookup]
    if missing:
        raise HeadforgeError(f"{source} has no geometry for {len(missing)} ground-truth frames, e.g. frame {missing[0]}")
    return np.array([lookup[int(f)] for f in frames], dtype=np.int64)


def load_prediction(pred: Path, frames: np.ndarray) -> PredictedGeometry:
    """A tracked dataset's head model at ``frames``, or a folder's exported geometry (a mesh or
    a point set)."""
    return tracked_geometry(pred, frames) if (pred / "tracking.safetensors").is_file() else exported_geometry(pred)


def read_gt_maps(subject: Path, frame: int, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """A synth subject's GT maps of ``frame``: (R, R, 3) camera-space normals (as stored, unit
    length where covered, 0 elsewhere) and (R, R) uint8 segmentation labels."""
    name = f"{frame:05d}.png"
    normals = _read_png(subject / "gt" / "normals" / name, -1)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise HeadforgeError(f"{subject / 'gt' / 'normals' / name} is not an RGB normal map")
    normals = normals[..., ::-1].astype(np.float32) / 255 * 2 - 1
    labels = _read_png(subject / "gt" / "labels" / name, 0)
    if normals.shape[:2] != (resolution, resolution) or labels.shape != (resolution, resolution):
        raise HeadforgeError(f"{subject / 'gt' / 'normals' / name} does not match the resolution {resolution}")
    return normals, labels


def render_normals(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, resolution: int) -> np.ndarray:
    """(R, R, 3) camera-space unit normals of a camera-space mesh, zero where empty."""
    from headforge.head.topology import vertex_normals
    from headforge.render import mesh
    from headforge.render.camera import Cameras

    v = torch.from_numpy(np.asarray(vertices, np.float32))[None]
    f = torch.from_numpy(np.asarray(faces, np.int64))
    cams = Cameras.at_origin(torch.from_numpy(np.asarray(K, np.float32)), 1, resolution)
    frags = mesh.rasterize(cams, v, f)
    n = torch.nn.functional.normalize(mesh.interpolate(vertex_normals(v, f), frags, f), dim=-1)
    return torch.where(frags.mask[..., None], n, torch.zeros(3))[0].numpy()


def splat_normals(points: np.ndarray, normals: np.ndarray, radius: np.ndarray, K: np.ndarray,
                  resolution: int, k: int = 8, surfel_min_cos: float = 0.0, hole_filling: bool = False) -> np.ndarray:
    """(R, R, 3) camera-space unit normals of a camera-space point set (P, 3) with normals (P, 3)
    and world radii (P,) metres, zero where empty: discs of ``fx * radius / depth`` pixels (or
    surfels of that radius when ``surfel_min_cos`` > 0, as the avatar drew them), the ``k``
    nearest in depth composited front to back, renormalised, kept where the accumulated alpha
    exceeds 0.5 (the point-set counterpart of :func:`render_normals`); with ``hole_filling`` (an
    avatar whose renders fill the holes between splats) the covered pixels are closed and each
    added pixel takes the mean normal of its covered neighbours (:func:`close_holes`)."""
    from headforge.render.camera import Cameras
    from headforge.render.points import close_holes, splat

    p = torch.from_numpy(np.asarray(points, np.float32))[None]
    n = torch.from_numpy(np.asarray(normals, np.float32))[None]
    r_px = float(K[0, 0]) * torch.from_numpy(np.asarray(radius, np.float32))[None] / p[..., 2].clamp(min=1e-3)
    cams = Cameras.at_origin(torch.from_numpy(np.asarray(K, np.float32)), 1, resolution)
    surfels = {"normals": n, "min_cos": surfel_min_cos} if surfel_min_cos > 0 else {}
    image = splat(cams, p, n, r_px, K=k, **surfels)
    out = torch.nn.functional.normalize(image.features, dim=-1)
    covered = image.mask > 0.5
    if hole_filling:
        out, covered = close_holes(out, covered)
        out = torch.nn.functional.normalize(out, dim=-1)
    return torch.where(covered[..., None], out, torch.zeros(3))[0].numpy()


def prediction_normals(prediction: PredictedGeometry, row: int, K: np.ndarray, resolution: int) -> np.ndarray:
    """(R, R, 3) normal map of ``prediction``'s row ``row``: rasterized for a mesh, splatted for
    a point set; zero where it does not cover."""
    if prediction.is_points:
        return splat_normals(prediction.vertices[row], prediction.normals[row], prediction.radius[row], K, resolution,
                             surfel_min_cos=prediction.surfel_min_cos, hole_filling=prediction.hole_filling)
    return render_normals(prediction.vertices[row], prediction.faces, K, resolution)


def _icp_to_face(source: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                 gt_face_vertices: np.ndarray, centre: bool = False) -> np.ndarray:
    """(4, 4) rigid ICP transform (point-to-point) taking the points ``source`` onto dense
    samples of the GT face surface, started from the identity; ``centre``: also from the
    translation that puts the source's centroid on the GT face's, keeping the lower final cost."""
    gt_face = trimesh.Trimesh(gt_verts, gt_faces[gt_face_vertices[gt_faces].all(1)], process=False)
    target, _ = trimesh.sample.sample_surface(gt_face, 30_000, seed=1)
    source = np.asarray(source, np.float64)
    starts = [np.eye(4)]
    if centre:
        starts.append(np.eye(4))
        starts[1][:3, 3] = target.mean(0) - source.mean(0)
    fits = [trimesh.registration.icp(source, target, initial=s, max_iterations=40, scale=False) for s in starts]
    return min(fits, key=lambda fit: fit[2])[0]


def similarity_to_face(source: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray, gt_skin_vertices: np.ndarray,
                       initial: np.ndarray, iterations: int = 300, trim: float = 0.9) -> np.ndarray:
    """(4, 4) similarity transform (rotation, translation and one scale factor: NoW's "rigid
    alignment (rotation, translation, and scaling)") taking the prediction's face points
    ``source`` (S, 3) onto the GT skin, refined from ``initial`` (the rigid face alignment).

    A monocular clip fixes a head only up to a scale about the camera (a head s times larger, s
    times farther, gives the same images), so a tracked head of the average size sits larger
    and farther than a small subject's. Point-to-point ICP with a free scale, each face point
    paired with its nearest of 60,000 samples of the GT head's skin (``gt_skin_vertices`` (V,)
    bool: the head without the hair, whose fringe would otherwise take the forehead), the farthest
    ``1 - trim`` of the pairs dropped, Umeyama's least squares on the rest. The target is the
    whole skin, not the GT face region, because the prediction's face region never matches the
    GT's: onto the face alone, a free scale shrinks the source into it (0.85 on a tracked head
    that is 0.97 here). On a point set sampled on the GT it finds 1.000 ± 0.002; stops
    when an iteration moves the transform by less than 1e-7 (point-to-point ICP creeps along the
    scale: ~100 iterations)."""
    skin = trimesh.Trimesh(gt_verts, gt_faces[gt_skin_vertices[gt_faces].all(1)], process=False)
    target, _ = trimesh.sample.sample_surface(skin, 60_000, seed=1)
    source = np.asarray(source, np.float64)
    tree = cKDTree(target)
    matrix = np.asarray(initial, np.float64)
    for _ in range(iterations):
        distance, nearest = tree.query(_moved(source, matrix))
        keep = distance <= np.quantile(distance, trim)
        previous = matrix
        matrix = trimesh.registration.procrustes(source[keep], target[nearest[keep]], reflection=False, scale=True,
                                                 return_cost=False)
        if np.abs(matrix - previous).max() < 1e-7:
            break
    return matrix


def transform_scale(matrix: np.ndarray) -> float:
    """The uniform scale factor of a (4, 4) similarity transform."""
    return float(np.cbrt(np.linalg.det(matrix[:3, :3])))


def _face_samples(verts: np.ndarray, pred_face_faces: np.ndarray) -> np.ndarray:
    """(5000, 3) area-uniform samples of the predicted face surface (fixed seed)."""
    return trimesh.sample.sample_surface(trimesh.Trimesh(verts, pred_face_faces, process=False), 5000, seed=2)[0]


def _moved(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def align_face(verts: np.ndarray, pred_face_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                gt_face_vertices: np.ndarray) -> np.ndarray:
    """``verts`` moved by the rigid ICP transform that aligns the predicted face surface to the
    GT face surface (point-to-point on dense samples)."""
    matrix = _icp_to_face(_face_samples(verts, pred_face_faces), gt_verts, gt_faces, gt_face_vertices)
    return _moved(verts, matrix)


def _face_subset(face_points: np.ndarray) -> np.ndarray:
    """At most 5000 of a point set's face points, a fixed random subset."""
    if len(face_points) > 5000:
        face_points = face_points[np.random.default_rng(2).choice(len(face_points), 5000, replace=False)]
    return face_points


def gt_point_labels(points: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                    gt_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each point's closest GT surface point (P, 3), its distance (P,), the closest triangle (P,)
    and the GT label there (P,): the label of that triangle's vertex nearest the closest point."""
    mesh = trimesh.Trimesh(gt_verts, gt_faces, process=False)
    closest, distance, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))
    corners = gt_faces[tri]
    nearest = np.linalg.norm(gt_verts[corners] - closest[:, None], axis=-1).argmin(1)
    return closest, distance, tri, gt_labels[corners[np.arange(len(tri)), nearest]]


def turntable_views(gt_vertices: np.ndarray, gt_faces: np.ndarray, pred_vertices: np.ndarray,
                    pred_faces: np.ndarray | None, K: np.ndarray, resolution: int,
                    yaws_deg: tuple[float, ...] = (0.0, 60.0, 90.0, 150.0), pred_normals: np.ndarray | None = None,
                    pred_radius: np.ndarray | None = None, pred_surfel_min_cos: float = 0.0,
                    pred_hole_filling: bool = False) -> np.ndarray:
    """(2R, len(yaws) R, 3) normal-map picture in [0, 1]: the GT mesh (top row) and the
    prediction (bottom row), both camera space in metres, turned by the same ``yaws_deg`` about
    the camera's vertical axis through the GT mesh's centroid. The frontal error map shows only
    what the camera saw; these views show the top and back, which a monocular clip rarely does.
    A point-set prediction: ``pred_faces`` None, its ``pred_normals`` and ``pred_radius`` given
    (and ``pred_surfel_min_cos`` when it is drawn as surfels, ``pred_hole_filling`` when its renders
    fill holes)."""
    pivot = np.asarray(gt_vertices, np.float64).mean(0)
    rows = []
    for verts, faces, normals in ((gt_vertices, gt_faces, None), (pred_vertices, pred_faces, pred_normals)):
        centred = np.asarray(verts, np.float64) - pivot
        tiles = []
        for yaw in np.radians(yaws_deg):
            c, s = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            if faces is None:
                n = splat_normals(centred @ R.T + pivot, normals @ R.T, pred_radius, K, resolution,
                                  surfel_min_cos=pred_surfel_min_cos, hole_filling=pred_hole_filling)
            else:
                n = render_normals(centred @ R.T + pivot, faces, K, resolution)
            tiles.append(np.where(np.linalg.norm(n, axis=-1, keepdims=True) > 0.5, 0.5 * (n + 1), 0.5))
        rows.append(np.concatenate(tiles, 1))
    return np.concatenate(rows, 0)


def outer_surface_faces(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, hair_label: int) -> np.ndarray:
    """(F,) bool: the faces of a GT mesh (body + closed hair volume, vertex ``labels`` (V,))
    that are on its outer surface, i.e. not a body face inside the hair volume and not a hair
    face under the skin (signed distance to the body surface < 0, its face normals outward).
    Without hair faces every face is outer; a hair mesh that is not watertight keeps the body
    faces under it (inside-ness is undefined)."""
    hair = (labels[faces] == hair_label).all(1)
    keep = np.ones(len(faces), bool)
    if not hair.any() or hair.all():
        return keep
    centres = vertices[faces].mean(1).astype(np.float64)
    hair_mesh = trimesh.Trimesh(vertices, faces[hair], process=False)
    body_mesh = trimesh.Trimesh(vertices, faces[~hair], process=False)
    body_idx, hair_idx = np.nonzero(~hair)[0], np.nonzero(hair)[0]
    if hair_mesh.is_watertight:
        keep[body_idx[hair_mesh.contains(centres[body_idx])]] = False
    closest, _, tri = trimesh.proximity.closest_point(body_mesh, centres[hair_idx])
    side = ((centres[hair_idx] - closest) * body_mesh.face_normals[tri]).sum(1)
    keep[hair_idx[side < 0]] = False
    return keep


def _faces_in(faces: np.ndarray, vertex_mask: np.ndarray) -> np.ndarray:
    return vertex_mask[faces].all(1)


def _rendered(normals: np.ndarray) -> np.ndarray:
    """(R, R) bool: the pixels a normal map from :func:`render_normals` covers."""
    return np.linalg.norm(normals, axis=-1) > 0.5


def _angle_map_deg(pred_n: np.ndarray, gt_n: np.ndarray) -> np.ndarray:
    """(R, R) per-pixel angle (degrees) between a rendered (R, R, 3) unit normal map and the GT's
    (8-bit, so renormalised)."""
    cos = (pred_n * gt_n).sum(-1) / np.maximum(np.linalg.norm(gt_n, axis=-1), 1e-6)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _normal_errors(pred_n: np.ndarray, gt_n: np.ndarray, head_px: np.ndarray, face_px: np.ndarray) -> tuple[float, float]:
    """Mean normal angle error (degrees) of a rendered (R, R, 3) map against the GT map over the
    (R, R) bool ``head_px`` and ``face_px`` masks, in that order."""
    pn, gn = torch.from_numpy(pred_n)[None], torch.from_numpy(gt_n.copy())[None]
    head, face = (float(normal_angle_error(pn, gn, torch.from_numpy(m)[None])[0]) for m in (head_px, face_px))
    return head, face


def split_rows(gt: dict, info: dict, subject: Path, split: str, every: int) -> tuple[np.ndarray, int]:
    """The rows of ``gt`` (every ``every``-th GT frame of ``split``: val, train or all) and how
    many GT frames the split has."""
    train = info["train_frames"]
    split_mask = {"val": gt["frames"] >= train, "train": gt["frames"] < train, "all": np.ones(len(gt["frames"]), bool)}
    if split not in split_mask:
        raise HeadforgeError(f"split must be val, train or all, got {split!r}")
    rows = np.nonzero(split_mask[split])[0][::every]
    if len(rows) == 0:
        raise HeadforgeError(f"{subject} has no ground-truth frames in split {split!r}")
    return rows, int(split_mask[split].sum())


def paired_normal_error(pred: str | Path, reference: str | Path, subject: str | Path, split: str = "val",
                        every: int = 1) -> dict:
    """Normal angle error (degrees) of ``pred`` and of ``reference`` (each a tracked dataset or
    exported geometry, a mesh or a point set, as for :func:`evaluate_geometry`) on the same pixels: the GT full-head
    (face) pixels that *both* predictions cover, per GT frame of ``split``, then the mean over
    frames. :func:`evaluate_geometry` charges each prediction only on the pixels it covers
    itself, so a bald head model that leaves the hair uncovered is scored on the skin alone while
    an avatar with hair is scored on the hair too; this is the like-for-like comparison.

    Returns ``{"frames": N, "mean": {...}, "per_frame": [...]}`` with ``normal_error_head_deg``,
    ``normal_error_face_deg``, ``reference_normal_error_head_deg``,
    ``reference_normal_error_face_deg``, ``common_coverage`` (fraction of the GT full-head
    pixels both cover) and ``coverage`` / ``reference_coverage`` (the fraction each covers: its
    ``head_coverage``)."""
    subject = Path(subject)
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, split, every)
    frames = gt["frames"][rows]
    sources = {"": Path(pred), "reference_": Path(reference)}
    predictions = {key: load_prediction(path, frames) for key, path in sources.items()}
    lookups = {key: prediction_rows(predictions[key], frames, path) for key, path in sources.items()}
    K, res = np.asarray(info["intrinsics"]), int(info["resolution"])
    per_frame = []
    for j, f in enumerate(frames):
        gt_n, labels = read_gt_maps(subject, int(f), res)
        gt_head = np.isin(labels, np.array(info["head_labels"]))
        normals = {key: prediction_normals(p, lookups[key][j], K, res) for key, p in predictions.items()}
        common = gt_head & np.logical_and.reduce([_rendered(n) for n in normals.values()])
        face = common & (labels == info["labels"]["face"])
        if not face.any():
            raise HeadforgeError(f"frame {int(f)}: the two predictions cover none of the ground-truth face in common")
        row = {"frame": int(f), "common_coverage": float(common.sum() / gt_head.sum())}
        for key, n in normals.items():
            row[f"{key}coverage"] = float((_rendered(n) & gt_head).sum() / gt_head.sum())
        for key, n in normals.items():
            row[f"{key}normal_error_head_deg"], row[f"{key}normal_error_face_deg"] = _normal_errors(n, gt_n, common, face)
        per_frame.append(row)
    keys = [k for k in per_frame[0] if k != "frame"]
    return {"frames": len(per_frame), "mean": {k: float(np.mean([r[k] for r in per_frame])) for k in keys},
            "per_frame": per_frame}


def normal_error_by_label(pred: str | Path | None, subject: str | Path, split: str = "val",
                          every: int = 1) -> dict[str, dict[str, float]]:
    """The full-head normal error of ``pred`` (a tracked dataset or exported geometry, mesh or points, as for
    :func:`evaluate_geometry`; None scores the GT meshes themselves, the floor the renderer and
    the 8-bit normal maps leave) split by GT label, the pixels pooled over every ``every``-th GT
    frame of ``split``. Per label name of the GT's full head: ``deg`` (mean angle error on the
    covered pixels), ``covered`` (fraction of the label's GT pixels the prediction covers) and
    ``share`` (the label's share of the prediction's covered full-head pixels; so
    ``sum(share * deg)`` is the pixel-pooled full-head error, which :func:`evaluate_geometry`
    averages per frame instead)."""
    subject = Path(subject)
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, split, every)
    frames = gt["frames"][rows]
    if pred is None:
        prediction = PredictedGeometry(gt["frames"], gt["vertices"], gt["faces"], None, None, "ground truth")
        lookup = rows
    else:
        prediction = load_prediction(Path(pred), frames)
        lookup = prediction_rows(prediction, frames, Path(pred))
    K, res = np.asarray(info["intrinsics"]), int(info["resolution"])
    names = {value: name for name, value in info["labels"].items()}
    sums = {label: np.zeros(3) for label in info["head_labels"]}  # error sum, covered px, GT px
    for j, frame in enumerate(frames):
        gt_n, labels = read_gt_maps(subject, int(frame), res)
        pred_n = prediction_normals(prediction, lookup[j], K, res)
        covered = _rendered(pred_n)
        err = _angle_map_deg(pred_n, gt_n)
        for label in sums:
            gt_px = labels == label
            hit = gt_px & covered
            sums[label] += (err[hit].sum(), hit.sum(), gt_px.sum())
    total = max(sum(s[1] for s in sums.values()), 1)
    return {names[label]: {"deg": float(s[0] / max(s[1], 1)), "covered": float(s[1] / max(s[2], 1)),
                           "share": float(s[1] / total)} for label, s in sums.items()}


def sample_gt_head(gt: dict, info: dict, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """``n`` area-uniform samples of the GT head's outer surface (neck, body, the scalp under the
    hair and the hair's inner shell left out), the same surface points in every GT frame:
    points (T, n, 3), their smooth normals (the interpolated vertex normals the GT normal maps
    show), the sample spacing sqrt(area / n) in metres, and the head faces sampled."""
    from headforge.geometry import vertex_normals

    V, F, L = gt["vertices"], gt["faces"], gt["labels"]
    head = np.isin(L, info["head_labels"])
    outer = outer_surface_faces(V[0], F, L, info["labels"]["hair"])
    faces = F[head[F].all(1) & outer]
    tri = V[0][faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    fid = rng.choice(len(faces), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    bary = np.stack([1 - u - v, u, v], 1)[None, :, :, None]
    vn = vertex_normals(torch.from_numpy(V.astype(np.float32)), torch.from_numpy(F.astype(np.int64))).numpy()
    points = (V[:, faces[fid]] * bary).sum(2)
    normals = (vn[:, faces[fid]] * bary).sum(2)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    # contiguous copies: safetensors' numpy writer would write these strided sums scrambled
    return (np.ascontiguousarray(points, np.float32), np.ascontiguousarray(normals, np.float32),
            float(np.sqrt(area.sum() / n)), faces)


def seen_gt_samples(gt_verts: np.ndarray, gt_faces: np.ndarray, head_faces: np.ndarray, K: np.ndarray,
                    resolution: int, n: int = 10_000) -> tuple[np.ndarray, np.ndarray]:
    """``n`` area-uniform samples (fixed seed) of the GT head surface the frame's camera sees: the
    faces among ``head_faces`` (F,) bool that cover a pixel of the GT mesh's z-buffer (the whole
    mesh occludes, body and hair included), with their face normals; (n, 3) each."""
    from headforge.render import mesh
    from headforge.render.camera import Cameras

    v = torch.from_numpy(np.asarray(gt_verts, np.float32))[None]
    cams = Cameras.at_origin(torch.from_numpy(np.asarray(K, np.float32)), 1, resolution)
    ids = mesh.rasterize(cams, v, torch.from_numpy(np.asarray(gt_faces, np.int64))).face_id.unique().numpy()
    seen = np.zeros(len(gt_faces), bool)
    seen[ids[ids >= 0]] = True
    seen &= head_faces
    if not seen.any():
        raise HeadforgeError("the camera sees none of the ground-truth head")
    gm = trimesh.Trimesh(gt_verts, gt_faces[seen], process=False)
    points, fid = trimesh.sample.sample_surface(gm, n, seed=0)
    return np.asarray(points), gm.face_normals[fid]


def _mesh_distances(prediction: PredictedGeometry, verts: np.ndarray, gv: np.ndarray, gf: np.ndarray,
                    gt_labels: np.ndarray, labels_face: int, outer: np.ndarray, skin: np.ndarray, samples: int,
                    face_sel: np.ndarray, head_sel: np.ndarray,
                    seen: tuple[np.ndarray, np.ndarray]) -> tuple[dict, np.ndarray]:
    """A mesh prediction's distance figures (mm) and normal consistency on one frame, and its
    aligned vertices. ``outer``: the GT's outer faces; ``skin``: its head vertices without the
    hair; ``seen``: :func:`seen_gt_samples` of the frame."""
    faces = prediction.faces
    cam_full = one_sided_hausdorff(verts, faces, gv, gf, samples=samples, region_mask=head_sel)
    cam_face = one_sided_hausdorff(verts, faces, gv, gf, samples=samples, region_mask=face_sel)
    source = _face_samples(verts, faces[face_sel])
    rigid = _icp_to_face(source, gv, gf, gt_labels == labels_face)
    aligned = _moved(verts, rigid)
    full = one_sided_hausdorff(aligned, faces, gv, gf, samples=samples, region_mask=head_sel)
    face = one_sided_hausdorff(aligned, faces, gv, gf, samples=samples, region_mask=face_sel)
    similar = similarity_to_face(source, gv, gf, skin, rigid)
    scaled = _moved(verts, similar)
    full_s = one_sided_hausdorff(scaled, faces, gv, gf, samples=samples, region_mask=head_sel)
    face_s = one_sided_hausdorff(scaled, faces, gv, gf, samples=samples, region_mask=face_sel)
    full_outer = one_sided_hausdorff(aligned, faces, gv, gf[outer], samples=samples, region_mask=head_sel)
    gm = trimesh.Trimesh(gv, gf, process=False)
    nc, nc_s = (_surface_consistency(trimesh.Trimesh(v, faces[head_sel], process=False), gm, seen) for v in (aligned, scaled))
    return (_distance_row(full, face, cam_full, cam_face, full_outer, nc) | _scaled_row(full_s, face_s, similar, nc_s),
            aligned)


def _surface_consistency(pm: trimesh.Trimesh, gm: trimesh.Trimesh, seen: tuple[np.ndarray, np.ndarray]) -> float:
    """Normal consistency of 4000 area samples of the prediction's head ``pm`` (fixed seed, face
    normals) with the GT ``gm`` and its seen head's samples ``seen`` (:func:`_points_consistency`)."""
    pts, fid = trimesh.sample.sample_surface(pm, 4000, seed=0)
    return _points_consistency(pts, pm.face_normals[fid], gm, seen)


def _points_consistency(points: np.ndarray, normals: np.ndarray, gm: trimesh.Trimesh,
                        seen: tuple[np.ndarray, np.ndarray]) -> float:
    """Normal consistency, both directions: the mean ``|cos|`` of each of ``points`` (P, 3) with
    ``normals`` against the GT face normal at its closest GT surface point (wherever on the GT it
    lies), and of each seen GT sample (:func:`seen_gt_samples`) against its nearest point's normal;
    the two means averaged."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    _, _, gfid = trimesh.proximity.closest_point(gm, np.asarray(points, np.float64))
    to_gt = np.abs((n * gm.face_normals[gfid]).sum(1)).mean()
    return float(0.5 * (to_gt + directed_normal_consistency(*seen, points, n)))


def _stats(d: np.ndarray) -> dict:
    return {"mean": float(d.mean()), "max": float(d.max())}


def _distance_row(full: dict, face: dict, cam_full: dict, cam_face: dict, full_outer: dict, nc: float) -> dict:
    return {"hausdorff_full_mm": 1000 * full["mean"], "hausdorff_face_mm": 1000 * face["mean"],
            "hausdorff_full_max_mm": 1000 * full["max"], "hausdorff_face_max_mm": 1000 * face["max"],
            "hausdorff_full_camera_mm": 1000 * cam_full["mean"], "hausdorff_face_camera_mm": 1000 * cam_face["mean"],
            "normal_consistency": nc, "hausdorff_full_outer_mm": 1000 * full_outer["mean"]}


def _scaled_row(full: dict, face: dict, similar: np.ndarray, nc: float) -> dict:
    return {"hausdorff_full_scaled_mm": 1000 * full["mean"], "hausdorff_face_scaled_mm": 1000 * face["mean"],
            "alignment_scale": transform_scale(similar), "normal_consistency_scaled": nc}


def _point_distances(points: np.ndarray, normals: np.ndarray, subset: np.ndarray, gv: np.ndarray, gf: np.ndarray,
                     gt_labels: np.ndarray, head_labels: np.ndarray, labels_face: int, outer: np.ndarray,
                     skin: np.ndarray, frame: int, seen: tuple[np.ndarray, np.ndarray],
                     regions: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[dict, np.ndarray, np.ndarray]:
    """A point set's distance figures (mm) and normal consistency on one frame (the definitions
    of the module docstring), and its aligned points and normals. ``seen``: the frame's
    :func:`seen_gt_samples`; ``regions``: the point set's own (face, head) masks (P,), else the GT
    labels decide."""
    scored = points[subset]
    _, distance, _, label = gt_point_labels(scored, gv, gf, gt_labels)
    if regions is None:
        head = np.isin(label, head_labels)
        face = head & (label == labels_face)
    else:
        head = regions[1][subset]
        face = head & regions[0][subset]
    if not face.any():
        raise HeadforgeError(f"frame {frame}: none of the prediction's scored points is a face point"
                             + (" (nearest the ground-truth face)" if regions is None else " (its face_points)"))
    face_source = _face_subset(scored[face])
    # the rigid ICP of align_face with the points as its source, also started from the centroids'
    # offset (a point avatar carries its tracking's depth error, centimetres, beyond 40 steps)
    matrix = _icp_to_face(face_source, gv, gf, gt_labels == labels_face, centre=True)
    R, t = matrix[:3, :3], matrix[:3, 3]
    aligned, aligned_n = points @ R.T + t, normals @ R.T
    head_pts = aligned[subset[head]]
    d_aligned = points_to_mesh(head_pts, gv, gf)
    similar = similarity_to_face(face_source, gv, gf, skin, matrix)
    scaled = _moved(points, similar)
    d_scaled = points_to_mesh(scaled[subset[head]], gv, gf)
    d_outer = points_to_mesh(head_pts, gv, gf[outer])
    nc_ids = subset[head][:4000]  # the subset is a random permutation: its first head points are a random draw
    gm = trimesh.Trimesh(gv, gf, process=False)
    nc = _points_consistency(aligned[nc_ids], aligned_n[nc_ids], gm, seen)
    nc_s = _points_consistency(scaled[nc_ids], normals[nc_ids] @ similar[:3, :3].T, gm, seen)  # |cos|: the scale cancels
    row = _distance_row(_stats(d_aligned), _stats(d_aligned[face[head]]), _stats(distance[head]),
                        _stats(distance[face]), _stats(d_outer), nc)
    row |= _scaled_row(_stats(d_scaled), _stats(d_scaled[face[head]]), similar, nc_s)
    return row | {"head_points": int(head.sum()), "face_points": int(face.sum())}, aligned, aligned_n


def evaluate_geometry(pred: str | Path, subject: str | Path, split: str = "val", samples: int = 10_000,
                      every: int = 1) -> dict:
    """Metrics of ``pred`` (tracked dataset or exported geometry, a mesh or a point set) against
    ``subject``'s gt/ (the definitions of the module docstring). ``samples``: area samples of a
    mesh, or scored points of a point set, per distance figure and frame."""
    subject, pred = Path(subject), Path(pred)
    gt, info = load_subject_gt(subject)
    rows, available = split_rows(gt, info, subject, split, every)
    frames = gt["frames"][rows]
    prediction = load_prediction(pred, frames)
    pred_rows = prediction_rows(prediction, frames, pred)
    K = np.asarray(info["intrinsics"])
    res = int(info["resolution"])
    labels_face = info["labels"]["face"]
    head_labels = np.array(info["head_labels"])
    if prediction.is_points:
        P = prediction.vertices.shape[1]
        subset = np.random.default_rng(0).permutation(P)[:samples]
    else:
        face_sel = _faces_in(prediction.faces, prediction.face_vertices)
        head_sel = _faces_in(prediction.faces, prediction.head_vertices)
    # a rest-like first frame decides which GT faces are outer (the hair rides on the head bone)
    outer = outer_surface_faces(gt["vertices"][rows[0]], gt["faces"], gt["labels"], info["labels"]["hair"])
    skin = np.isin(gt["labels"], head_labels) & (gt["labels"] != info["labels"]["hair"])
    gt_head_faces = np.isin(gt["labels"], head_labels)[gt["faces"]].all(1)
    per_frame, error_maps, views = [], [], None
    for row, f, i in zip(rows, frames, pred_rows):
        verts = prediction.vertices[i]
        gt_n, labels = read_gt_maps(subject, int(f), res)
        pred_n = prediction_normals(prediction, i, K, res)
        covered = _rendered(pred_n) & (labels > 0)
        face_px = covered & (labels == labels_face)
        gt_head_px = np.isin(labels, head_labels)
        head_px = covered & gt_head_px
        if not face_px.any() or not head_px.any():
            raise HeadforgeError(f"frame {int(f)}: the prediction covers none of the ground-truth face")
        nae_head, nae_face = _normal_errors(pred_n, gt_n, head_px, face_px)
        gv, gf = gt["vertices"][row], gt["faces"]
        seen = seen_gt_samples(gv, gf, gt_head_faces, K, res)
        if prediction.is_points:
            regions = None if prediction.face_vertices is None else (prediction.face_vertices, prediction.head_vertices)
            scores, aligned, aligned_n = _point_distances(verts, prediction.normals[i], subset, gv, gf, gt["labels"],
                                                          head_labels, labels_face, outer, skin, int(f),
                                                          seen, regions)
            if views is None:
                views = turntable_views(gv, gf, aligned, None, K, res, pred_normals=aligned_n,
                                        pred_radius=prediction.radius[i],
                                        pred_surfel_min_cos=prediction.surfel_min_cos,
                                        pred_hole_filling=prediction.hole_filling)
        else:
            scores, aligned = _mesh_distances(prediction, verts, gv, gf, gt["labels"], labels_face, outer, skin,
                                              samples, face_sel, head_sel, seen)
            if views is None:
                views = turntable_views(gv, gf, aligned, prediction.faces[head_sel], K, res)
        per_frame.append({"frame": int(f), "normal_error_face_deg": nae_face, "normal_error_head_deg": nae_head,
                          **scores, "head_coverage": float(head_px.sum() / gt_head_px.sum())})
        if len(error_maps) < 3:
            err = np.where(head_px, _angle_map_deg(pred_n, gt_n) / 45.0, 0)
            error_maps.append(np.concatenate([0.5 * (gt_n + 1), 0.5 * (pred_n + 1), np.repeat(err[..., None], 3, -1)], 1))
    keys = [k for k in per_frame[0] if k != "frame"]
    mean = {k: float(np.mean([r[k] for r in per_frame])) for k in keys}
    return {"prediction": prediction.source, "kind": prediction.kind, "subject": str(subject), "split": split,
            "frames": len(per_frame), "frames_available": available, "mean": mean, "per_frame": per_frame,
            "error_maps": error_maps, "views": views, "hair": info["subject"]["hair_style"]}


def write_geometry_report(result: dict, out_dir: Path) -> None:
    from headforge.render.io import write_png

    make_folder(out_dir)
    maps = result.pop("error_maps")
    views = result.pop("views", None)
    (out_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    lines = [f"Geometry of {result['prediction']} ({result.get('kind', 'mesh')}) against {result['subject']} ({result['split']} split): "
             f"{result['frames']} of {result['frames_available']} ground-truth frames.", "",
             "| metric | mean |", "| --- | --- |"]
    lines += [f"| {k} | {v:.3f} |" for k, v in result["mean"].items()]
    (out_dir / "metrics.md").write_text("\n".join(lines) + "\n")
    if maps:
        write_png(out_dir / "normal_error.png", np.clip(np.concatenate(maps, 0), 0, 1))
    if views is not None:
        write_png(out_dir / "views.png", np.clip(views, 0, 1))
