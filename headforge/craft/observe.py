"""Partial observations for HeadCraft's fitting (§4.3, App. B.1): depth maps and point clouds in,
points in head axes out; and depth maps rendered from scans (the benchmark's observations).

Frames:

- a depth map's points are first back-projected in its camera's frame, OpenCV (x right, y down,
  z forward, metres);
- every observation is then turned into *observation head axes* W: y up, the face looking
  roughly toward +z (headforge's head-space convention, up to the head's own yaw/pitch). For a
  depth map or a camera-frame cloud that is ``diag(1, -1, -1)`` (the one head-to-camera flip of
  :mod:`headforge.head.pose`): the camera sits at W's origin looking along -z. Clouds in other
  axes say so with ``up`` / ``forward`` (the scan readers' options).

Depth files: a 16-bit PNG (``depth_scale`` metres per unit, default 0.001: millimetres) or a
float ``.npy`` (default metres), with a camera JSON holding ``fx, fy, cx, cy`` (or ``K``), and
optionally ``width``, ``height``, ``depth_scale``. Zero, non-finite and saturated (65535) pixels
are no measurement. Clouds: PLY (vertices; a PLY with faces is a scan, not a cloud) and PCD
(organised or not, via ``pypcd4``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

MIN_POINTS = 300  # fewer points cannot constrain a head model's pose and shape (the fit has ~160 unknowns)
HEAD_DEPTH_M = 0.4  # foreground: points within this depth behind the nearest ones (a head is < 30 cm deep)
CAMERA_TO_W = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> observation head axes W
DEPTH_SUFFIXES = (".png", ".npy")
CLOUD_SUFFIXES = (".ply", ".pcd")


@dataclass
class DepthCamera:
    """Pinhole intrinsics of a depth map (pixels; pixel (0, 0) is the top-left pixel's centre)."""

    K: np.ndarray  # (3, 3)
    width: int
    height: int
    depth_scale: float | None = None  # metres per stored unit (None: the file type's default)
    R: np.ndarray | None = None  # optional (3, 3) world-to-camera rotation (a scan's frame; benchmarks)
    t: np.ndarray | None = None  # optional (3,) world-to-camera translation, metres

    @classmethod
    def from_json(cls, path: str | Path) -> DepthCamera:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise HeadforgeError(f"cannot read camera file {path}: {exc}") from None
        if "K" in d:
            K = np.asarray(d["K"], np.float64)
            if K.shape != (3, 3):
                raise HeadforgeError(f"{path.name}: K must be 3x3, got shape {K.shape}")
        elif all(k in d for k in ("fx", "fy", "cx", "cy")):
            K = np.array([[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1.0]], np.float64)
        else:
            raise HeadforgeError(f"{path.name} holds no intrinsics: give fx, fy, cx, cy (pixels) or a 3x3 K")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise HeadforgeError(f"{path.name}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        pose = [np.asarray(d[k], np.float64) if k in d else None for k in ("R", "t")]
        if pose[0] is not None and (pose[0].shape != (3, 3) or pose[1] is None or pose[1].shape != (3,)):
            raise HeadforgeError(f"{path.name}: a pose needs R (3x3) and t (3)")
        return cls(K, int(d.get("width", 0)), int(d.get("height", 0)), d.get("depth_scale"), *pose)

    def to_json(self) -> dict:
        out = {"fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]), "cx": float(self.K[0, 2]), "cy": float(self.K[1, 2]),
               "width": self.width, "height": self.height}
        if self.depth_scale is not None:
            out["depth_scale"] = self.depth_scale
        if self.R is not None:
            out["R"], out["t"] = np.asarray(self.R).tolist(), np.asarray(self.t).tolist()
        return out

    def pinhole(self):
        """This camera as a :class:`headforge.render.camera.PinholeCamera` (identity pose if none)."""
        from headforge.render.camera import PinholeCamera

        R = np.eye(3) if self.R is None else self.R
        t = np.zeros(3) if self.t is None else self.t
        return PinholeCamera(K=self.K, R=R, t=t, width=self.width, height=self.height)


@dataclass
class Observation:
    """Points of a partial observation in observation head axes W (module doc), metres."""

    points: np.ndarray  # (N, 3)
    kind: str  # "depth" | "cloud"
    name: str
    to_source: np.ndarray = field(default_factory=lambda: CAMERA_TO_W.T.copy())  # (3, 3): W -> the file's axes
    camera: DepthCamera | None = None
    depth: np.ndarray | None = None  # (H, W) metres, 0 where no measurement (depth maps)

    @property
    def camera_centre(self) -> np.ndarray | None:
        """The sensor's centre in W (its origin) when the points came from a camera, else None."""
        return np.zeros(3) if self.kind == "depth" else None

    def spacing_m(self) -> float:
        """Median distance from a point to its nearest neighbour (the cloud's sampling density)."""
        from scipy.spatial import cKDTree

        d, _ = cKDTree(self.points).query(self.points, k=2)
        return float(np.median(d[:, 1]))


def backproject(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) depth (metres along the optical axis, 0 = none) -> ((N, 3) camera-frame points,
    (N, 2) (row, col) of each)."""
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols]
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], 1), np.stack([rows, cols], 1)


def foreground(depth: np.ndarray) -> np.ndarray:
    """Keep the nearest ~head-deep layer of a depth map (background walls and furniture behind
    the person dropped): pixels within :data:`HEAD_DEPTH_M` of the 1st depth percentile."""
    valid = depth > 0
    if not valid.any():
        return depth
    near = np.percentile(depth[valid], 1)
    return np.where(valid & (depth <= near + HEAD_DEPTH_M), depth, 0.0)


def _camera_for(path: Path, camera: str | Path | None) -> DepthCamera:
    if camera is not None:
        return DepthCamera.from_json(camera)
    for cand in (path.with_suffix(".json"), path.with_name(path.stem + "_camera.json"), path.parent / "camera.json"):
        if cand.is_file():
            return DepthCamera.from_json(cand)
    raise HeadforgeError(f"depth map {path.name} has no intrinsics: pass --camera FILE.json with fx, fy, cx, cy "
                         f"(looked for {path.stem}.json, {path.stem}_camera.json and camera.json beside it)")


def read_depth(path: str | Path, camera: str | Path | None = None, depth_scale: float | None = None) -> Observation:
    """A depth map (16-bit PNG or float .npy) and its intrinsics -> an :class:`Observation`."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise HeadforgeError(f"no depth map at {path}")
    cam = _camera_for(path, camera)
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise HeadforgeError(f"cannot read {path.name}: {exc}") from None
        if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number):
            raise HeadforgeError(f"{path.name}: a depth .npy must be a 2-D numeric array, got {raw.dtype} {raw.shape}")
        scale = depth_scale or cam.depth_scale or 1.0
        depth = np.where(np.isfinite(raw), raw.astype(np.float64), 0.0) * scale
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise HeadforgeError(f"cannot read depth map {path.name}")
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise HeadforgeError(f"{path.name}: a depth PNG must be single-channel 16-bit, got {raw.dtype} "
                                 f"with shape {raw.shape}")
        scale = depth_scale or cam.depth_scale or 0.001
        depth = np.where(raw == 65535, 0, raw).astype(np.float64) * scale  # 65535: saturated / no return
    if (cam.width and cam.width != depth.shape[1]) or (cam.height and cam.height != depth.shape[0]):
        raise HeadforgeError(f"{path.name} is {depth.shape[1]}x{depth.shape[0]} but its camera says {cam.width}x{cam.height}")
    depth = np.where(depth > 0, depth, 0.0)
    if not (depth > 0).any():
        raise HeadforgeError(f"{path.name} has no valid depth (every pixel is zero, saturated or not finite)")
    depth = foreground(depth)
    pts, _ = backproject(depth, cam.K)
    cam = DepthCamera(cam.K, depth.shape[1], depth.shape[0], scale, cam.R, cam.t)
    return _checked(Observation(pts @ CAMERA_TO_W.T, "depth", path.stem, CAMERA_TO_W.T.copy(), cam, depth))


def read_cloud(path: str | Path, up: str = "-y", forward: str = "-z", units: str = "m") -> Observation:
    """A PLY or PCD point cloud -> an :class:`Observation`. Defaults: a sensor's camera frame
    (OpenCV: up -y, the face looking at the sensor along -z), metres."""
    from headforge.craft.scans import UNITS, axes_matrix

    path = Path(path)
    if not path.is_file():
        raise HeadforgeError(f"no point cloud at {path}")
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        pts = _read_pcd(path)
    elif suffix == ".ply":
        import trimesh

        try:
            obj = trimesh.load(path, process=False)
        except Exception as exc:  # trimesh raises many types on corrupt files
            raise HeadforgeError(f"cannot read {path.name}: {exc}") from None
        if isinstance(obj, trimesh.Trimesh) and len(obj.faces):
            raise HeadforgeError(f"{path.name} is a mesh (it has faces): fit it as a full scan, not as a cloud")
        pts = np.asarray(getattr(obj, "vertices", np.zeros((0, 3))), np.float64)
    else:
        raise HeadforgeError(f"{path.name}: unsupported point cloud format (PLY or PCD)")
    if units not in UNITS:
        try:
            scale = float(units)
        except ValueError:
            raise HeadforgeError(f"--units must be m, cm, mm or metres per unit, got {units!r}") from None
    else:
        scale = UNITS[units]
    pts = pts[np.isfinite(pts).all(1)] * scale
    A = axes_matrix(up, forward)
    return _checked(Observation(pts @ A.T, "cloud", path.stem, A.T.copy()))


def _read_pcd(path: Path) -> np.ndarray:
    from pypcd4 import PointCloud

    try:
        pc = PointCloud.from_path(str(path))
    except Exception as exc:  # pypcd4 raises ValueError, KeyError, struct errors ... on broken files
        raise HeadforgeError(f"cannot read {path.name}: {exc}") from None
    if not all(f in pc.fields for f in ("x", "y", "z")):
        raise HeadforgeError(f"{path.name} has no x, y, z fields (fields: {', '.join(pc.fields)})")
    return np.asarray(pc.numpy(("x", "y", "z")), np.float64)  # organised clouds: NaN pixels dropped by the caller


def _checked(obs: Observation) -> Observation:
    if len(obs.points) < MIN_POINTS:
        raise HeadforgeError(f"{obs.name} has {len(obs.points)} valid points; a fit needs at least {MIN_POINTS}")
    extent = np.ptp(obs.points, axis=0)
    if extent.max() > 3.0 or extent.max() < 0.03:
        raise HeadforgeError(f"{obs.name} spans {extent.max():.3g} m: not a head in metres (wrong units? pass --units)")
    return obs


def read_observation(path: str | Path, camera: str | Path | None = None, depth_scale: float | None = None,
                     up: str = "-y", forward: str = "-z", units: str = "m") -> Observation:
    """A depth map or a point cloud, by file type (see the module doc)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in DEPTH_SUFFIXES:
        return read_depth(path, camera, depth_scale)
    if suffix in CLOUD_SUFFIXES:
        return read_cloud(path, up, forward, units)
    raise HeadforgeError(f"{path.name}: not a depth map (PNG, NPY) or a point cloud (PLY, PCD)")


def subsample(obs: Observation, fraction: float, seed: int = 0) -> Observation:
    """A random ``fraction`` of the points, as an unorganised cloud (the paper's 1 % clouds)."""
    rng = np.random.default_rng(seed)
    keep = rng.random(len(obs.points)) < fraction
    return Observation(obs.points[keep], "cloud", f"{obs.name}_sub{fraction:g}", obs.to_source.copy())


# ---------------------------------------------------------------- depth maps of meshes
def render_depth(vertices: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """(H, W) depth along the optical axis (metres, 0 where no hit) of a mesh seen by a
    :class:`headforge.render.camera.PinholeCamera` (ray casting: exact visibility)."""
    from headforge.render.raycast import raycast

    hits = raycast(vertices, faces, camera)
    _, dirs = camera.rays()
    axis = camera.R[2]  # the optical axis in world coordinates
    z = hits.depth.reshape(-1) * (dirs @ axis)
    return np.where(hits.mask.reshape(-1), z, 0.0).reshape(camera.height, camera.width)


def write_depth(path: str | Path, depth: np.ndarray, camera, depth_scale: float = 1e-4, pose: bool = True) -> Path:
    """A 16-bit depth PNG (``depth_scale`` metres per unit; 0.1 mm by default) and its camera
    JSON beside it (``<stem>.json``; with ``pose`` the scan-to-camera R, t too); both atomic."""
    import cv2

    path = Path(path)
    units = np.round(np.asarray(depth) / depth_scale)
    if units.max() >= 65535:
        raise HeadforgeError(f"depth up to {depth.max():.2f} m does not fit 16 bits at {depth_scale} m per unit")
    tmp = path.with_name(path.stem + ".partial.png")
    if not cv2.imwrite(str(tmp), units.astype(np.uint16)):
        raise HeadforgeError(f"cannot write {path}")
    cam = DepthCamera(np.asarray(camera.K), camera.width, camera.height, depth_scale,
                      np.asarray(camera.R) if pose else None, np.asarray(camera.t) if pose else None)
    jtmp = path.with_name(path.stem + ".json.partial")
    jtmp.write_text(json.dumps(cam.to_json(), indent=1))
    jtmp.replace(path.with_suffix(".json"))
    tmp.replace(path)
    return path


def depth_camera(target: np.ndarray, yaw_deg: float = 0.0, pitch_deg: float = 0.0, size: int = 512,
                 distance: float = 0.6, focal: float | None = None):
    """A sensor-like camera ``distance`` metres from ``target`` (head axes), orbited by yaw and
    pitch: about 40 degrees of field of view by default (a consumer depth sensor's)."""
    from headforge.render.camera import look_at_head

    return look_at_head(size, size, focal=focal or 1.35 * size, distance=distance, yaw_deg=yaw_deg,
                        pitch_deg=pitch_deg, target=target)


def depth_preview(depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 picture of a depth map: near bright, far dark, no measurement black."""
    valid = depth > 0
    img = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        lo, hi = np.percentile(depth[valid], [1, 99])
        v = 1 - np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
        img[valid] = (np.stack([v, v, v], -1)[valid] * 215 + 40).astype(np.uint8)
    return img
