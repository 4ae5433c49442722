"""``headforge eval``: image metrics between folders, geometry against a synth subject's ground
truth, or the scoring protocol of a trained run's held-out frames."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import console, progress
from headforge.errors import HeadforgeError


def evaluate(pred: Path = typer.Argument(..., help="predicted images, or a tracked dataset / geometry folder"),
             gt: Path = typer.Argument(..., help="ground-truth images (same file names), or a headforge synth subject"),
             masks: Optional[Path] = typer.Option(None, help="folder of masks (same names) for masked metrics"),
             split: str = typer.Option("val", help="geometry mode: val, train or all ground-truth frames"),
             every: int = typer.Option(1, help="geometry mode: use every N-th ground-truth frame"),
             reference: Optional[Path] = typer.Option(
                 None, help="geometry mode: another prediction (e.g. the tracked dataset); adds both normal "
                            "errors on the pixels both cover (paired_*)"),
             protocol: bool = typer.Option(False, "--protocol", help="a run folder against a synth subject: the "
                                                                      "image scoring protocol instead of geometry"),
             output: Path = typer.Option(Path("eval"), "-o", "--output", help="report folder"),
             as_json: bool = typer.Option(False, "--json", help="print the mean metrics as one JSON object")) -> None:
    """Image metrics (L1, PSNR, SSIM, MS-SSIM, CPBD; LPIPS when its weights exist) between two
    folders; or, when GT is a synth subject, geometry metrics (normal angle error, one-sided
    Hausdorff full head / face in mm, normal consistency) of a tracked dataset or exported geometry
    (a mesh, or a point avatar's point set: its points splatted for the normal maps);
    with --reference, also the normal errors of both predictions on the pixels both cover; or,
    when PRED is a run folder of headforge fit and GT its dataset (not a synth subject, or with
    --protocol), the scoring protocol of its held-out frames (metrics.json, metrics.md, val_worst.png)."""
    is_run = (pred / "run.json").is_file() or (pred / "config.json").is_file()
    if is_run and (protocol or not (gt / "gt" / "geometry.safetensors").is_file()):
        from headforge.avatars.engine import evaluate_run

        summary = evaluate_run(pred, gt, output, log=progress)
        if as_json:
            print(json.dumps(summary))
        else:
            console.print((output / "metrics.md").read_text())
        return
    if (gt / "gt" / "geometry.safetensors").is_file():
        from headforge.metrics.benchmark import evaluate_geometry, paired_normal_error, write_geometry_report

        if every < 1:
            raise HeadforgeError(f"--every must be >= 1, got {every}")
        # the pair first: it is the quick part, so a wrong --reference fails before the long one
        pair = {} if reference is None else paired_normal_error(pred, reference, gt, split=split, every=every)["mean"]
        result = evaluate_geometry(pred, gt, split=split, every=every)
        result["mean"] |= {f"paired_{k}": v for k, v in pair.items()}
        write_geometry_report(result, output)
        summary = {"frames": result["frames"], "kind": result["kind"], "hair": result["hair"], **result["mean"]}
    else:
        from headforge.metrics.evaluate import evaluate_folders, write_report

        if reference is not None:
            raise HeadforgeError(f"--reference needs a headforge synth subject as GT (geometry mode); {gt} has no gt/")
        result = evaluate_folders(pred, gt, masks)
        write_report(result, output)
        summary = {"images": result["images"], **result["mean"]}
    if as_json:
        print(json.dumps(summary))
    else:
        console.print((output / "metrics.md").read_text())
