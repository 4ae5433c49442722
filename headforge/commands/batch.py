"""``headforge batch track|fit``: one job per video or dataset of a folder, in-process or on Ray.

Built on :mod:`headforge.batch` (per-item isolation, resume, Ray as an optional backend). The
output folder holds one finished item per name (``OUT/<name>/``: a dataset for ``track``, a run
folder for ``fit``), ``_failed/<name>.json`` (the one-line error and the traceback),
``_logs/<name>.log`` (the item's own progress lines), ``summary.json`` and ``summary.md``.
The item functions are module-level so that Ray workers can import them.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import FLAME_OPT, MODEL_OPT, console
from headforge.errors import HeadforgeError

app = typer.Typer(help="Run track or fit over every video or dataset of a folder (in-process, or on Ray).",
                  no_args_is_help=True)

TRACK_COLUMNS = ("frames_valid", "landmark_median_px", "track_seconds")
FIT_COLUMNS = ("val_psnr", "val_psnr_head", "val_akd_px", "train_minutes")

RAY_OPT = typer.Option(False, "--ray", help="run the items as tasks on a local Ray runtime (pip install 'headforge\\[ray]')")
ADDRESS_OPT = typer.Option(None, "--ray-address", help="an existing Ray cluster, host:port or ray://host:port (implies --ray)")
CPUS_OPT = typer.Option(1.0, "--cpus-per-item", help="CPUs per item: Ray's request, and the item's torch threads")
GPUS_OPT = typer.Option(0.0, "--gpus-per-item", help="GPUs per item (Ray's request; fractions share a GPU)")
RAY_CPUS_OPT = typer.Option(None, "--ray-cpus", help="CPUs of a local Ray runtime (default: the machine's)")
WORKERS_OPT = typer.Option(1, "--workers", help="run N items at a time in local processes (no Ray needed)")


def _logger(output: Path, key: str):
    """Progress lines of one item, appended to ``output/_logs/<key>.log`` (items run side by side)."""
    import time

    path = output / "_logs" / f"{key}.log"
    path.parent.mkdir(parents=True, exist_ok=True)

    def log(message: str) -> None:
        with path.open("a") as f:
            f.write(f"{time.strftime('%H:%M:%S')} {message}\n")

    return log


def _threads(cpus: float) -> None:
    """A Ray worker starts before its item is known: cap its threads at the item's CPUs."""
    from headforge.devices import limit_threads

    limit_threads(cpus)


def track_item(key: str, payload: dict, workdir: Path) -> dict:
    """Track ``payload["video"]`` into ``workdir`` (the dataset); returns the tracking metrics."""
    from headforge.track.pipeline import TrackOptions, track_video

    _threads(payload["cpus"])
    options = TrackOptions(**payload["options"])
    return track_video(payload["video"], workdir, options, log=_logger(workdir.parent, key))


def fit_item(key: str, payload: dict, workdir: Path) -> dict:
    """Train ``payload["method"]`` on ``payload["dataset"]`` into ``workdir`` (the run folder;
    a partial run left by a killed batch resumes); returns metrics.json's figures."""
    from headforge.avatars import registry
    from headforge.avatars.engine import fit
    from headforge.commands.fit import make_config
    from headforge.devices import resolve_device

    _threads(payload["cpus"])
    method = registry.get(payload["method"])
    config = make_config(method, payload["preset"], payload["iterations"], payload["resolution"], payload["set"],
                         payload["dataset"])
    return fit(method, payload["dataset"], workdir, config, log=_logger(workdir.parent, key),
               device=resolve_device(payload["device"]))


def list_videos(folder: Path) -> list[tuple[str, Path]]:
    """(name, path) of the videos in ``folder`` (by suffix, sorted; hidden files skipped)."""
    from headforge.data.video import VIDEO_SUFFIXES

    if not folder.is_dir():
        raise HeadforgeError(f"{folder} is not a folder")
    videos = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES and not p.name.startswith(".")]
    if not videos:
        raise HeadforgeError(f"no videos in {folder} (looked for {', '.join(sorted(VIDEO_SUFFIXES))})")
    return [(p.stem, p) for p in videos]


def list_datasets(folder: Path) -> list[tuple[str, Path]]:
    """(name, path) of the datasets in ``folder``: its sub-folders with a dataset.json (sorted)."""
    if not folder.is_dir():
        raise HeadforgeError(f"{folder} is not a folder")
    found = [p for p in sorted(folder.iterdir())
             if p.is_dir() and not p.name.startswith((".", "_")) and (p / "dataset.json").is_file()]
    if not found:
        raise HeadforgeError(f"no datasets in {folder} (sub-folders with a dataset.json, as headforge track writes)")
    return [(p.name, p) for p in found]


