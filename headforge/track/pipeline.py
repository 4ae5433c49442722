"""``headforge track VIDEO -o DATASET``: video -> cropped, masked, landmarked, tracked dataset.

Steps, each checkpointed in ``DATASET.partial/`` so an interrupted run resumes:
  1. detections.npz   MediaPipe landmarks of every kept frame (tracking mode)
  2. frames/, masks/  crops (and selfie-segmentation masks) written by a thread pool
  3. tracking.safetensors   the head model fitted to the landmarks of the whole clip (then,
     with ``photometric``, refined against the crops with the renderer)
  4. overlay.mp4      streamed frame by frame
  5. dataset.json, metrics.json, transforms.json; then the folder is renamed

Every option is checked before any work (``TrackOptions.validate``). The dataset's ``fps`` is
the source's rate divided by ``every``: the video's own rate, or for a folder of frames
``TrackOptions.fps`` (default :data:`FOLDER_FPS`); ``fps`` given for a video overrides its rate.
"""

from __future__ import annotations

import json
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from safetensors.torch import load_file, save_file

from headforge.data import dataset as ds
from headforge.data.preprocess import (
    ClipDetections,
    Segmenter,
    crop,
    crop_windows,
    detect_clip,
    transform_points,
)
from headforge.data.video import FOLDER_FPS, image_files, iter_frames, video_info
from headforge.errors import HeadforgeError
from headforge.head.landmarks import LandmarkSpec
from headforge.head.model import HeadModel
from headforge.head.pose import FRAME_KEYS, head_to_camera
from headforge.paths import open_partial
from headforge.render.camera import project_points
from headforge.track.photometric import PhotometricConfig, load_target
from headforge.track.tracker import TrackerConfig, track_landmarks


@dataclass
class TrackOptions:
    model: str = "open-head"
    flame_dir: str | None = None
    resolution: int = 512
    every: int = 1
    max_frames: int | None = None
    val_fraction: float = 0.2
    preset: str = "quick"
    overlay: bool = True
    focal: float | None = None  # known focal length in crop pixels; estimated when None
    crop: str = "face"  # "face": a smooth window around the face; "full": the whole (square) frame
    masks: str | None = None  # folder of foreground masks named like the frames (instead of selfie segmentation)
    photometric: bool = False  # refine the landmark fit against the crops with the renderer
    fps: float | None = None  # frame rate of the source: a video's own when None, FOLDER_FPS for a folder

    MAX_RESOLUTION = 4096

    def validate(self) -> None:
        """One-line errors naming the option, before any work is done."""
        from headforge.head import MODEL_NAMES

        if self.model not in MODEL_NAMES:
            raise HeadforgeError(f"--model must be one of {', '.join(MODEL_NAMES)}, got {self.model!r}")
        if not 64 <= self.resolution <= self.MAX_RESOLUTION:
            raise HeadforgeError(f"--resolution must be in [64, {self.MAX_RESOLUTION}], got {self.resolution}")
        if self.every < 1:
            raise HeadforgeError(f"--every must be >= 1, got {self.every}")
        if self.max_frames is not None and self.max_frames < 1:
            raise HeadforgeError(f"--max-frames must be >= 1, got {self.max_frames}")
        if not 0 <= self.val_fraction < 1:  # also false for NaN
            raise HeadforgeError(f"--val-fraction must be in [0, 1), got {self.val_fraction}")
        if self.preset not in ("quick", "paper"):
            raise HeadforgeError(f"--preset must be quick or paper, got {self.preset!r}")
        if self.focal is not None and not 0 < self.focal < float("inf"):
            raise HeadforgeError(f"--focal must be a positive number of crop pixels, got {self.focal}")
        if self.crop not in ("face", "full"):
            raise HeadforgeError(f"--crop must be face or full, got {self.crop!r}")
        if self.masks is not None and not Path(self.masks).is_dir():
            raise HeadforgeError(f"--masks folder not found: {self.masks}")
        if self.fps is not None and not 0 < self.fps < float("inf"):
            raise HeadforgeError(f"--fps must be > 0, got {self.fps}")


