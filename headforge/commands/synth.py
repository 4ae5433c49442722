"""``headforge synth``: synthetic talking-head subjects with exact ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from headforge.commands.common import Bars, console, progress


def synth(output: Path = typer.Option(..., "-o", "--output", help="benchmark folder to write"),
          subjects: int = typer.Option(4, help="number of subjects"),
          train_frames: int = typer.Option(200, help="training frames per subject"),
          val_frames: int = typer.Option(210, help="validation frames per subject (unseen expressions/poses)"),
          resolution: int = typer.Option(512, help="image size in pixels"),
          seed: int = typer.Option(0, help="random seed (subjects and motion)"),
          gt_every: int = typer.Option(5, help="full ground truth (meshes, views, relit, albedo; normals and labels of validation frames) every N frames; every training frame has its normals, labels and landmarks"),
          supersample: int = typer.Option(2, help="anti-aliasing: render at N x N samples per pixel")) -> None:
    """Synthetic talking-head subjects (full anny body, hair, skin albedo) with exact ground truth,
    each written as a tracked headforge dataset plus gt/."""
    from headforge.bench.synthetic import SynthConfig, synthesize

    config = SynthConfig(subjects=subjects, train_frames=train_frames, val_frames=val_frames, resolution=resolution,
                         seed=seed, gt_every=gt_every, supersample=supersample)
    with Bars() as bars:
        report = synthesize(output, config, log=progress, progress_factory=bars.factory)
    console.print(f"benchmark written to {output}/ (contact_sheet.png, benchmark.json, subject_*/)")
    print(json.dumps({k: report[k] for k in ("render_seconds", "track_seconds", "total_seconds")}
                     | {"subjects": len(report["subjects"])}))