def _run(items, fn, output: Path, columns, ray: bool, ray_address, cpus: float, gpus: float, ray_cpus,
         keep_partial: bool, workers: int = 1) -> None:
    from headforge.batch import run_batch, summary_table

    if cpus <= 0:
        raise HeadforgeError(f"--cpus-per-item must be > 0, got {cpus:g}")
    if gpus < 0:
        raise HeadforgeError(f"--gpus-per-item must be >= 0, got {gpus:g}")
    result = run_batch(items, fn, output, ray=ray, ray_address=ray_address, num_cpus=ray_cpus, cpus_per_item=cpus,
                       gpus_per_item=gpus, keep_partial=keep_partial, columns=columns, workers=workers,
                       log=lambda m: console.print(m, markup=False, highlight=False))
    typer.echo(summary_table(result, columns))
    skipped = sum(r.status == "skipped" for r in result.items)
    console.print(f"{len(result.ok) - skipped} done, {len(result.failed)} failed, {skipped} skipped (finished earlier) "
                  f"in {result.wall_seconds:.1f} s (the items took {result.item_seconds:.1f} s added up); "
                  f"{output / 'summary.md'}", markup=False, highlight=False)
    if not result.ok:
        raise HeadforgeError(f"no item of the batch succeeded (errors in {output / 'summary.md'})")


@app.command("track")
def track(videos: Path = typer.Argument(..., help="folder of videos (mp4, mov, ...); one dataset per video"),
          output: Path = typer.Option(..., "-o", "--output", help="folder for the datasets (resumed when it exists)"),
          model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
          resolution: int = typer.Option(512, help="crop size in pixels"),
          every: int = typer.Option(1, help="keep every N-th frame"),
          max_frames: Optional[int] = typer.Option(None, help="stop after this many kept frames"),
          preset: str = typer.Option("quick", help="quick (CPU) or paper"),
          photometric: bool = typer.Option(False, help="refine the fit against the pixels (slower)"),
          overlay: bool = typer.Option(True, help="write overlay.mp4 in each dataset"),
          ray: bool = RAY_OPT, ray_address: Optional[str] = ADDRESS_OPT, cpus_per_item: float = CPUS_OPT,
          gpus_per_item: float = GPUS_OPT, ray_cpus: Optional[int] = RAY_CPUS_OPT, workers: int = WORKERS_OPT) -> None:
    """Track every video of a folder (headforge track per video) into OUT/NAME/, with OUT/summary.md.
    A failing video is reported and never stops the others; a re-run skips the finished ones."""
    from headforge.track.pipeline import TrackOptions

    options = TrackOptions(model, flame_dir, resolution, every, max_frames, preset=preset, overlay=overlay,
                           photometric=photometric)
    options.validate()  # a bad option fails once, before any item
    items = [(k, {"video": str(p.resolve()), "options": asdict(options), "cpus": cpus_per_item})
             for k, p in list_videos(videos)]
    _run(items, track_item, output, TRACK_COLUMNS, ray, ray_address, cpus_per_item, gpus_per_item, ray_cpus, False, workers)


@app.command("fit")
def fit(method: str = typer.Argument(..., help="avatar method: nha or pointavatar"),
        datasets: Path = typer.Argument(..., help="folder of datasets (e.g. the output of headforge batch track)"),
        output: Path = typer.Option(..., "-o", "--output", help="folder for the run folders (resumed when it exists)"),
        preset: str = typer.Option("quick", help="quick (CPU) or paper"),
        iterations: Optional[int] = typer.Option(None, help="scale the method's schedule to this many iterations"),
        resolution: Optional[int] = typer.Option(None, help="training resolution (default: preset's)"),
        device: str = typer.Option("auto", help="auto, cpu or cuda[:N] (on Ray: the GPU Ray gives the item)"),
        set_: Optional[list[str]] = typer.Option(None, "--set", metavar="FIELD=VALUE", help="override a config field"),
        ray: bool = RAY_OPT, ray_address: Optional[str] = ADDRESS_OPT, cpus_per_item: float = CPUS_OPT,
        gpus_per_item: float = GPUS_OPT, ray_cpus: Optional[int] = RAY_CPUS_OPT, workers: int = WORKERS_OPT) -> None:
    """Train one avatar per dataset of a folder (headforge fit per dataset) into OUT/NAME/, with
    OUT/summary.md. A killed batch resumes its unfinished runs where they stopped."""
    from headforge.avatars import registry
    from headforge.commands.fit import make_config

    make_config(registry.get(method), preset, iterations, resolution, set_ or [])  # bad settings fail up front
    if not (ray or ray_address):
        from headforge.devices import resolve_device

        resolve_device(device)
    payload = {"method": method, "preset": preset, "iterations": iterations, "resolution": resolution,
               "set": set_ or [], "device": device, "cpus": cpus_per_item}
    items = [(k, {**payload, "dataset": str(p.resolve())}) for k, p in list_datasets(datasets)]
    _run(items, fit_item, output, FIT_COLUMNS, ray, ray_address, cpus_per_item, gpus_per_item, ray_cpus, True, workers)
