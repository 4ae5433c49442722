"""``headforge view RUN|DATASET|MAP``: look at an avatar, a tracked dataset or a HeadCraft map in
the browser (a three.js page served on 127.0.0.1)."""

from __future__ import annotations

from pathlib import Path

import typer

from headforge.commands.common import console, progress


def view(path: Path = typer.Argument(..., help="a run folder, a tracked dataset or a HeadCraft map folder"),
         port: int = typer.Option(8765, help="port to serve on (0: any free port)"),
         host: str = typer.Option("127.0.0.1", help="address to bind; 0.0.0.0 shows it to your network"),
         texture_size: int = typer.Option(512, help="baked texture size of a mesh avatar, pixels"),
         max_frames: int = typer.Option(600, help="at most this many frames of the driving sequence")) -> None:
    """Serve a browser viewer: the avatar (or tracked head) over its frames, with play/pause,
    expression, jaw, neck and eye sliders, an orbit camera and (point avatars) the light."""
    from headforge.errors import HeadforgeError
    from headforge.viewer.scene import build_scene
    from headforge.viewer.server import ViewerServer

    if max_frames < 1 or texture_size < 8:
        raise HeadforgeError("need --max-frames >= 1 and --texture-size >= 8")
    progress(f"preparing {path}")
    scene = build_scene(path, texture_size, max_frames)
    server = ViewerServer(scene, host, port)
    if host not in ("127.0.0.1", "localhost", "::1"):
        console.print(f"[yellow]note:[/] serving on {host}: other machines on your network can see this avatar")
    console.print(f"viewer: [bold]{server.url}[/]  (Ctrl-C to stop)")
    print(server.url, flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
