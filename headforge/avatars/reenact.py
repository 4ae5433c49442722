"""Frame-parameter sequences that drive an avatar: its own fitted frames, or another tracked
dataset's expressions and poses retargeted onto it (reenactment)."""

from __future__ import annotations

from pathlib import Path

import torch

from headforge.errors import HeadforgeError
from headforge.head.pose import FRAME_KEYS, FrameParams


def own_sequence(avatar, assets, split: str = "val") -> FrameParams:
    """The avatar's fitted parameters of its dataset's ``split`` frames (train, val or all)."""
    rows = assets.rows(split)
    return {k: avatar.frames[k].detach()[rows] for k in FRAME_KEYS}


def driving_sequence(avatar, assets, driving: Path) -> FrameParams:
    """The valid frames of the tracked dataset ``driving`` as parameters of this avatar (its
    head model and joint limits), keeping the avatar's own framing: its mean translation, with
    the driver's motion around it."""
    from headforge.avatars.run import RunAssets

    other = RunAssets.from_dataset(Path(driving))
    if other.meta["model"] != assets.meta["model"] or other.meta.get("n_shape") != assets.meta.get("n_shape"):
        raise HeadforgeError(f"{driving} was tracked with {other.meta['model']}, the avatar uses {assets.meta['model']}")
    seq = {k: v[other.rows("all")] for k, v in avatar.params_from_tracking(other.tracking).items()}
    own = avatar.frames["translation"].detach()
    seq["translation"] = seq["translation"] - seq["translation"].mean(0) + own.mean(0)
    return seq


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