def track_video(video: str | Path, output: str | Path, options: TrackOptions = TrackOptions(), log=print,
                progress_factory=None) -> dict:
    """Run the whole pipeline; returns the metrics dict. ``progress_factory(description, total)``
    returns a callable advancing a progress bar (or None for no bars)."""
    from headforge.head import load_data

    options.validate()
    start = time.perf_counter()
    video, output = Path(video), Path(output)
    info = video_info(video)
    fps = dataset_fps(video, options, info)
    if options.masks is not None:
        _check_masks(video, options, info)
    settings = {"video": str(video.resolve()), "size": video.stat().st_size, **asdict(options)}
    settings.pop("overlay")
    work = open_partial(output, settings, log)
    bar = progress_factory or (lambda description, total: None)

    # 1. landmarks
    det_path = work / "detections.npz"
    det = _load_checkpoint(det_path, ClipDetections.load, log)
    if det is None:
        expected = info["frames"] // options.every if info["frames"] else None
        if expected and options.max_frames:
            expected = min(expected, options.max_frames)
        advance = bar("landmarks", expected)
        det = detect_clip(video, options.every, options.max_frames, progress=advance and (lambda n: advance()))
        det.save(work / "detections.tmp.npz")
        (work / "detections.tmp.npz").replace(det_path)
    T = len(det.valid)
    if not det.valid.any():
        shutil.rmtree(work)
        raise HeadforgeError(f"no face found in any of the {T} frames of {video}")
    log(f"{int(det.valid.sum())} of {T} frames have a face")
    if options.crop == "full":
        w, h = det.frame_size
        windows = np.tile([(w - 1) / 2, (h - 1) / 2, max(w, h)], (T, 1)).astype(np.float64)
    else:
        windows = crop_windows(det.landmarks, det.valid, det.frame_size)
    res = options.resolution
    lmk = np.stack([transform_points(det.landmarks[t], windows[t], res) for t in range(T)])

    data = load_data(options.model, options.flame_dir)

    # 2. crops and masks, written by a thread pool
    write_start = time.perf_counter()
    (work / "frames").mkdir(exist_ok=True)
    (work / "masks").mkdir(exist_ok=True)
    if options.masks is None:
        segment = Segmenter()
    else:
        mask_files = image_files(options.masks)

        def segment(image, t=None):
            if t >= len(mask_files):
                raise HeadforgeError(f"--masks folder {options.masks} has no mask for frame {t}")
            mask = cv2.imread(str(mask_files[t]), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise HeadforgeError(f"cannot read mask {mask_files[t]}")
            if mask.shape != image.shape[:2]:
                raise HeadforgeError(f"mask {mask_files[t]} is {mask.shape[1]}x{mask.shape[0]}, frame {t} is "
                                     f"{image.shape[1]}x{image.shape[0]}")
            return mask
    advance = bar("crops and masks", T)
    with ThreadPoolExecutor(max_workers=2) as pool:
        jobs = []
        for t, (_, image) in enumerate(iter_frames(video, options.every, options.max_frames)):
            if t >= T:
                break
            name = f"{t:05d}.png"
            frame_path, mask_path = work / "frames" / name, work / "masks" / name
            if not (frame_path.is_file() and mask_path.is_file()):
                crop_rgb = crop(image, windows[t], res)
                mask = crop(segment(image) if options.masks is None else segment(image, int(det.frame_indices[t])),
                            windows[t], res, interpolation=cv2.INTER_LINEAR)
                jobs.append(pool.submit(_write_pair, frame_path, crop_rgb, mask_path, mask))
            if advance:
                advance()
        for job in jobs:
            job.result()
    if options.masks is None:
        segment.close()
    write_seconds = time.perf_counter() - write_start

    # 3. tracking
    head = HeadModel(data)
    track_path = work / "tracking.safetensors"
    track_start = time.perf_counter()
    checkpoint = _load_checkpoint(track_path, lambda p: (load_file(str(p)),
                                                         np.asarray(json.loads((work / "camera.json").read_text())["K"])), log)
    if checkpoint is not None:
        tracked, K = checkpoint
    else:
        config = TrackerConfig.paper() if options.preset == "paper" else TrackerConfig.quick()
        config.focal = options.focal
        target = None
        if options.photometric:
            photo = PhotometricConfig.paper() if options.preset == "paper" else PhotometricConfig.quick()
            photo.size = min(photo.size, res)
            names = [f"{t:05d}.png" for t in range(T)]
            target = load_target([work / "frames" / n for n in names], [work / "masks" / n for n in names],
                                 det.valid, head, photo)
        advance = bar("tracking", config.rigid_steps + config.steps + (target.config.steps if target else 0))
        result = track_landmarks(HeadModel(data, landmarks_only=True), lmk, det.valid, res, config,
                                 progress=advance and (lambda loss: advance()), photometric=target)
        # "projected" holds the model's landmarks at the detections they match (NaN elsewhere)
        projected = np.full_like(lmk, np.nan)
        projected[:, result.spec.detection_ids] = result.projected
        tracked = {"shape": result.shape, **result.frames, "landmarks": torch.tensor(lmk, dtype=torch.float32),
                   "valid": torch.tensor(det.valid), "projected": torch.tensor(projected, dtype=torch.float32)}
        K = result.K
        if result.photometric_preview is not None:
            from headforge.render.io import write_png

            write_png(work / "photometric.png", torch.from_numpy(result.photometric_preview).float() / 255)
        (work / "camera.json").write_text(json.dumps({"K": K.tolist(), "photometric_l1": result.photometric_l1}))
        save_file({k: v.contiguous() for k, v in tracked.items()}, str(work / "tracking.tmp.safetensors"))
        (work / "tracking.tmp.safetensors").replace(track_path)
    fit_seconds = time.perf_counter() - track_start
    errors = np.linalg.norm(tracked["projected"].numpy() - lmk, axis=-1)  # NaN where not matched
    errors[~det.valid] = np.nan
    spec = LandmarkSpec.for_model(head.num_landmarks)
    inner = spec.detection_ids[~spec.contour]

    # 4. overlay video, streamed (decoding and cropping again is cheaper than holding the clip)
    if options.overlay:
        from headforge.render.io import write_mp4

        verts = _camera_vertices(head, tracked)
        projected_all = tracked["projected"].numpy()
        frames_in = ((t, crop(image, windows[t], res))
                     for t, (_, image) in enumerate(iter_frames(video, options.every, options.max_frames)) if t < T)
        write_mp4(work / "overlay.mp4", (_draw_overlay(f, lmk[t], projected_all[t], verts[t], head, K, det.valid[t])
                                         for t, f in frames_in), fps=fps, total=T,
                  description="overlay video")

    # 5. metadata
    n_val = int(round(T * options.val_fraction))
    frames = [{"index": t, "source_frame": int(det.frame_indices[t]), "valid": bool(det.valid[t]),
               "split": "val" if t >= T - n_val else "train", "image": f"frames/{t:05d}.png",
               "mask": f"masks/{t:05d}.png", "crop": [round(float(v), 3) for v in windows[t]]} for t in range(T)]
    meta = {"format": ds.FORMAT, "version": ds.VERSION, "model": data.name, "n_shape": int(tracked["shape"].shape[1]),
            "expression_names": data.expression_names, "resolution": res, "fps": fps,
            "video": str(video), "intrinsics": np.asarray(K).tolist(),
            "camera": "OpenCV pinhole at the origin; head vertex x -> diag(1,-1,-1) x + translation",
            "frames": frames}
    (work / "dataset.json").write_text(json.dumps(meta, indent=1))
    with torch.no_grad():
        root_joint = head(shape=tracked["shape"]).joints[0, 0].double().numpy()
    (work / "transforms.json").write_text(json.dumps(ds.transforms_from(meta, tracked, root_joint), indent=1))
    preprocess_seconds = det.seconds + write_seconds
    metrics = {"frames_total": T, "frames_valid": int(det.valid.sum()),
               "fps_preprocess": round(T / preprocess_seconds, 2),
               "track_seconds": round(time.perf_counter() - start, 2), "fit_seconds": round(fit_seconds, 2),
               "landmark_median_px": round(float(np.nanmedian(errors[:, inner])), 3),
               "landmark_median_px_all": round(float(np.nanmedian(errors)), 3),
               "landmark_error_excludes": "face-contour points (MediaPipe's 36 face-oval / iBUG's 17 jaw points)",
               "resolution": res, "focal_px": round(float(K[0][0]), 2)}
    photometric_l1 = json.loads((work / "camera.json").read_text()).get("photometric_l1")
    if photometric_l1 is not None:
        metrics["photometric_l1"] = round(photometric_l1, 4)
    (work / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if output.exists():
        shutil.rmtree(output)
    work.replace(output)
    return metrics


def dataset_fps(video: Path, options: TrackOptions, info: dict) -> float:
    """The rate of the kept frames: the source's (``options.fps``, else a video's own rate, a
    folder's :data:`FOLDER_FPS`) over ``options.every``."""
    source = options.fps or (FOLDER_FPS if Path(video).is_dir() else info["fps"])
    return source / options.every


def _load_checkpoint(path: Path, load, log):
    """``load(path)`` of a checkpoint in the work folder, or None when it is absent or unreadable
    (a run killed while writing it, a disk error): that step is then redone."""
    if not path.is_file():
        return None
    try:
        return load(path)
    except Exception as exc:  # numpy, safetensors, JSON: any failure means "redo the step"
        log(f"{path} is unreadable ({type(exc).__name__}): redoing that step")
        path.unlink(missing_ok=True)
        return None


def _check_masks(video: Path, options: TrackOptions, info: dict) -> None:
    """A --masks folder needs one mask per source frame, of the frames' size (read: the first)."""
    masks = image_files(options.masks)
    if info["frames"] and len(masks) < info["frames"]:
        raise HeadforgeError(f"--masks folder {options.masks} has {len(masks)} images, {video} has {info['frames']} frames")
    first = cv2.imread(str(masks[0]), cv2.IMREAD_GRAYSCALE)
    if first is None:
        raise HeadforgeError(f"cannot read mask {masks[0]}")
    if first.shape != (info["height"], info["width"]):
        raise HeadforgeError(f"mask {masks[0]} is {first.shape[1]}x{first.shape[0]}, the frames of {video} are "
                             f"{info['width']}x{info['height']}")


def _write_pair(frame_path: Path, rgb: np.ndarray, mask_path: Path, mask: np.ndarray) -> None:
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    for path, image in ((frame_path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), (mask_path, mask)):
        tmp = path.with_name(path.stem + ".tmp.png")
        if not cv2.imwrite(str(tmp), image, params):
            raise HeadforgeError(f"cannot write {path} (disk full?)")
        tmp.replace(path)


def _camera_vertices(head: HeadModel, tracked: dict, chunk: int = 64) -> np.ndarray:
    """(T, V, 3) full-mesh vertices in camera space."""
    T = tracked["translation"].shape[0]
    out = []
    with torch.no_grad():
        for s in range(0, T, chunk):
            sl = slice(s, s + chunk)
            n = len(tracked["translation"][sl])
            o = head(shape=tracked["shape"].expand(n, -1), **{k: tracked[k][sl] for k in FRAME_KEYS[:-1]})
            out.append(head_to_camera(o.vertices, tracked["translation"][sl]).numpy())
    return np.concatenate(out)


# MediaPipe contours drawn as lines in the overlay (right eye, left eye, outer lips).
CONTOURS = (
    [33, 246, 161, 160, 159, 158, 157, 173, 133, 155, 154, 153, 145, 144, 163, 7],
    [263, 466, 388, 387, 386, 385, 384, 398, 362, 382, 381, 380, 374, 373, 390, 249],
    [61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291, 375, 321, 405, 314, 17, 84, 181, 91, 146],
)


def _draw_overlay(image, detected, projected, verts_cam, head: HeadModel, K, valid) -> np.ndarray:
    """Crop with the projected model wireframe (front-facing triangles, faint blue), and the eye
    and lip contours of the detections (green) and of the model (red): closed model lids on
    blink frames are visible at a glance."""
    faces = head.faces.numpy()
    uv = project_points(torch.from_numpy(verts_cam).float(), torch.from_numpy(np.asarray(K)).float()).numpy()
    tri = verts_cam[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = (normal * tri.mean(1)).sum(-1) < 0  # facing the camera at the origin
    wire = image.copy()
    cv2.polylines(wire, list(np.round(uv[faces[front]] * 4).astype(np.int32)), True, (90, 140, 255), 1, cv2.LINE_AA, shift=2)
    out = cv2.addWeighted(image, 0.65, wire, 0.35, 0)
    if valid:
        for pts, colour in ((detected, (40, 220, 40)), (projected, (240, 40, 40))):
            contours = [np.round(pts[c] * 4).astype(np.int32) for c in CONTOURS if np.isfinite(pts[c]).all()]
            cv2.polylines(out, contours, True, colour, 1, cv2.LINE_AA, shift=2)
            if not contours:  # a model with sparse landmarks (iBUG-68): dots
                for x, y in np.round(pts[np.isfinite(pts).all(-1)]).astype(int):
                    cv2.circle(out, (int(x), int(y)), 1, colour, -1)
    else:
        cv2.putText(out, "no face", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 60, 60), 2)
    return out
