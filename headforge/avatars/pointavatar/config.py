"""PointAvatar's settings: the engine's shared fields plus the method's own, with the ``quick``
(CPU) and ``paper`` presets. Every deviation from the paper and its code: docs/pointavatar.md."""

from __future__ import annotations

from dataclasses import dataclass

from headforge.avatars.config import EngineConfig
from headforge.errors import HeadforgeError


@dataclass
class PointAvatarConfig(EngineConfig):
    resolution: int = 256
    batch: int = 2
    iterations: int = 8000  # the authors' 63 epochs of 8-frame batches on a ~1000-frame clip
    # canonical cloud, coarse to fine (supp. 2.2)
    init_points: int = 400
    max_points: int = 409_600
    init_radius: float = 0.6  # initial sphere (and the SDF's initial zero set), normalised units (x 0.15 m)
    init_cloud: str = "sphere"  # sphere: the paper; head: on the canonical head model's surface (docs/pointavatar.md)
    init_point_radius: float = 0.0  # world radius (m) of the initial discs; 0: discs covering the sphere twice
    radius_factor: float = 0.75  # radius multiple at each doubling
    upsample_spread: float = 0.5  # half-width of the copies' uniform perturbation, in point radii (the authors' code)
    # beyond the paper, off in both presets: points added inside the canonical mouth at each doubling;
    # measured worse on talking_bun (AKD 4.09 -> 4.28 px; docs/pointavatar.md, deviation 15)
    mouth_seed: int = 0
    upsample_every: int = 625  # iterations between doublings (the authors' 5 epochs)
    prune_every: int = 125  # iterations between prunes (one epoch)
    # the authors' code keeps a point composited above 0.5 *or* nearest on some pixel; False: the
    # weight alone (the quick preset: deviation 18 in docs/pointavatar.md)
    prune_keeps_front: bool = True
    points_per_pixel: int = 10
    # 0: every point a screen-facing disc (the paper's PyTorch3D points); > 0: its tangent disc (a
    # surfel), foreshortened by |cos(normal, view ray)| clamped at this value, so the outline falls
    # at the points rather than a radius beyond them (docs/pointavatar.md, deviation 17)
    surfel_min_cos: float = 0.0
    # networks (supp. Fig. 3)
    canonical_width: int = 256
    canonical_layers: int = 9
    canonical_skip: int = 4
    frequencies: int = 6
    deformer_width: int = 128
    deformer_layers: int = 4
    shading_width: int = 64
    shading_layers: int = 2
    # headforge's deviation 12 (docs/pointavatar.md; quick: 64): albedo from a separate MLP with its
    # own, finer positional encoding; 0: albedo from the canonical network, as the paper
    albedo_width: int = 0
    albedo_layers: int = 3
    albedo_frequencies: int = 8
    # beyond the paper, off in both presets: an MLP of the frame's expression and jaw adding a change
    # to the albedo of the points near the canonical mouth (within about ``mouth_albedo_radius`` m of
    # the inner lips); on talking_bun within one seed's spread (docs/pointavatar.md, deviation 19)
    mouth_albedo_width: int = 0
    mouth_albedo_layers: int = 3
    mouth_albedo_radius: float = 0.015
    # the method's switches (the paper's ablations)
    jacobian_normals: bool = True  # False: normals by the blended skinning rotation only (Fig. 6, column 3)
    canonical_offset: bool = True  # False: points learnt directly in the head model's canonical space (Fig. 9)
    shading: str = "learned"  # learned: albedo x shading MLP; none: entangled colour MLP (Fig. 6, column 1)
    hole_filling: bool = True  # erode-then-dilate of renders outside training (supp. 2.3)
    eikonal_samples: int = 0  # points (and as many perturbed) in the Eikonal term; 0: all
    # optimisation (Eq. 11, supp. 2.2)
    lr: float = 1e-4
    lr_points: float = 1e-4
    lr_frames: float = 5e-4
    # the training frames' expressions refined with their poses (the authors' code); quick: held
    # (talking_bun AKD 4.45 -> 3.92 px; docs/pointavatar.md, deviation 16)
    refine_expression: bool = True
    # the training frames' poses and camera refined (the authors' code); quick: held where the tracker put them
    # (talking_bun: refined, the frames drifted 2.5 px from the detections; docs/pointavatar.md, deviation 21)
    refine_poses: bool = True
    w_rgb: float = 1.0
    w_mask: float = 1.0
    w_ssim: float = 0.0  # a weight-free stand-in for the VGG term (no pretrained weights here)
    # the head-model regulariser on mean squared errors (the authors' code): E and P in metres per
    # unit coefficient, where their 10 x 10 x 100 on FLAME's x4 units is 1.6e5; W (weights) 1
    w_flame: float = 1.0
    # the regulariser halves this many times, at every ``flame_halving_every`` of the iterations (the
    # authors' code: at epochs 10, 20, 30, 40 of 63), so the images shape the deformer late in training
    flame_halvings: int = 4
    flame_halving_every: float = 10 / 63
    # True: the pseudo ground truth may come from the head model's mouth and eye cavities too
    # (headforge before 2026-12-05); False: from its outer surface, as FLAME's (docs/pointavatar.md)
    pseudo_gt_inner: bool = False
    w_expr: float = 1.6e5
    w_pose: float = 1.6e5
    w_weights: float = 1.0
    w_sdf: float = 1.0
    w_eikonal: float = 0.1
    # beyond the paper (paper preset: 0): with --supervision gt, an L1 of the splatted normals
    # against the subject's GT normal maps, as NHA's quick preset (docs/pointavatar.md)
    w_normal_abs: float = 1.0
    # beyond the paper, off in both presets: with --supervision gt, an L1 of each visible point's
    # own normal against the GT normal at its pixel; tried for the normal consistency target and
    # measured worse (bob 0.890 -> 0.839: the deformer bends to turn the normals; docs/pointavatar.md, deviation 14)
    w_normal_points: float = 0.0
    # beyond the paper, off in both presets (the paper's frame fitting is RGB only): in the frame
    # fitting, the head model's landmarks at the frame's parameters (less the avatar's landmark
    # bias) against the detections (L1, px x 10 / resolution) and the eye opening, as NHA's; on
    # talking_bun they cost 4 dB of held-out PSNR (docs/pointavatar.md, deviation 13)
    w_landmarks: float = 0.0
    w_eyelids: float = 0.0
    # head_model: the terms above as described; avatar: on the avatar's own landmarks instead (the
    # canonical head model's, deformed by the avatar's deformer as its points are), in training too;
    # on talking_bun 2-4 dB worse, AKD within a seed's spread (docs/pointavatar.md, deviation 20)
    landmarks_through: str = "head_model"
    landmarks_oval: bool = True  # False: MediaPipe's 36 face-oval landmarks (the 2D outline) left out

    @classmethod
    def quick(cls) -> "PointAvatarConfig":
        """Sized by the measured cost per step (docs/pointavatar.md: 2 CPU threads, 256^2, 2 frames:
        0.38 s at 5K points, 1.2 s at 20K, 10 s at 100K with these networks; the paper's 4.3 / 13 /
        43 s): at most 6400 points, 3000 iterations, the Eikonal term on 2000 + 2000 samples; the
        albedo from its own 4 x 256 network with 10 encoding frequencies (deviation 12: a 3 x 64 one
        with 8 took talking_bun's AKD 4.93 -> 4.09 px, talking_longhair's 3.60 -> 2.35; 4 x 256 with
        10 took talking_bun's 4.43 -> 3.69 px, +0.4 dB, over two seeds, docs/pointavatar.md); the
        head-model regulariser halved 4 times as the authors' code (talking_bun AKD 4.09 -> 3.71 px);
        the deformer at the paper's 4 x 128 (3 x 64 until 2026-12-07: talking_bun AKD 3.69 -> 3.30 px,
        +0.25 dB); the training frames held where the tracker put them, poses and expressions
        (deviations 16 and 21: refined, they drifted 2.5 px from the detections; held, talking_bun AKD
        3.30 -> 2.76 px, head-only PSNR -0.5 dB, two seeds, docs/pointavatar.md); the prunes keep the
        points composited above 1/2 only (deviation 18: the short subject 0.9 dB and 0.65 deg better
        than with the authors' rule, the bob level)."""
        return cls(iterations=3000, max_points=6400, upsample_every=500, prune_every=250, points_per_pixel=6,
                   albedo_width=256, albedo_layers=4, albedo_frequencies=10,
                   canonical_width=64, canonical_layers=4, canonical_skip=2, frequencies=4, deformer_width=128,
                   deformer_layers=4, shading_width=32, eikonal_samples=2000, lr=5e-4, lr_points=5e-4,
                   val_every=500, checkpoint_every=250, tto_steps=50, tto_photometric_steps=0,
                   refine_expression=False, refine_poses=False, prune_keeps_front=False)

    @classmethod
    def paper(cls) -> "PointAvatarConfig":
        return cls(resolution=512, batch=8, w_normal_abs=0.0)

    @property
    def total_iters(self) -> int:
        return self.iterations

    def scale_schedule(self, iterations: int) -> None:
        """Rescale the schedule (doublings, prunes, validations) to ``iterations`` in total."""
        if iterations < 2:
            raise HeadforgeError(f"--iterations must be >= 2, got {iterations}")
        f = iterations / self.iterations
        self.iterations = iterations
        self.upsample_every = max(1, round(self.upsample_every * f))
        self.prune_every = max(1, round(self.prune_every * f))
        self.val_every = max(1, round(self.val_every * f))
        self.checkpoint_every = max(1, round(self.checkpoint_every * f))

    def validate(self) -> None:
        if not 0 <= self.surfel_min_cos <= 1:
            raise HeadforgeError(f"surfel_min_cos must be in [0, 1] (0: discs), got {self.surfel_min_cos}")
        if self.init_cloud not in ("sphere", "head"):
            raise HeadforgeError(f"init_cloud must be sphere or head, got {self.init_cloud!r}")
        if self.landmarks_through not in ("head_model", "avatar"):
            raise HeadforgeError(f"landmarks_through must be head_model or avatar, got {self.landmarks_through!r}")
        if self.shading not in ("learned", "none"):
            raise HeadforgeError(f"shading must be learned or none, got {self.shading!r}")
        if self.init_points < 1 or self.max_points < self.init_points:
            raise HeadforgeError(f"need 1 <= init_points <= max_points, got {self.init_points}, {self.max_points}")
        if self.flame_halvings < 0 or self.flame_halving_every <= 0:
            raise HeadforgeError(f"flame_halvings must be >= 0 and flame_halving_every > 0, got "
                                 f"{self.flame_halvings}, {self.flame_halving_every}")
        if self.mouth_albedo_width < 0 or self.mouth_albedo_radius <= 0:
            raise HeadforgeError(f"mouth_albedo_width must be >= 0 and mouth_albedo_radius > 0, got "
                                 f"{self.mouth_albedo_width}, {self.mouth_albedo_radius}")
        if min(self.lr, self.lr_points, self.lr_frames) <= 0:
            raise HeadforgeError(f"lr, lr_points and lr_frames must be > 0 (torch's Adam refuses 0), "
                                 f"got {self.lr}, {self.lr_points}, {self.lr_frames}")
        if self.upsample_spread < 0 or self.mouth_seed < 0:
            raise HeadforgeError(f"upsample_spread and mouth_seed must be >= 0, got {self.upsample_spread}, {self.mouth_seed}")
