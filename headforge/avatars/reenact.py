"""Frame-parameter sequences that drive an avatar: its own fitted frames, or another tracked
dataset's expressions and poses retargeted onto it (reenactment)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.head.model import POSE_ARGS
from headforge.head.pose import FRAME_KEYS, FrameParams


def own_sequence(avatar, assets, split: str = "val") -> FrameParams:
    """The avatar's fitted parameters of its dataset's ``split`` frames (train, val or all)."""
    rows = assets.rows(split)
    return {k: avatar.frames[k].detach()[rows] for k in FRAME_KEYS}


DRIVING_MODES = ("relative", "absolute")


def driving_clip(avatar, assets, driving: Path | None, split: str = "all", mode: str = "relative",
                 neutral: int = 0) -> tuple[FrameParams, float]:
    """(sequence, fps) that drive ``avatar``: with ``driving`` None its own ``split`` frames at its
    dataset's fps; a ``.csv`` file: an ARKit blendshape recording (:func:`arkit_sequence`; its
    head rotation is always applied on top of the avatar's); else a tracked dataset
    (:func:`driving_sequence`, ``mode`` relative or absolute, ``neutral`` the driver's neutral frame)."""
    if mode not in DRIVING_MODES:
        raise HeadforgeError(f"--driving-mode must be one of {', '.join(DRIVING_MODES)}, got {mode!r}")
    if driving is None:
        return own_sequence(avatar, assets, split), float(assets.meta.get("fps", 25.0))
    driving = Path(driving)
    if driving.suffix.lower() == ".csv":
        return arkit_sequence(avatar, assets, driving)
    return driving_sequence(avatar, assets, driving, mode, neutral), float(_dataset_fps(driving))


def _dataset_fps(root: Path) -> float:
    from headforge.data.dataset import read_meta

    return float(read_meta(root).get("fps", 25.0))


def arkit_sequence(avatar, assets, path: Path) -> tuple[FrameParams, float]:
    """A Live Link Face–style CSV (:mod:`headforge.data.arkit`) as parameters of this avatar:
    the blendshape weights as its expressions (the head model's expressions must be the ARKit
    names, as open-head's are), the head rotation applied on top of the avatar's mean root pose,
    the eye rotations as eye poses, the jaw and neck at rest (ARKit's jawOpen is a blendshape),
    the avatar's mean translation. Returns (sequence, the recording's fps)."""
    from scipy.spatial.transform import Rotation

    from headforge.data.arkit import read_arkit_csv

    names = list(assets.meta.get("expression_names") or avatar.head.expression_names)
    if not names:
        raise HeadforgeError(f"{path}: ARKit CSV driving needs a head model with named ARKit expressions (open-head); "
                             f"this avatar's {assets.meta.get('model')} has unnamed ones")
    clip = read_arkit_csv(path, names)
    T = len(clip.weights)
    own = {k: v.detach().cpu() for k, v in avatar.frames.items()}
    poses = avatar.head.effective_poses({"root_pose": own["root_pose"]})  # the tracked (limited) rotations
    mean_root = Rotation.from_rotvec(poses["root_pose"].numpy()).mean()
    root = (Rotation.from_rotvec(clip.rotations["head"]) * mean_root).as_rotvec()
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    tracked = {"expression": f32(clip.weights), "root_pose": f32(root), "neck_pose": torch.zeros(T, 3),
               "jaw_pose": torch.zeros(T, 3), "eye_left_pose": f32(clip.rotations["eye_left"]),
               "eye_right_pose": f32(clip.rotations["eye_right"]),
               "translation": own["translation"].mean(0).expand(T, 3).clone()}
    return avatar.params_from_tracking(tracked), clip.fps


def driving_sequence(avatar, assets, driving: Path, mode: str = "relative", neutral: int = 0,
                     avatar_neutral: int = 0) -> FrameParams:
    """The valid frames of the tracked dataset ``driving`` as parameters of this avatar (its
    head model and joint limits).

    ``relative`` (NHA App. B.1): the driver's expressions and poses relative to its own neutral
    frame (``neutral``-th valid frame) added to the avatar's neutral (its ``avatar_neutral``-th
    valid frame, as fitted): expression and translation by difference, rotations composed --
    the root's change on the left (in head space), a joint's on the right (in its parent's
    frame). A driver at its neutral frame gives the avatar's neutral parameters.
    ``absolute``: the driver's own values, keeping the avatar's framing (its mean translation,
    with the driver's motion around it)."""
    from headforge.avatars.run import RunAssets

    other = RunAssets.from_dataset(Path(driving))
    if other.meta["model"] != assets.meta["model"] or other.meta.get("n_shape") != assets.meta.get("n_shape"):
        raise HeadforgeError(f"{driving} was tracked with {other.meta['model']}, the avatar uses {assets.meta['model']}")
    rows = other.rows("all")
    if mode == "absolute":
        seq = {k: v[rows] for k, v in avatar.params_from_tracking(other.tracking).items()}
        own = avatar.frames["translation"].detach()
        seq["translation"] = seq["translation"] - seq["translation"].mean(0) + own.mean(0)
        return seq
    own_rows = assets.rows("all")
    for n, count, who in ((neutral, len(rows), str(driving)), (avatar_neutral, len(own_rows), "the avatar's dataset")):
        if not 0 <= n < count:
            raise HeadforgeError(f"neutral frame {n} is outside {who}'s {count} valid frames")
    driver = {k: other.tracking[k][rows].float() for k in FRAME_KEYS}  # poses as the skinning uses them
    own = {k: v.detach()[own_rows[avatar_neutral]][None].float().cpu() for k, v in avatar.frames.items()}
    own |= avatar.head.effective_poses({k: own[k] for k in POSE_ARGS})  # the avatar's limited poses
    return avatar.params_from_tracking(relative_to_neutral(driver, {k: v[neutral][None] for k, v in driver.items()}, own))


def relative_to_neutral(driver: FrameParams, driver_neutral: FrameParams, target_neutral: FrameParams) -> FrameParams:
    """NHA App. B.1's retargeting: ``driver`` (T, ...) relative to ``driver_neutral`` (1, ...)
    added to ``target_neutral`` (1, ...); poses axis-angle as the skinning uses them. Expression
    and translation: target + (driver - driver neutral). root_pose: (R R0^T) R_target, the head's
    change in head space; the other joints: R_target (R0^T R), the change in the joint's frame."""
    import roma

    out = {}
    for k in FRAME_KEYS:
        if k in POSE_ARGS:
            R, R0, Rt = (roma.rotvec_to_rotmat(p[k]) for p in (driver, driver_neutral, target_neutral))
            change = R @ R0.transpose(-1, -2) if k == "root_pose" else R0.transpose(-1, -2) @ R
            out[k] = roma.rotmat_to_rotvec(change @ Rt if k == "root_pose" else Rt @ change)
        else:
            out[k] = target_neutral[k] + driver[k] - driver_neutral[k]
    return out


def truncate(seq: FrameParams, max_frames: int | None) -> FrameParams:
    if max_frames is None:
        return seq
    if max_frames < 1:
        raise HeadforgeError(f"--max-frames must be >= 1, got {max_frames}")
    return {k: v[:max_frames] for k, v in seq.items()}


@torch.no_grad()
def render_sequence(avatar, K: torch.Tensor, resolution: int, seq: FrameParams, orbit: bool = False,
                    orbit_degrees: float = 30.0, options: dict | None = None):
    """Yield (R, R, 3) frames of ``seq`` on white, optionally with the head turning by up to
    ``orbit_degrees`` about the camera's vertical axis (novel views); ``options``: passed to the
    avatar's render (e.g. a point avatar's ``light``)."""
    from scipy.spatial.transform import Rotation

    from headforge.render.camera import Cameras

    T = seq["translation"].shape[0]
    for t in range(T):
        params = {k: v[t:t + 1] for k, v in seq.items()}
        if orbit:
            import math

            yaw = orbit_degrees * math.sin(2 * math.pi * t / max(T, 1))
            turned = Rotation.from_euler("y", yaw, degrees=True) * Rotation.from_rotvec(params["root_pose"][0].numpy())
            params["root_pose"] = torch.tensor(turned.as_rotvec(), dtype=torch.float32)[None]
        yield avatar.render(params, Cameras.at_origin(K, 1, resolution), background=1.0, **(options or {})).rgb[0].clamp(0, 1).numpy()
