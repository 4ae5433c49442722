"""Shared timing helper for the benchmark scripts."""

from __future__ import annotations

import statistics
import time


def timed(fn, repeats: int, warmup: int = 1) -> float:
    """Median wall-clock milliseconds of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - start))
    return statistics.median(times)


def render_fps(run, device, repeats: int = 10) -> float:
    """Frames per second of a loaded run's avatar (:func:`headforge.avatars.run.load_run`)
    rendering its first held-out frame at the training resolution on ``device``; the warm-up
    render fills what an avatar caches between frames of a sequence."""
    import torch

    from headforge.render.camera import Cameras

    avatar, res = run.avatar, run.config.resolution
    params = avatar.frame_params(torch.tensor(run.assets.rows("val")[:1], device=device))
    cams = Cameras.at_origin(run.assets.intrinsics(res).to(device), 1, res)

    def render() -> None:
        avatar.render(params, cams)
        if device.type == "cuda":
            torch.cuda.synchronize()

    with torch.no_grad():
        return round(1000 / timed(render, repeats=repeats), 2)
