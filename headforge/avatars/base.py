"""The interface every avatar method implements: an :class:`Avatar` module that renders frame
parameters through cameras into an :class:`AvatarRender`, and a :class:`Method` that builds it,
names its stages and optimisers, computes its energies and adds its own steps as hooks. The
training engine (:mod:`headforge.avatars.engine`) owns everything else.

Coordinates: canonical head space (metres, y up, face toward +z); cameras OpenCV at the origin,
the head moving (:mod:`headforge.head.pose`). Images (B, H, W, C) float in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import torch
from torch import nn

from headforge.head.pose import FrameParams
from headforge.render.camera import Cameras

if TYPE_CHECKING:
    from headforge.avatars.config import EngineConfig
    from headforge.avatars.engine import TrainingContext
    from headforge.avatars.run import RunAssets


@dataclass
class AvatarRender:
    """What an avatar renders for a batch of frames.

    rgb (B, H, W, 3) composited on the requested background; coverage (B, H, W) in [0, 1];
    normals (B, H, W, 3) camera-space unit normals (zero off the avatar) or None when not asked
    for; landmarks (B, L, 3) camera-space head-model landmarks or None. Methods add their own
    fields by subclassing (NHA: fragments, vertices, offsets).
    """

    rgb: torch.Tensor
    coverage: torch.Tensor
    landmarks: torch.Tensor | None = None
    normals: torch.Tensor | None = None


@dataclass
class Geometry:
    """An avatar's surface for evaluation, in camera space (metres, OpenCV).

    vertices (B, V, 3); faces (F, 3) long for a mesh, None for a point set; normals (B, V, 3)
    or None; face_vertices / head_vertices (V,) bool: the face and the head without the neck
    (what the geometry metrics score), or None when the method cannot tell; radius (B, V)
    world-space point radii (metres) for a point set (what a splat of it covers), else None;
    surfel_min_cos: a point set drawn as surfels (:func:`headforge.render.points.splat`'s
    ``min_cos``), 0 for screen-facing discs; hole_filling: the avatar's renders of the point set
    close the holes between its splats (PointAvatar's supp. 2.3), so the geometry protocol's
    normal maps do too.
    """

    vertices: torch.Tensor
    faces: torch.Tensor | None = None
    normals: torch.Tensor | None = None
    face_vertices: torch.Tensor | None = None
    head_vertices: torch.Tensor | None = None
    radius: torch.Tensor | None = None
    surfel_min_cos: float = 0.0
    hole_filling: bool = False


@dataclass
class Clip:
    """A driving clip for an animated export: ``sequence`` the avatar's frame parameters (T, ...)
    (its own fitted frames or a retargeted driver, :mod:`headforge.avatars.reenact`), ``fps``, and
    the clip's camera: intrinsics ``K`` (3, 3) pixels at ``resolution`` (square images)."""

    sequence: FrameParams
    fps: float
    K: torch.Tensor
    resolution: int


class Avatar(nn.Module):
    """Base of every method's avatar. ``frames`` holds the per-frame parameters of the run's
    dataset (``FRAME_KEYS`` -> (T, ...) parameters): training fits them, test-time fitting
    fits the held-out ones, reenactment replaces them."""

    frames: nn.ParameterDict

    def frame_params(self, rows: torch.Tensor) -> FrameParams:
        return {k: self.frames[k][rows] for k in self.frames}

    def render(self, params: FrameParams, cameras: Cameras, background: float = 1.0) -> AvatarRender:
        raise NotImplementedError

    def geometry(self, params: FrameParams) -> Geometry:
        raise NotImplementedError

    def export(self, output: Path, fmt: str, frames: list[int] | None = None, texture_size: int = 512,
               clip: Clip | None = None) -> list[Path]:
        """Write the avatar to ``output`` in ``fmt``; returns the files written. ``clip``: the
        sequence an animated format (glb, a PLY sequence) carries."""
        raise NotImplementedError

    def export_formats(self) -> tuple[str, ...]:
        return ()

    def load_weights(self, state: dict[str, torch.Tensor]) -> None:
        """Load a checkpoint's tensors. Methods whose parameters change size during training
        (pruning, upsampling) resize them to the checkpoint's first."""
        self.load_state_dict(state)


@dataclass
class Stage:
    """A phase of training: ``iterations`` steps that step the optimisers named in ``optimisers``."""

    name: str
    iterations: int
    optimisers: tuple[str, ...]


class Method:
    """A method: its config type, how to build its avatar, its stages, optimisers, energies
    and hooks. Subclasses override; the engine calls. ``name`` is the registry key."""

    name: ClassVar[str] = ""
    Config: ClassVar[type] = object

    def build(self, assets: "RunAssets", config: "EngineConfig") -> Avatar:
        raise NotImplementedError

    def stages(self, config: "EngineConfig") -> list[Stage]:
        raise NotImplementedError

    def optimisers(self, avatar: Avatar, config: "EngineConfig") -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def losses(self, avatar: Avatar, batch: dict, K: torch.Tensor, config: "EngineConfig", stage: str,
               params: FrameParams | None = None) -> dict[str, torch.Tensor]:
        """Weighted energy terms of one batch (:meth:`FrameData.batch`). ``stage``: a training
        stage's name, or ``align`` / ``align_rgb`` when the engine fits per-frame parameters
        (geometry-only terms, then with the photometric ones). ``params``: the batch's frame
        parameters (default: the avatar's rows for ``batch["index"]``)."""
        raise NotImplementedError

    def lr_factor(self, iteration: int, config: "EngineConfig") -> float:
        """Learning-rate multiple at ``iteration`` (a function of the iteration alone, so a
        resumed run gets the same rates)."""
        return 1.0

    # ---- hooks (defaults do nothing) -----------------------------------------------------------
    def before_iteration(self, ctx: "TrainingContext") -> None:
        """Called before every training step; may run method steps (NHA: per-frame alignment)
        and checkpoint through ``ctx``."""

    def after_iteration(self, ctx: "TrainingContext") -> bool:
        """Called after every step; returns True when it changed the set or size of the
        parameters (pruning, upsampling), so the engine rebuilds the optimisers."""
        return False

    def after_training(self, ctx: "TrainingContext") -> dict:
        """Called once after the last step, before the held-out frames are fitted (NHA: the
        soft matte); returns figures for metrics.json."""
        return {}

    def extra_scores(self, ctx: "TrainingContext") -> dict:
        """Method-specific figures for metrics.json, after the held-out frames are scored."""
        return {}

    def render_for_scoring(self, avatar: Avatar, params: FrameParams, cameras: Cameras, **options) -> AvatarRender:
        """The render the scoring protocol compares with the frames (default: ``render`` on white)."""
        return avatar.render(params, cameras, background=1.0, **options)


# SGD steps per frame parameter group, scaled so one step moves translation by ~0.1 mm and
# rotations by ~1e-3 rad at typical gradients. Not Adam: its momentum would keep moving the frames
# that are not in the batch.
FRAME_LR_SCALE = {"translation": 0.01, "root_pose": 0.1, "neck_pose": 0.1, "jaw_pose": 0.1, "eye_left_pose": 0.1,
                  "eye_right_pose": 0.1, "expression": 1.0}


def frame_optimiser(avatar: Avatar, lr: float) -> torch.optim.Optimizer:
    """The optimiser of the per-frame parameters during training (NHA's: SGD, rates scaled per group)."""
    return torch.optim.SGD([{"params": [avatar.frames[k]], "lr": lr * scale} for k, scale in FRAME_LR_SCALE.items()])


class RowAdam(torch.optim.SparseAdam):
    """Adam over the rows (frames) of per-frame parameters (T, D) that the step's loss touched,
    as a SparseAdam over embeddings: a frame outside the batch keeps its value and its moments,
    where dense Adam's momentum would move every frame at every step. Each dense gradient is
    turned into a sparse one of its non-zero rows before the step."""

    def step(self, closure=None):
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None and not p.grad.is_sparse:
                    rows = torch.nonzero(p.grad.flatten(1).abs().sum(1))[:, 0]
                    p.grad = torch.sparse_coo_tensor(rows[None], p.grad[rows], p.shape, check_invariants=True).coalesce()
        return super().step(closure)

