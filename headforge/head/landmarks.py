"""Landmarks: MediaPipe's 478-point face mesh embedded on a head model, and its iBUG-68 subset.

The embedding of `open-head` is learned by asking MediaPipe where the landmarks are on
renders of the model: a skin-like procedural shading (lips, brows, irises painted), several
identities, expressions and views; each detected landmark is back-projected by ray casting to
a (triangle, barycentric) pair, and per landmark the medoid of those surface points (in the
mean template) is kept.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np
import trimesh

from headforge.errors import HeadforgeError
from headforge.head.model import HeadModelData
from headforge.render.camera import PinholeCamera, look_at_head
from headforge.render.raycast import RayHits, cast, interpolate, raycast, shade_lambert

log = logging.getLogger(__name__)

N_MEDIAPIPE = 478

# MediaPipe face-mesh index of each of the 68 iBUG points (0-16 jaw, 17-26 brows, 27-35 nose,
# 36-47 eyes, 48-67 mouth). iBUG's "right" is the subject's right (image left when frontal).
MEDIAPIPE_TO_IBUG68 = np.array([
    162, 234, 93, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 323, 454, 389,
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300,
    168, 197, 5, 4, 75, 97, 2, 326, 305,
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181, 78, 82, 13, 312, 308, 317, 14, 87,
])
IBUG_JAW = np.arange(17)  # jaw-contour points: silhouette-dependent, often excluded

# Upper/lower eyelid pairs (MediaPipe ids) for NHA's eye-lid distance term; right eye first.
EYELID_PAIRS = np.array([[159, 145], [158, 153], [160, 144], [386, 374], [385, 380], [387, 373]])
# MediaPipe's face-oval loop, in order around the face from the top of the forehead.
FACE_OVAL_LOOP = (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 361, 288, 397, 365, 379, 378, 400, 377,
                  152, 148, 176, 149, 150, 136, 172, 58, 132, 93, 234, 127, 162, 21, 54, 103, 67, 109)
# Face-oval (silhouette) points of MediaPipe: excluded from "inner" error figures.
FACE_OVAL = np.array(sorted(FACE_OVAL_LOOP))
# MediaPipe's inner-lip contour as a closed loop (upper lip from the subject's right, then the lower back)
INNER_LIP_LOOP = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 324, 318, 402, 317, 14, 87, 178, 88, 95)

# iBUG-68 upper/lower eyelid pairs (right eye first), for models embedding iBUG-68 (FLAME).
IBUG_EYELID_PAIRS = np.array([[37, 41], [38, 40], [43, 47], [44, 46]])


@dataclass(frozen=True)
class LandmarkSpec:
    """How a model's embedded landmarks correspond to MediaPipe's 478 detections.

    detection_ids: (L,) MediaPipe index of each model landmark; contour: (L,) bool, points on
    the face silhouette (down-weighted, excluded from the headline error); eyelid_pairs: (P, 2)
    model-landmark indices of upper/lower lid points.
    """

    detection_ids: np.ndarray
    contour: np.ndarray
    eyelid_pairs: np.ndarray

    @classmethod
    def for_model(cls, n_landmarks: int) -> "LandmarkSpec":
        if n_landmarks == N_MEDIAPIPE:
            contour = np.zeros(N_MEDIAPIPE, bool)
            contour[FACE_OVAL] = True
            return cls(np.arange(N_MEDIAPIPE), contour, EYELID_PAIRS)
        if n_landmarks == 68:
            contour = np.zeros(68, bool)
            contour[IBUG_JAW] = True
            return cls(MEDIAPIPE_TO_IBUG68, contour, IBUG_EYELID_PAIRS)
        raise HeadforgeError(f"cannot track a model with {n_landmarks} landmarks: headforge tracks models that "
                             f"embed MediaPipe's {N_MEDIAPIPE} points or iBUG's 68 (FLAME's landmark_embedding.npy)")


SKIN = np.array([0.86, 0.66, 0.55])
LIPS = np.array([0.62, 0.28, 0.30])
BROW = np.array([0.22, 0.15, 0.11])
SCLERA = np.array([0.93, 0.92, 0.90])
IRIS = np.array([0.30, 0.20, 0.12])
PUPIL = np.array([0.03, 0.03, 0.03])
MOUTH = np.array([0.35, 0.10, 0.12])
LASH = np.array([0.25, 0.17, 0.15])


# ---- MediaPipe ---------------------------------------------------------------------------
_FACE_MESH = {}


def detect_mediapipe(image: np.ndarray, static: bool = True) -> np.ndarray | None:
    """478 MediaPipe landmarks of the largest face in ``image``.

    Args:
        image: (H, W, 3) uint8 RGB, or float in [0, 1].
    Returns:
        (478, 2) pixel coordinates (pixel centres at integers), or None when no face is found.
    """
    os.environ.setdefault("GLOG_minloglevel", "2")
    import mediapipe as mp

    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    key = static
    if key not in _FACE_MESH:
        _FACE_MESH[key] = mp.solutions.face_mesh.FaceMesh(
            static_image_mode=static, max_num_faces=1, refine_landmarks=True,
            min_detection_confidence=0.5)
    result = _FACE_MESH[key].process(np.ascontiguousarray(image[..., :3]))
    if not result.multi_face_landmarks:
        return None
    h, w = image.shape[:2]
    pts = np.array([(p.x, p.y) for p in result.multi_face_landmarks[0].landmark])
    return pts * np.array([w, h]) - 0.5


# ---- a render MediaPipe recognises -----------------------------------------------------
def _eye_centres(data: HeadModelData, vertices: np.ndarray) -> np.ndarray:
    return np.stack([vertices[data.regions["eyeball_left"]].mean(0),
                     vertices[data.regions["eyeball_right"]].mean(0)])


def paint_albedo(data: HeadModelData, hits: RayHits, canonical: np.ndarray) -> np.ndarray:
    """Per-pixel albedo (H, W, 3) from the canonical (mean-template) surface position.

    Painting in the canonical frame keeps brows, irises and lips attached to the same
    surface points whatever the identity, expression or view.
    """
    faces = data.faces
    V = len(data.v_template)
    onehot = lambda ids: np.isin(np.arange(V), ids).astype(np.float64)[:, None]  # noqa: E731
    lips = interpolate(hits, faces, onehot(data.regions["lips"]))[..., 0]
    mouth = interpolate(hits, faces, onehot(data.regions["mouth_interior"]))[..., 0]
    eyeball = interpolate(hits, faces, onehot(data.regions["eyeballs"]))[..., 0]
    cavity = interpolate(hits, faces, onehot(data.regions["eye_cavities"]))[..., 0]
    albedo = np.broadcast_to(SKIN, canonical.shape).copy()
    albedo = albedo * (1 - 0.1 * cavity[..., None])
    albedo = np.where((lips > 0.5)[..., None], LIPS, albedo)
    albedo = np.where((mouth > 0.5)[..., None], MOUTH, albedo)
    x, y, z = canonical[..., 0], canonical[..., 1], canonical[..., 2]
    eyes = _eye_centres(data, data.v_template)
    for ex, ey, ez in eyes:
        # Brows: an arch above each eye, on the front of the face.
        dx = (x - ex) * np.sign(ex)  # + toward the temple
        arch = ey + 0.018 + 0.004 * np.cos(np.clip(dx / 0.02, -1.6, 1.6)) - 0.006 * (dx > 0) * (dx / 0.02) ** 2
        brow = (np.abs(y - arch) < 0.0045 - 0.0015 * np.clip(dx / 0.02, 0, 1)) & (dx > -0.017) & (dx < 0.024) & (z > ez - 0.01)
        albedo = np.where((brow & (cavity < 0.5) & (eyeball < 0.5))[..., None], BROW, albedo)
        # Irises and pupils on the eyeball, around its forward (+z) axis.
        r = np.hypot(x - ex, y - ey)
        on_eye = (eyeball > 0.5) & (np.abs(x - ex) < 0.02)
        colour = np.where((r < 0.0055)[..., None], IRIS, SCLERA)
        colour = np.where((r < 0.0025)[..., None], PUPIL, colour)
        albedo = np.where(on_eye[..., None], colour, albedo)
    # A darker lash line where eyelid skin meets the eyeball.
    albedo = np.where(((cavity > 0.2) & (cavity < 0.8) & (eyeball < 0.5))[..., None], LASH, albedo)
    return albedo


def render_for_landmarks(data: HeadModelData, vertices: np.ndarray, camera: PinholeCamera):
    """A skin-like shaded image (H, W, 3) in [0, 1] of posed ``vertices`` and its hits."""
    hits = raycast(vertices, data.faces, camera)
    canonical = interpolate(hits, data.faces, data.v_template)
    image = shade_lambert(hits, data.faces, vertices, paint_albedo(data, hits, canonical), camera,
                          background=(0.55, 0.6, 0.65))
    return image, hits


# ---- embedding -------------------------------------------------------------------------
@dataclass
class LandmarkSample:
    """A view of the model used to build or test the embedding."""

    shape: np.ndarray
    expression: np.ndarray
    jaw: float
    yaw: float
    pitch: float


def _pose_vertices(model, sample: LandmarkSample) -> np.ndarray:
    import torch

    with torch.no_grad():
        out = model(shape=torch.tensor(sample.shape[None], dtype=torch.float32),
                    expression=torch.tensor(sample.expression[None], dtype=torch.float32),
                    jaw_pose=torch.tensor([[sample.jaw, 0.0, 0.0]], dtype=torch.float32))
    return out.vertices[0].double().numpy()


def make_samples(data: HeadModelData, seed: int, n_identities: int, views, expressions) -> list[LandmarkSample]:
    """Identities (first is the mean when seed == 0) x expressions x views."""
    rng = np.random.default_rng(seed)
    n_shape, n_expr = data.shapedirs.shape[2], data.exprdirs.shape[2]
    shapes = [np.zeros(n_shape)] if seed == 0 else []
    while len(shapes) < n_identities:
        shapes.append(np.clip(rng.normal(0, 0.8, n_shape), -2.5, 2.5) * (np.arange(n_shape) < 50))
    names = data.expression_names
    samples = []
    for shape in shapes:
        for expr_dict, jaw in expressions:
            expr = np.zeros(n_expr)
            for k, v in expr_dict.items():
                expr[names.index(k)] = v
            for yaw, pitch in views:
                samples.append(LandmarkSample(shape, expr, jaw, yaw, pitch))
    return samples


BUILD_VIEWS = [(0, 0), (-18, 0), (18, 0), (0, -10), (0, 10)]
BUILD_EXPRESSIONS = [({}, 0.0), ({"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5}, 0.0),
                     ({"jawOpen": 0.2}, 0.12)]
TEST_VIEWS = [(-8, 4), (10, -5), (4, 8)]
TEST_EXPRESSIONS = [({"browInnerUp": 0.6, "mouthFunnel": 0.4}, 0.05),
                    ({"mouthFrownLeft": 0.5, "mouthFrownRight": 0.5, "eyeSquintLeft": 0.3,
                      "eyeSquintRight": 0.3}, 0.0),
                    ({"jawOpen": 0.3, "mouthStretchLeft": 0.3, "mouthStretchRight": 0.3}, 0.2)]


def _camera_for(sample: LandmarkSample, resolution: int) -> PinholeCamera:
    return look_at_head(resolution, resolution, focal=2.2 * resolution, distance=0.6,
                        yaw_deg=sample.yaw, pitch_deg=sample.pitch, target=(0.0, -0.02, 0.0))


def _detect_on_render(data: HeadModelData, model, sample: LandmarkSample, resolution: int):
    vertices = _pose_vertices(model, sample)
    camera = _camera_for(sample, resolution)
    image, hits = render_for_landmarks(data, vertices, camera)
    return vertices, camera, image, detect_mediapipe(image)


def embed_landmarks(data: HeadModelData, resolution: int = 512, progress=None,
                    n_identities: int = 10) -> HeadModelData:
    """Compute and store ``landmark_faces``/``landmark_bary`` (478 MediaPipe points) in ``data``.

    Measured (512 px, ~140 px face width): 4 identities -> 3.32 px held-out median error,
    10 identities -> 3.15 px; the error on the build renders themselves is 2.75 px, i.e.
    MediaPipe's points slide on the surface by that much across identities and expressions.
    """
    say = progress or (lambda msg: log.info(msg))
    samples = make_samples(data, seed=0, n_identities=n_identities, views=BUILD_VIEWS,
                           expressions=BUILD_EXPRESSIONS)
    say(f"embedding MediaPipe landmarks from {len(samples)} renders at {resolution}px")
    from headforge.head.model import HeadModel

    model = HeadModel(data)
    hits_face, hits_bary, used = [], [], 0
    for sample in samples:
        vertices, camera, _, lmk = _detect_on_render(data, model, sample, resolution)
        if lmk is None:
            continue
        used += 1
        origins, dirs = camera.rays(lmk)
        fid, bary, _ = cast(vertices, data.faces, origins, dirs)
        hits_face.append(fid)
        hits_bary.append(bary)
    if used < 3:
        raise HeadforgeError(f"MediaPipe found a face in only {used} of {len(samples)} renders of the head model; "
                             "cannot embed landmarks")
    fids, barys = np.stack(hits_face), np.stack(hits_bary)  # (R, 478)
    tmpl = data.v_template
    canonical = (tmpl[data.faces[np.maximum(fids, 0)]] * barys[..., None]).sum(axis=2)  # (R, 478, 3)
    faces_out = np.zeros(N_MEDIAPIPE, dtype=np.int64)
    bary_out = np.zeros((N_MEDIAPIPE, 3))
    for k in range(N_MEDIAPIPE):
        ok = fids[:, k] >= 0
        if not ok.any():
            raise HeadforgeError(f"landmark {k} never hit the head model; cannot embed it")
        pts, hit_faces = canonical[ok, k], np.unique(fids[ok, k])
        # Trimmed mean of the canonical hits, snapped to the closest of the triangles hit.
        dist = np.linalg.norm(pts - np.median(pts, axis=0), axis=1)
        target = pts[dist <= np.quantile(dist, 0.8)].mean(axis=0)
        tris = tmpl[data.faces[hit_faces]]
        closest = trimesh.triangles.closest_point(tris, np.repeat(target[None], len(tris), axis=0))
        best = np.argmin(np.linalg.norm(closest - target, axis=1))
        faces_out[k] = hit_faces[best]
        bary_out[k] = trimesh.triangles.points_to_barycentric(tris[best:best + 1], closest[best:best + 1])[0]
    data.landmark_faces, data.landmark_bary = faces_out, bary_out
    data.meta["landmarks"] = {"kind": "mediapipe-478", "renders_used": used, "renders": len(samples),
                              "resolution": resolution,
                              "mediapipe_to_ibug68": MEDIAPIPE_TO_IBUG68.tolist()}
    error = evaluate_embedding(data, resolution)
    data.meta["landmarks"].update(landmark_median_px=error["landmark_median_px"], heldout=error)
    say(f"landmark embedding: median reprojection error {error['landmark_median_px']:.2f}px on "
        f"{error['renders_used']} held-out renders ({error['landmark_median_px_inner']:.2f}px without the face oval)")
    return data


def evaluate_embedding(data: HeadModelData, resolution: int = 512, seed: int = 1) -> dict:
    """Median distance (px) between MediaPipe detections and the projected embedded landmarks
    on renders of identities, expressions and views not used to build the embedding."""
    from headforge.head.model import HeadModel

    samples = make_samples(data, seed=seed, n_identities=3, views=TEST_VIEWS, expressions=TEST_EXPRESSIONS)
    model = HeadModel(data)
    errors = []
    for sample in samples:
        vertices, camera, _, lmk = _detect_on_render(data, model, sample, resolution)
        if lmk is None:
            continue
        corners = vertices[data.faces[data.landmark_faces]]
        model_lmk = (corners * data.landmark_bary[..., None]).sum(axis=1)
        errors.append(np.linalg.norm(camera.project(model_lmk) - lmk, axis=1))
    if not errors:
        raise HeadforgeError("MediaPipe found no face in the held-out renders of the head model")
    err = np.stack(errors)
    inner = np.setdiff1d(np.arange(N_MEDIAPIPE), FACE_OVAL)
    return {"landmark_median_px": float(np.median(err)), "landmark_median_px_inner": float(np.median(err[:, inner])),
            "landmark_p90_px": float(np.percentile(err, 90)), "renders_used": len(errors),
            "renders_tested": len(samples)}
