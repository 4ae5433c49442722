"""Settings every method's config shares (the engine's), and the ``--set FIELD=VALUE`` parser.
A method's config dataclass subclasses :class:`EngineConfig` and adds its own fields."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from headforge.errors import HeadforgeError


@dataclass
class EngineConfig:
    resolution: int = 256  # training and evaluation image size (px)
    batch: int = 2  # frames per training step
    checkpoint_every: int = 200  # iterations between checkpoints (a killed run resumes from the last)
    val_every: int = 500  # iterations between in-training validations (progress.png)
    val_frames: int = 4  # held-out frames of an in-training validation
    lr_align: float = 6e-3  # per-frame fitting: Adam on rotations (rad) and expression; translation (m) gets a tenth
    tto_steps: int = 100  # test-time fitting steps per held-out frame (talking_bun: 30/60/100 -> +0/0.14/0.19 dB)
    tto_photometric_steps: int = 10  # then with the photometric terms added
    val_tto_steps: int = 30  # the same fitting for the in-training validation, kept short
    lr_decay_start: float = 0.7  # fraction of the iterations after which all learning rates decay...
    lr_final: float = 0.1  # ...along a half cosine to this multiple at the end (1: constant rates)
    seed: int = 0
    supervision: str = "predicted"  # gt: a synth subject's GT normals, labels, landmarks on the training frames (NHA Sec. 4.1)

    nonnegative_prefixes = ("w_",)  # fields that are energy weights: < 0 would reward the error

    @classmethod
    def quick(cls) -> "EngineConfig":
        return cls()

    @classmethod
    def paper(cls) -> "EngineConfig":
        return cls()

    @classmethod
    def preset(cls, name: str) -> "EngineConfig":
        if name not in ("quick", "paper"):
            raise HeadforgeError(f"--preset must be quick or paper, got {name!r}")
        return cls.quick() if name == "quick" else cls.paper()

    @property
    def total_iters(self) -> int:
        raise NotImplementedError

    def scale_schedule(self, iterations: int) -> None:
        raise HeadforgeError(f"{type(self).__name__} has no --iterations scaling")

    def schedule_for(self, train_frames: int) -> None:
        """Fit a schedule given per epoch to a dataset of ``train_frames`` training frames (a
        method's config may; by default the schedule is in iterations and nothing changes)."""

    def override(self, assignment: str) -> None:
        """Set one field from ``"name=value"`` (the value parsed as the field's current type;
        tuples as comma-separated ints), e.g. ``"tex_grid=256"`` or ``"normal_channels=32,32,16"``."""
        name, sep, text = assignment.partition("=")
        name = name.strip()
        if not sep or name not in {f.name for f in fields(self)}:
            raise HeadforgeError(f"--set expects FIELD=VALUE with a {type(self).__name__} field, got {assignment!r}")
        current = getattr(self, name)
        try:
            if isinstance(current, bool):
                if text.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(text)
                value = text.lower() in ("true", "1")
            elif isinstance(current, tuple):
                value = tuple(int(v) for v in text.split(","))
            else:
                value = type(current)(text)
        except ValueError:
            raise HeadforgeError(f"--set {name}: {text!r} is not a {type(current).__name__}") from None
        if name.startswith(self.nonnegative_prefixes) and isinstance(value, float) and value < 0:
            raise HeadforgeError(f"--set {name}: an energy weight must be >= 0, got {value}")
        setattr(self, name, value)

    @classmethod
    def from_saved(cls, saved: dict, source: Path) -> "EngineConfig":
        """The config recorded in ``source``; settings this version lacks are refused, settings
        added since take their default."""
        unknown = sorted(set(saved) - {f.name for f in fields(cls)})
        if unknown:
            raise HeadforgeError(f"{source} was written by another headforge version (unknown settings {', '.join(unknown)})")
        defaults = cls()
        values = {k: tuple(v) if isinstance(getattr(defaults, k), tuple) else v for k, v in saved.items()}
        return cls(**values)
