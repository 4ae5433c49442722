"""``headforge export RUN -o OUT``: the avatar in standard formats, from the run folder alone."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.errors import HeadforgeError


def parse_frames(text: str) -> list[int]:
    """``"0,10,20"`` or ``"0-99"`` (or a mix) -> frame indices."""
    try:
        wanted = []
        for part in text.split(","):
            a, _, b = part.partition("-")
            wanted += list(range(int(a), int(b) + 1)) if b else [int(a)]
        return wanted
    except ValueError:
        raise HeadforgeError(f"--frames must look like 0,10,20 or 0-99, got {text!r}") from None


def export(run: Path = typer.Argument(..., help="a run folder of headforge fit"),
           output: Path = typer.Option(..., "-o", "--output", help="folder to write"),
           fmt: str = typer.Option("obj", "--format", help="obj, ply or glb (meshes; what a method offers)"),
           frames: Optional[str] = typer.Option(None, help="also export these tracked frames, e.g. 0,10,20 or 0-99"),
           texture_size: int = typer.Option(512, help="baked texture size in pixels"),
           driving: Optional[Path] = typer.Option(None, help="glb: the animation's clip, a tracked dataset or a Live "
                                                             "Link Face CSV (default: the run's own frames)"),
           driving_mode: str = typer.Option("relative", help="a tracked --driving dataset: relative (NHA App. B.1) "
                                                             "or absolute, as in render avatar"),
           driving_neutral: int = typer.Option(0, help="relative driving: the driving dataset's neutral frame"),
           max_frames: Optional[int] = typer.Option(None, help="at most this many frames of the animation")) -> None:
    """Export the avatar (neutral and per frame) with its baked texture; glb: animatable (skin,
    expression morph targets, an animation of the driving clip)."""
    from headforge.avatars.base import Clip
    from headforge.avatars.reenact import driving_clip, truncate
    from headforge.avatars.run import load_run

    if texture_size < 8:
        raise HeadforgeError(f"--texture-size must be >= 8, got {texture_size}")
    r = load_run(run)
    formats = r.avatar.export_formats()
    if fmt not in formats:
        raise HeadforgeError(f"--format must be one of {', '.join(formats)} for a {r.method.name} avatar, got {fmt!r}")
    animated = {}
    if fmt == "glb" or driving is not None:  # an animation (glb) or a PLY sequence (point avatars)
        seq, fps = driving_clip(r.avatar, r.assets, driving, "all", driving_mode, driving_neutral)
        seq = truncate(seq, max_frames)
        if seq["translation"].shape[0] == 0:
            raise HeadforgeError("the driving clip has no frames")
        animated["clip"] = Clip(seq, fps, r.assets.intrinsics(r.config.resolution), r.config.resolution)
    written = r.avatar.export(output, fmt, parse_frames(frames) if frames else None, texture_size, **animated)
    print(json.dumps({"output": str(output), "files": [str(p) for p in written]}))
