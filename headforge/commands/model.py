"""``headforge model``: build, inspect and fit the parametric head models."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from headforge.commands.common import FLAME_OPT, MODEL_OPT, console, load_model, progress
from headforge.errors import HeadforgeError

app = typer.Typer(help="Parametric head models: build, inspect, fit to a photo.", no_args_is_help=True)


@app.command("info")
def info(model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
         as_json: bool = typer.Option(False, "--json", help="print one JSON object")) -> None:
    """Sizes, bases, regions and landmarks of a head model."""
    head = load_model(model, flame_dir)
    summary = {
        "model": head.name, "vertices": head.num_vertices, "faces": int(head.faces.shape[0]),
        "joints": len(head.joint_names), "joint_names": head.joint_names, "n_shape": head.n_shape,
        "n_expr": head.n_expr, "expression_names": head.expression_names,
        "shape_variance_explained": head.meta.get("shape_variance_explained"),
        "landmarks": head.num_landmarks, "landmark_kind": head.meta.get("landmarks", {}).get("kind"),
        "landmark_median_px": head.meta.get("landmarks", {}).get("landmark_median_px"),
        "regions": {name: int(head.region(name).numel()) for name in head.region_names},
        "pose_correctives": head.posedirs is not None, "source": head.meta.get("source"),
    }
    if as_json:
        print(json.dumps(summary))
        return
    for key, value in summary.items():
        if key != "expression_names":
            console.print(f"[bold]{key}[/]: {value}")
    console.print(f"[bold]expression_names[/]: {', '.join(summary['expression_names'][:8])}, ...")


@app.command("build")
def build(rebuild: bool = typer.Option(False, help="rebuild even if cached")) -> None:
    """Build and cache the open-head model (identity PCA, expressions, landmark embedding)."""
    from headforge.head.open_head import cache_path, load_open_head

    data = load_open_head(rebuild=rebuild, progress=progress)
    console.print(f"open-head: {len(data.v_template)} vertices, cached at {cache_path()}")


@app.command("fit-image")
def fit_image(image: Path = typer.Argument(..., help="a photo with one face, or a video (see --frame)"),
              output: Path = typer.Option(..., "-o", "--output", help="overlay PNG to write"),
              model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
              steps: int = typer.Option(300, help="Adam steps"),
              frame: int = typer.Option(0, help="frame index when IMAGE is a video")) -> None:
    """Fit the head model (rigid + shape + expression) to MediaPipe landmarks of a photo."""
    from headforge.data.video import read_picture
    from headforge.head.fit import ImageFitConfig, fit_image, overlay
    from headforge.render.io import write_png

    if steps < 1:
        raise HeadforgeError(f"--steps must be >= 1, got {steps}")
    pixels = read_picture(image, frame)
    head = load_model(model, flame_dir)
    progress(f"fitting {head.name} to {image.name} ({steps} steps)")
    fit = fit_image(head, pixels, ImageFitConfig(steps=steps))
    write_png(output, overlay(pixels, fit, head.faces.numpy()))
    print(json.dumps({"image": str(image), "output": str(output), "landmark_median_px": round(fit.median_px, 3),
                      "landmark_median_px_inner": round(fit.median_px_inner, 3)}))
