"""NHA's settings (:class:`NHAConfig`): the engine's shared fields plus the method's own, with
the ``quick`` (CPU) and ``paper`` presets. Every deviation from the paper: docs/nha.md."""

from __future__ import annotations

from dataclasses import dataclass

from headforge.avatars.config import EngineConfig
from headforge.errors import HeadforgeError


@dataclass
class NHAConfig(EngineConfig):
    nonnegative_prefixes = ("w_", "laplacian_")

    resolution: int = 256
    subdivide: bool = True
    remove_lower_neck: bool = False  # True: App. A.1's cut; kept, the silhouette terms see the chin's outline (docs/nha_table1.md)
    embed_dim: int = 32
    geo_layers: int = 6
    geo_width: int = 128
    max_offset: float = 0.08
    tex_grid: int = 256
    tex_channels: int = 64
    tex_layers: int = 8
    tex_width: int = 256
    tex_mouth_grid: int = 64
    normal_channels: tuple[int, ...] = (128, 128, 32)
    tex_head_width: int = 128
    geometry_iters: int = 2000
    texture_iters: int = 2000
    joint_iters: int = 6000
    lr_geometry: float = 3e-4
    lr_texture: float = 5e-4
    lr_grid: float = 1e-2
    lr_frames: float = 1e-3
    lr_shape: float = 1e-4
    w_landmarks: float = 1.0
    w_eyelids: float = 1.0  # eye opening: upper-to-lower lid landmark offsets against the detections
    w_silhouette: float = 10.0
    w_contour: float = 1.0
    w_normal: float = 1.0  # NHA's E_normal on GT normal maps (--supervision gt); the paper gives no value
    w_normal_abs: float = 1.0  # beyond NHA (paper preset: 0): L1 of the normals against the GT maps (--supervision gt); bob 18.55 -> 14.22 deg (docs/nha_table1.md)
    w_classes: float = 5.0  # NHA's E_semantic on GT labels (--supervision gt): skin+neck, eyes, hair; as w_semantic
    semantic_classes: str = "labels"  # labels: voted from the GT labels (--supervision gt only); template: the head model's regions; bob 22.48 -> 19.12 deg (docs/nha_table1.md)
    w_semantic: float = 5.0  # face-oval region of the avatar vs the detected landmarks' face oval
    w_rgb: float = 20.0  # photometric L1 on the matted frame; 1 -> 20 took Table 1 from 15.86 to 14.67 deg (docs/nha_table1.md)
    w_ssim: float = 0.2
    w_laplacian: float = 1.0  # on offsets in mm, times the per-region weights
    laplacian_scalp: float = 0.1  # the scalp's region weight (the face's is 20); 1.0 and 0.02 lose on Table 1 (docs/nha_table1.md)
    laplacian_top_back_factor: float = 1.0  # times laplacian_scalp on the scalp's unseen top-back; 0.2 costs bob 2 deg (docs/nha_table1.md)
    laplacian_face_cut: bool = True  # the face's Laplacian ignores scalp neighbours: 17.48 -> 16.29 deg (docs/nha_table1.md)
    laplacian_scalp_shell: bool = False  # Laplacian on the hair's thickness, not its offset; worse on curly and bob (docs/nha_table1.md)
    laplacian_per_level: bool = True  # the umbrella Laplacian's input x laplacian_level_factor per subdivision level: the subdivided bob tore without (docs/nha_table1.md)
    laplacian_level_factor: float = 4.0  # 4: a smooth field costs what it costs on the tracked template (edges halve, squared norm)
    shading: bool = False  # beyond NHA: albedo x learned SH; costs talking_bun 1.07 dB at w_rgb 5, the hair does not flatten (docs/nha_table1.md)
    w_albedo_tv: float = 1.0  # L1 of the albedo's differences between neighbouring pixels (with shading only)
    w_offset_face: float = 0.01  # squared face offsets in mm^2
    w_offset_inner: float = 1.0  # squared offsets in mm^2 of the surfaces inside the head (eyeballs, eye cavities, mouth interior): they drifted through the face (docs/nha_table1.md)
    w_surface: float = 1.0
    w_edge: float = 10.0
    w_prior: float = 1e-3
    align_steps: int = 30  # per training frame after the geometry stage (0: off); 10 -> 30 +0.11 dB on talking_bun (docs/nha_figures.md)
    joint_limits: bool = True  # NHA's tanh joint limits (App. A.1) on the neck, jaw and eyes
    # App. A (paper preset): each field defaults to the quick preset's behaviour; NHAConfig.paper()
    # switches them all to the paper's. Side by side with the reasons: docs/nha.md, "Deviations".
    laplacian_regions: str = "headforge"  # headforge | table3 (App. Table 3's region weights, doubled in the joint stage)
    laplacian_operator: str = "uniform"  # uniform (umbrella) | cotangent (Laplace-Beltrami on the template, App. A.3)
    laplacian_norm: str = "squared"  # squared | l1 (App. A.3); the L1 subgradient drowned the hair signal (docs/nha.md)
    edge_mode: str = "template"  # template (ratio to each template edge) | mean (excess over 1.5x the mean edge, App. A.3)
    tex_last_width: int = 0  # width of T's last SIREN layer (0: tex_width); App. A.2.2: 128
    tex_mapping_width: int = 128  # T's mapping-network width; App. A.2.2: as G's, 256
    mouth_condition: str = "jaw3"  # jaw3 (jaw rotation + 3 inner-lip distances) | neck10 (global∘neck + 10, App. A.2.2)
    close_mouth: bool = False  # App. A.1: close FLAME's mouth hole (FLAME templates only; open-head has a mouth interior)
    tex_weight_decay: float = 0.0  # Adam weight decay of T's network (not its UV grids); NHA's code: 1e-4
    stage_epochs: tuple[int, ...] = ()  # (geometry, texture, joint) epochs (App. A.3: 150, 100, 50); (): the *_iters fields
    epoch_frames_cap: int = 750  # App. A.3: longer clips keep the iterations of a 750-frame clip
    early_stop_frames: int = 0  # joint stage: frames held back from the end of the training range (0: off)
    early_stop_every: int = 250  # iterations between two checks of the held-back frames' loss
    early_stop_patience: int = 2  # checks without improvement before the joint stage ends

    @classmethod
    def quick(cls) -> "NHAConfig":
        return cls(subdivide=False, geo_layers=4, geo_width=96, tex_grid=128, tex_channels=16, tex_layers=4,
                   tex_width=96, tex_mouth_grid=32, normal_channels=(16, 16, 16), tex_head_width=48,
                   # twice the 400 / 400 / 1200 of before 2026-12-07: Table 1 12.16 -> 11.34 deg, talking_bun
                   # 24.12 -> 24.16 dB (docs/nha_table1.md, "Table 1 at twice the schedule")
                   geometry_iters=800, texture_iters=800, joint_iters=2400, val_every=250,
                   tto_photometric_steps=0)

    @classmethod
    def paper(cls) -> "NHAConfig":
        """App. A's choices (docs/nha.md, "Deviations"); the iterations follow from ``stage_epochs``
        and the dataset (:meth:`schedule_for`, which ``headforge fit`` calls)."""
        return cls(resolution=512, laplacian_regions="table3", laplacian_operator="cotangent", laplacian_norm="l1",
                   laplacian_face_cut=False, edge_mode="mean", tex_last_width=128, tex_mapping_width=256,
                   mouth_condition="neck10", close_mouth=True, tex_weight_decay=1e-4, stage_epochs=(150, 100, 50),
                   early_stop_frames=8, w_normal_abs=0.0, laplacian_per_level=False)

    CHOICES = {"laplacian_regions": ("headforge", "table3"), "laplacian_operator": ("uniform", "cotangent"),
               "laplacian_norm": ("squared", "l1"), "edge_mode": ("template", "mean"),
               "mouth_condition": ("jaw3", "neck10"),
               "semantic_classes": ("template", "labels")}

    def check(self) -> None:
        """One-line errors for settings out of their range (the string choices, the epochs)."""
        for name, allowed in self.CHOICES.items():
            if getattr(self, name) not in allowed:
                raise HeadforgeError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if self.stage_epochs and (len(self.stage_epochs) != 3 or min(self.stage_epochs) < 1):
            raise HeadforgeError(f"stage_epochs must be three epoch counts >= 1 (geometry, texture, joint), got {self.stage_epochs}")

    def epoch_iterations(self, train_frames: int) -> tuple[int, int, int]:
        """(geometry, texture, joint) iterations of ``stage_epochs`` on ``train_frames`` training
        frames in batches of ``batch`` (frames beyond ``epoch_frames_cap`` add none, App. A.3)."""
        frames = min(train_frames, self.epoch_frames_cap)
        return tuple(max(1, round(e * frames / self.batch)) for e in self.stage_epochs)

    def schedule_for(self, train_frames: int) -> None:
        """With ``stage_epochs`` set, the stages' iterations for a dataset of ``train_frames``
        training frames; without, nothing changes."""
        self.check()
        if self.stage_epochs:
            self.geometry_iters, self.texture_iters, self.joint_iters = self.epoch_iterations(train_frames)

    def scale_schedule(self, iterations: int) -> None:
        """Rescale the three stages to ``iterations`` in total, keeping their proportions (with
        ``stage_epochs``: the epochs' proportions, which then no longer set the schedule)."""
        if iterations < 3:
            raise HeadforgeError(f"--iterations must be >= 3, got {iterations}")
        if self.stage_epochs:
            self.geometry_iters, self.texture_iters, self.joint_iters = self.stage_epochs
            self.stage_epochs = ()
        total = self.total_iters
        self.geometry_iters = max(1, round(iterations * self.geometry_iters / total))
        self.texture_iters = max(1, round(iterations * self.texture_iters / total))
        self.joint_iters = max(1, iterations - self.geometry_iters - self.texture_iters)

    @property
    def total_iters(self) -> int:
        return self.geometry_iters + self.texture_iters + self.joint_iters
