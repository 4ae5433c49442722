"""``headforge track``: a video or folder of frames -> a tracked headforge dataset."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import FLAME_OPT, MODEL_OPT, Bars, console, progress


def track(video: Path = typer.Argument(..., help="a video with one face (mp4, mov, ...) or a folder of frames"),
          output: Path = typer.Option(..., "-o", "--output", help="dataset folder to write"),
          model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
          resolution: int = typer.Option(512, help="crop size in pixels"),
          every: int = typer.Option(1, help="keep every N-th frame"),
          max_frames: Optional[int] = typer.Option(None, help="stop after this many kept frames"),
          val_fraction: float = typer.Option(0.2, help="last fraction of frames held out for validation"),
          preset: str = typer.Option("quick", help="quick (CPU) or paper"),
          focal: Optional[float] = typer.Option(None, help="known focal length in crop pixels (default: estimated)"),
          crop: str = typer.Option("face", help="face: a smooth window around the face; full: the whole square frame"),
          masks: Optional[Path] = typer.Option(None, help="folder of foreground masks named like the frames "
                                                          "(default: MediaPipe selfie segmentation)"),
          photometric: bool = typer.Option(False, help="refine the landmark fit against the crops with the "
                                                        "renderer (shading + silhouette; slower, better shape)"),
          fps: Optional[float] = typer.Option(None, help="the source's frame rate (default: the video's own; "
                                                           "30 for a folder of frames)"),
          overlay: bool = typer.Option(True, help="write overlay.mp4 (landmarks + model wireframe)")) -> None:
    """Preprocess a video or a folder of frames (crops, masks, landmarks) and track the head model in it."""
    from headforge.track.pipeline import TrackOptions, track_video

    options = TrackOptions(model, flame_dir, resolution, every, max_frames, val_fraction, preset, overlay, focal,
                           crop, None if masks is None else str(masks), photometric, fps)
    with Bars() as bars:
        metrics = track_video(video, output, options, log=progress, progress_factory=bars.factory)
    console.print(f"dataset written to {output}/ (dataset.json, frames/, masks/, overlay.mp4, metrics.json)")
    print(json.dumps(metrics))
