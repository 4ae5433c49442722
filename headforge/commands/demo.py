"""``headforge demo``: the main job end to end on the embedded default (:mod:`headforge.demo`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import Bars, console, progress


def demo(output: Path = typer.Option(Path("headforge-demo"), "-o", "--output", help="report folder"),
         video: Optional[Path] = typer.Option(None, help="use this video (first 300 frames) instead of a synthetic subject"),
         method: str = typer.Option("nha", help="nha (Neural Head Avatars), pointavatar, or headcraft (scans -> "
                                                "registration -> generative model -> samples -> eval)"),
         iterations: Optional[int] = typer.Option(None, help="training iterations (the quick preset's schedule, "
                                                             "scaled; default nha 900, pointavatar 1500, headcraft: "
                                                             "300 StyleGAN2 steps)"),
         device: str = typer.Option("auto", help="training device: auto (a CUDA GPU when there is one), cpu or cuda[:N]")) -> None:
    """Synth one small subject (or track --video) -> fit an avatar (quick) -> render val frames,
    a novel-view orbit and the turntable -> evaluate. Writes a report folder. ``--method headcraft``:
    generated scans -> registration -> StyleGAN2 + PCA -> sample sheets, animation -> Tables 1-2."""
    if method == "headcraft":
        _headcraft(output, video, iterations)
        return
    from headforge.demo import run_demo

    with Bars() as bars:
        metrics = run_demo(output, video, iterations, device, log=progress, progress_factory=bars.factory, method=method)
    export = "export/avatar.obj" if method == "nha" else "export/canonical.ply, avatar_relit.mp4"
    console.print(f"report written to {output}/ (metrics.md, avatar_val.mp4, avatar_orbit.mp4, {method}/progress.png, "
                  f"{export}, turntable.mp4, ...)")
    print(json.dumps(metrics))


def _headcraft(output: Path, video: Optional[Path], iterations: Optional[int]) -> None:
    from headforge.craft.demo import CraftDemoConfig, run_craft_demo
    from headforge.craft.pipeline import torch_threads
    from headforge.errors import HeadforgeError

    try:
        if video is not None:
            raise HeadforgeError("--video is for the avatar demos; --method headcraft generates its own scans")
        if iterations is not None and iterations < 1:
            raise HeadforgeError(f"--iterations must be positive, got {iterations}")
        torch_threads()
        config = CraftDemoConfig() if iterations is None else CraftDemoConfig(stylegan2_steps=iterations)
        metrics = run_craft_demo(output, config, log=progress)
    except HeadforgeError as exc:
        console.print(f"error: {exc}")
        raise typer.Exit(1)
    console.print(f"report written to {output}/ (metrics.md, eval.md, samples/sheet.png, samples_truncated/sheet.png, "
                  "interpolation/strip.png, animation.mp4, maps_train.png, run/)")
    print(json.dumps(metrics))
