"""``headforge render``: the head model turning, and avatars reenacted or seen from new views."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import FLAME_OPT, MODEL_OPT, load_model
from headforge.errors import HeadforgeError

app = typer.Typer(help="Render head models and avatars to PNG/MP4.", no_args_is_help=True)


@app.command("turntable")
def turntable(output: Path = typer.Option(..., "-o", "--output", help="MP4 to write (a PNG of frame 0 beside it)"),
              model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
              frames: int = typer.Option(60, help="number of frames (one full turn)"),
              resolution: int = typer.Option(256, help="height of each panel in pixels"),
              points: int = typer.Option(100_000, help="surface points for the point panel"),
              fps: float = typer.Option(30.0)) -> None:
    """The head model turning: mesh path (shaded) | point path (coloured by normal)."""
    from headforge.head.turntable import write_turntable

    if frames < 1 or resolution < 16 or points < 1 or fps <= 0:
        raise HeadforgeError("need --frames >= 1, --resolution >= 16, --points >= 1 and --fps > 0")
    head = load_model(model, flame_dir)
    start = time.perf_counter()
    png = write_turntable(head, output, frames, resolution, points, fps)
    seconds = time.perf_counter() - start
    print(json.dumps({"output": str(output), "preview": str(png), "frames": frames,
                      "seconds": round(seconds, 2), "frames_per_second": round(frames / seconds, 2)}))


@app.command("avatar")
def avatar(run: Path = typer.Argument(..., help="a run folder of headforge fit"),
           output: Path = typer.Option(..., "-o", "--output", help="MP4 to write"),
           driving: Optional[Path] = typer.Option(None, help="dataset whose tracked expressions/poses drive the avatar, "
                                                             "or a Live Link Face CSV of ARKit blendshapes"),
           driving_mode: str = typer.Option("relative", help="a tracked --driving dataset: relative (NHA App. B.1: its "
                                                             "change from its neutral frame added to the avatar's "
                                                             "first frame) or absolute (its own values)"),
           driving_neutral: int = typer.Option(0, help="relative driving: the driving dataset's neutral frame "
                                                       "(position among its valid frames)"),
           orbit: bool = typer.Option(False, help="orbit the camera around the head (novel views)"),
           split: str = typer.Option("val", help="frames of the run's own dataset when not driven: train, val or all"),
           max_frames: Optional[int] = typer.Option(None, help="at most this many frames"),
           light: Optional[str] = typer.Option(None, help="relight (point avatars): a direction X,Y,Z toward the light "
                                                          "(Lambert on the learned albedo; head axes: x the subject's "
                                                          "left, y up, z to the camera), rotate:DEGREES (the learned "
                                                          "shading, light turned) or a file of 9x3 SH coefficients"),
           fps: Optional[float] = typer.Option(None, help="frame rate of the video (default: the driving clip's)")) -> None:
    """Reenactment, novel views and relighting of a trained avatar, from the run folder alone."""
    from headforge.avatars.reenact import driving_clip, render_sequence, truncate
    from headforge.avatars.run import load_run
    from headforge.render.io import write_mp4

    if fps is not None and fps <= 0:
        raise HeadforgeError(f"--fps must be > 0, got {fps}")
    options = {}
    if light is not None:
        from headforge.render.shading import parse_light

        options["light"] = parse_light(light)
    r = load_run(run)
    if options and not getattr(r.avatar, "relightable", False):
        raise HeadforgeError(f"--light: {r.method.name} avatars cannot be relit (PointAvatar's can)")
    seq, clip_fps = driving_clip(r.avatar, r.assets, driving, split, driving_mode, driving_neutral)
    fps = fps or clip_fps
    seq = truncate(seq, max_frames)
    T = seq["translation"].shape[0]
    if T == 0:
        raise HeadforgeError(f"no frames to render ({'the driving dataset' if driving else 'split ' + split} is empty)")
    K = r.assets.intrinsics(r.config.resolution)
    write_mp4(output, render_sequence(r.avatar, K, r.config.resolution, seq, orbit=orbit, options=options), fps=fps, total=T,
              description=f"rendering {T} frames")
    print(json.dumps({"output": str(output), "frames": T}))
