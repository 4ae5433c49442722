"""``headforge fit METHOD DATASET -o RUN``: train any registered avatar method on the engine."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import Bars, console, progress
from headforge.errors import HeadforgeError


def make_config(method, preset: str, iterations: Optional[int], resolution: Optional[int], assignments: list[str],
                dataset: Optional[Path] = None):
    """The method's config: a preset, then ``--resolution``, ``--iterations`` and ``--set``; with
    ``dataset``, a schedule given in epochs (NHA's ``paper`` preset) turned into iterations of its
    training frames (``config.schedule_for``)."""
    config = method.Config.preset(preset)
    if resolution is not None:
        if resolution < 64:
            raise HeadforgeError(f"--resolution must be >= 64, got {resolution}")
        config.resolution = resolution
    if iterations is not None:
        config.scale_schedule(iterations)
    for assignment in assignments:
        config.override(assignment)
    if dataset is not None:
        from headforge.avatars.run import RunAssets

        config.schedule_for(len(RunAssets.from_dataset(Path(dataset)).rows("train")))
    return config


def fit(method: str = typer.Argument(..., help="avatar method: nha or pointavatar"),
        dataset: Path = typer.Argument(..., help="a dataset written by headforge track or synth"),
        output: Path = typer.Option(..., "-o", "--output", help="run folder (resumed when it exists)"),
        preset: str = typer.Option("quick", help="quick (CPU) or paper (the paper's sizes and choices, e.g. NHA's App. A; for a GPU)"),
        iterations: Optional[int] = typer.Option(None, help="scale the method's schedule to this many iterations"),
        resolution: Optional[int] = typer.Option(None, help="training resolution (default: preset's)"),
        device: str = typer.Option("auto", help="auto (a CUDA GPU when there is one), cpu or cuda[:N]"),
        supervision: str = typer.Option("predicted", help="predicted: what a real clip gives (detected landmarks, "
                                        "masks); gt: a headforge synth subject's ground-truth normal maps, labels and "
                                        "landmarks supervise the training frames (NHA's synthetic protocol)"),
        set_: Optional[list[str]] = typer.Option(None, "--set", metavar="FIELD=VALUE",
                                                 help="override a config field, e.g. --set tex_grid=256 (repeatable)")) -> None:
    """Train an avatar (nha: Neural Head Avatars -- geometry MLP offsets + neural texture on the tracked
    head model; pointavatar: PointAvatar -- a deformable point cloud with albedo x learned shading).
    Over several processes: ``torchrun --nproc-per-node N -m headforge.cli fit ...`` (each rank trains
    on its share of every batch; gloo on the CPU, NCCL on CUDA GPUs, one GPU per process)."""
    from headforge import distributed
    from headforge.avatars import registry
    from headforge.avatars.engine import fit as run_fit

    from headforge.devices import resolve_device

    m = registry.get(method)
    resolve_device(device)  # an unusable --device is named before the dataset is read
    config = make_config(m, preset, iterations, resolution, [f"supervision={supervision}", *(set_ or [])], dataset)
    target = distributed.init_from_environment(device)  # the device as asked when not under torchrun
    try:
        if distributed.is_main():
            if distributed.active():
                progress(f"training over {distributed.world_size()} processes ({target} on rank 0)")
            with Bars() as bars:
                metrics = run_fit(m, dataset, output, config, log=progress,
                                  progress=bars.factory("training", config.total_iters), device=target)
            console.print(f"run written to {output}/ (checkpoint, progress.png, val/, val_worst.png, metrics.json)")
            print(json.dumps(metrics))
        else:
            try:
                run_fit(m, dataset, output, config, log=progress, device=target)
            except HeadforgeError:
                raise typer.Exit(1) from None  # the same one-line error: rank 0 prints it
    finally:
        distributed.shutdown()
