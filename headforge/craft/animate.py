"""Animate a HeadCraft displacement map (App. B.1): the map's displacements are looked up on the
neutral dense template of an identity, expressed in the neutral per-vertex TBN frames, and
re-expressed in the TBN frames of the posed template of every frame (expression, jaw, neck,
head pose). The dense template is the consistent subdivision with HeadCraft's per-region
Laplacian smoothing (lips 3, face 5, scalp and neck 10 iterations; mouth, ears, eyeballs kept),
:func:`headforge.craft.register.dense_base`.

Canonical head space: metres, y up, face toward +z. Frames are (Vd, 3, 3) with columns
(tangent along +u, bitangent, normal): :func:`headforge.head.topology.tbn_frames`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from headforge.craft import uvmap
from headforge.craft.register import RegisterConfig, Template, dense_base
from headforge.errors import HeadforgeError
from headforge.head.topology import tbn_frames


def frames(template: Template, duv: uvmap.DenseUV, vertices: torch.Tensor) -> torch.Tensor:
    """(Vd, 3, 3) TBN frames of a dense template mesh (Vd, 3)."""
    return tbn_frames(vertices.double(), template.faces, torch.as_tensor(duv.uvs, dtype=torch.float64),
                      torch.as_tensor(duv.uv_faces))


def to_tbn(displacement: torch.Tensor, neutral_frames: torch.Tensor) -> torch.Tensor:
    """(Vd, 3) object-space displacements -> (t . d, b . d, n . d) in the neutral frames."""
    return torch.einsum("vij,vi->vj", neutral_frames, displacement.double())


def from_tbn(d_tbn: torch.Tensor, posed_frames: torch.Tensor) -> torch.Tensor:
    """(Vd, 3) TBN coordinates -> object space with the posed frames: [t b n] d_tbn."""
    return torch.einsum("vij,vj->vi", posed_frames, d_tbn)


def transfer(displacement: torch.Tensor, neutral_frames: torch.Tensor, posed_frames: torch.Tensor) -> torch.Tensor:
    """B.1: re-orient displacements from the neutral frames to the posed ones, (Vd, 3)."""
    return from_tbn(to_tbn(displacement, neutral_frames), posed_frames)


def neutral_params(params: dict | None) -> dict:
    """The identity of ``params`` with zero expression and pose (B.1's F_neutral)."""
    params = params or {}
    return {"shape": torch.as_tensor(params["shape"], dtype=torch.float32).reshape(1, -1)} if "shape" in params else {}


class Animator:
    """A map on one identity, posed frame by frame.

    ``map_m`` (R, R, 3) metres, post-processed (seams equalised, every texel filled).
    ``identity`` head-model parameters with at least ``shape`` (1, S) (others ignored)."""

    def __init__(self, template: Template, duv: uvmap.DenseUV, map_m: np.ndarray, identity: dict | None = None,
                 smooth_iterations: dict | None = None):
        self.template, self.duv = template, duv
        self.smooth = smooth_iterations or RegisterConfig().smooth_iterations
        self.identity = neutral_params(identity)
        self.neutral = dense_base(template, self.identity, self.smooth)
        self.displacement = uvmap.lookup(map_m, duv, template.n_vertices)
        self.d_tbn = to_tbn(self.displacement, frames(template, duv, self.neutral))

    def neutral_mesh(self) -> torch.Tensor:
        return self.neutral + self.displacement

    def posed_mesh(self, frame: dict[str, torch.Tensor]) -> torch.Tensor:
        """(Vd, 3) mesh for one frame's parameters (expression (1, E), *_pose (1, 3); shape is
        the identity's)."""
        params = {k: torch.as_tensor(v, dtype=torch.float32).reshape(1, -1) for k, v in frame.items()
                  if k not in ("shape", "translation")}
        base = dense_base(self.template, {**self.identity, **params}, self.smooth)
        return base + from_tbn(self.d_tbn, frames(self.template, self.duv, base))


def driving_frames(dataset: str | Path, head_model: str, max_frames: int | None = None) -> tuple[list[dict], float]:
    """Per-frame parameters of a tracked dataset (expression and joint rotations) and its fps;
    a one-line error when it was tracked with another head model."""
    from headforge.data.dataset import load_tracking, read_meta
    from headforge.head.pose import POSE_KEYS

    meta = read_meta(dataset)
    model = meta.get("model")
    model_name = model.get("name") if isinstance(model, dict) else model
    if model_name != head_model:
        raise HeadforgeError(f"{dataset} was tracked with {model_name!r}; this map lives on {head_model!r} "
                             f"(track the clip again with --model {head_model})")
    tracking = load_tracking(dataset, meta)
    T = len(meta["frames"])
    valid = tracking["valid"].bool() if "valid" in tracking else torch.ones(T, dtype=torch.bool)
    rows = torch.nonzero(valid)[:, 0].tolist()
    if max_frames is not None:
        rows = rows[:max_frames]
    if not rows:
        raise HeadforgeError(f"{dataset} has no valid tracked frame")
    keys = ("expression",) + tuple(POSE_KEYS)
    return [{k: tracking[k][r:r + 1] for k in keys} for r in rows], float(meta.get("fps", 30.0))


def render_views(vertices: np.ndarray, faces: np.ndarray, size: int = 256, yaws=(0.0, 90.0, 180.0),
                 colour=(0.78, 0.76, 0.74)) -> np.ndarray:
    """(size, size * len(yaws), 3) float grey renders of a head mesh from the given yaws
    (0 = front, 90 = its left side, 180 = back), aimed at the middle of the head."""
    from headforge.craft.scans import render_mesh

    upper = vertices[vertices[:, 1] > np.percentile(vertices[:, 1], 20)]
    target = 0.5 * (upper.min(0) + upper.max(0))
    target[0] = 0.0
    col = np.tile(np.asarray(colour), (len(vertices), 1))
    return np.concatenate([render_mesh(vertices, faces, col, size, yaw, target, distance=0.65) for yaw in yaws], 1)


def sweep_frames(template: Template, frames: int = 48) -> list[dict]:
    """A built-in driving sequence when no tracked video is at hand (``headforge demo --method
    headcraft``): the jaw opens and closes, a smile comes and goes, the head turns 25 degrees
    left and right; ``frames`` per-frame parameter dicts like :func:`driving_frames`'."""
    from headforge.head.pose import POSE_KEYS

    names = list(template.model.expression_names)
    E = template.model.n_expr
    out = []
    for k in range(frames):
        t = 2 * np.pi * k / frames
        expr = torch.zeros(1, E)
        for name, value in (("jawOpen", max(0.0, np.sin(t))), ("mouthSmileLeft", max(0.0, -np.sin(t))),
                            ("mouthSmileRight", max(0.0, -np.sin(t)))):
            if name in names:
                expr[0, names.index(name)] = float(value)
        frame = {"expression": expr, **{key: torch.zeros(1, 3) for key in POSE_KEYS}}
        frame["jaw_pose"][0, 0] = 0.25 * max(0.0, float(np.sin(t)))
        frame["root_pose"][0, 1] = float(np.radians(25.0) * np.sin(2 * t))
        out.append(frame)
    return out


def render_animation(template: Template, duv: uvmap.DenseUV, map_m: np.ndarray, identity: dict | None,
                     params: list[dict], fps: float, output: str | Path, size: int = 256, yaws=(0.0, 60.0),
                     log=print) -> int:
    """Render the map on ``identity`` posed by ``params`` (per-frame dicts) to an MP4 (atomic);
    returns the number of frames."""
    from rich.progress import track

    from headforge.render.io import write_mp4

    anim = Animator(template, duv, map_m, identity)
    faces = template.faces.numpy()
    imgs = []
    for frame in track(params, description="animating", transient=True):
        v = anim.posed_mesh(frame).numpy()
        imgs.append((np.clip(render_views(v, faces, size, yaws), 0, 1) * 255).astype(np.uint8))
    write_mp4(output, imgs, fps=fps)  # atomic
    log(f"{len(imgs)} frames -> {output}")
    return len(imgs)


def animate(template: Template, duv: uvmap.DenseUV, map_m: np.ndarray, identity: dict | None, dataset: str | Path,
            head_model: str, output: str | Path, max_frames: int | None = 150, size: int = 256,
            yaws=(0.0, 60.0), log=print) -> int:
    """Render the map on ``identity`` driven by a tracked dataset to an MP4 (atomic); returns
    the number of frames."""
    params, fps = driving_frames(dataset, head_model, max_frames)
    return render_animation(template, duv, map_m, identity, params, fps, output, size, yaws, log)
