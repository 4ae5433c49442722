"""The ``headforge`` command line (typer). Every user-facing error is one line, exit code 1."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

from headforge.errors import HeadforgeError

app = typer.Typer(help="headforge: animatable 3D head avatars from phone videos or head scans.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
model_app = typer.Typer(help="Parametric head models: build, inspect, fit to a photo.", no_args_is_help=True)
app.add_typer(model_app, name="model")
render_app = typer.Typer(help="Render head models and avatars to PNG/MP4.", no_args_is_help=True)
app.add_typer(render_app, name="render")
fit_app = typer.Typer(help="Train avatars from a tracked dataset.", no_args_is_help=True)
app.add_typer(fit_app, name="fit")
console = Console(stderr=True)

MODEL_OPT = typer.Option("open-head", "--model", "-m", help="open-head (built in) or flame (your own files)")
FLAME_OPT = typer.Option(None, "--flame-dir", help="folder with FLAME's generic_model.pkl (or HEADFORGE_FLAME_DIR)")


def _progress(message: str) -> None:
    console.print(f"[dim]{time.strftime('%H:%M:%S')}[/] {message}")


class _Bars:
    """Rich progress bars; ``factory(description, total)`` returns a no-argument advance callable."""

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                 console=console, transient=True)
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        return self.progress.__exit__(*exc)

    def factory(self, description: str, total):
        task = self.progress.add_task(description, total=total)
        return lambda: self.progress.advance(task)


def _load_model(name: str, flame_dir: Optional[str]):
    from headforge.head import create

    return create(name, flame_dir=flame_dir, progress=_progress)


def _read_image(path: Path, frame: int = 0):
    """An RGB uint8 image from a picture file, or frame ``frame`` of a video file."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from headforge.data.video import is_video, read_frame

    if is_video(path):
        return read_frame(path, frame)
    if not path.is_file():
        raise HeadforgeError(f"image not found: {path}")
    try:
        return np.asarray(Image.open(path).convert("RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise HeadforgeError(f"cannot read image {path}: {exc}") from None


@model_app.command("info")
def model_info(model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
               as_json: bool = typer.Option(False, "--json", help="print one JSON object")) -> None:
    """Sizes, bases, regions and landmarks of a head model."""
    head = _load_model(model, flame_dir)
    info = {
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
        print(json.dumps(info))
        return
    for key, value in info.items():
        if key != "expression_names":
            console.print(f"[bold]{key}[/]: {value}")
    console.print(f"[bold]expression_names[/]: {', '.join(info['expression_names'][:8])}, ...")


@model_app.command("build")
def model_build(rebuild: bool = typer.Option(False, help="rebuild even if cached")) -> None:
    """Build and cache the open-head model (identity PCA, expressions, landmark embedding)."""
    from headforge.head.open_head import cache_path, load_open_head

    data = load_open_head(rebuild=rebuild, progress=_progress)
    console.print(f"open-head: {len(data.v_template)} vertices, cached at {cache_path()}")


@model_app.command("fit-image")
def model_fit_image(image: Path = typer.Argument(..., help="a photo with one face, or a video (see --frame)"),
                    output: Path = typer.Option(..., "-o", "--output", help="overlay PNG to write"),
                    model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
                    steps: int = typer.Option(300, help="Adam steps"),
                    frame: int = typer.Option(0, help="frame index when IMAGE is a video")) -> None:
    """Fit the head model (rigid + shape + expression) to MediaPipe landmarks of a photo."""
    from headforge.head.fit import ImageFitConfig, fit_image, overlay
    from headforge.render.io import write_png

    if steps < 1:
        raise HeadforgeError(f"--steps must be >= 1, got {steps}")
    pixels = _read_image(image, frame)
    head = _load_model(model, flame_dir)
    _progress(f"fitting {head.name} to {image.name} ({steps} steps)")
    fit = fit_image(head, pixels, ImageFitConfig(steps=steps))
    write_png(output, overlay(pixels, fit, head.faces.numpy()))
    summary = {"image": str(image), "output": str(output), "landmark_median_px": round(fit.median_px, 3),
               "landmark_median_px_inner": round(fit.median_px_inner, 3)}
    print(json.dumps(summary))


@render_app.command("turntable")
def render_turntable(output: Path = typer.Option(..., "-o", "--output", help="MP4 to write (a PNG of frame 0 beside it)"),
                     model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
                     frames: int = typer.Option(60, help="number of frames (one full turn)"),
                     resolution: int = typer.Option(256, help="height of each panel in pixels"),
                     points: int = typer.Option(100_000, help="surface points for the point panel"),
                     fps: float = typer.Option(30.0)) -> None:
    """The head model turning: mesh path (shaded) | point path (coloured by normal)."""
    from headforge.render.io import write_mp4, write_png
    from headforge.render.turntable import turntable_frames

    if frames < 1 or resolution < 16 or points < 1:
        raise HeadforgeError("need --frames >= 1, --resolution >= 16 and --points >= 1")
    head = _load_model(model, flame_dir)
    start = time.perf_counter()
    first = {}

    def frames_keeping_first():
        for i, frame in enumerate(turntable_frames(head, frames, resolution, points)):
            if i == 0:
                first["frame"] = frame
            yield frame

    write_mp4(output, frames_keeping_first(), fps=fps, total=frames, description=f"rendering {frames} frames")
    png = write_png(output.with_suffix(".png"), first["frame"])
    seconds = time.perf_counter() - start
    print(json.dumps({"output": str(output), "preview": str(png), "frames": frames,
                      "seconds": round(seconds, 2), "frames_per_second": round(frames / seconds, 2)}))


@app.command("track")
def track(video: Path = typer.Argument(..., help="a video with one face (mp4, mov, ...) or a folder of frames"),
          output: Path = typer.Option(..., "-o", "--output", help="dataset folder to write"),
          model: str = MODEL_OPT, flame_dir: Optional[str] = FLAME_OPT,
          resolution: int = typer.Option(512, help="crop size in pixels"),
          every: int = typer.Option(1, help="keep every N-th frame"),
          max_frames: Optional[int] = typer.Option(None, help="stop after this many kept frames"),
          val_fraction: float = typer.Option(0.2, help="last fraction of frames held out for validation"),
          preset: str = typer.Option("quick", help="quick (CPU) or paper"),
          focal: Optional[float] = typer.Option(None, help="known focal length in crop pixels (default: estimated)"),
          crop: str = typer.Option("face", help="face: a smooth window around the face; full: the whole square frame"),
          masks: Optional[Path] = typer.Option(None, help="folder of foreground masks named like the frames "
                                                          "(default: MediaPipe selfie segmentation)"),
          photometric: bool = typer.Option(False, help="refine the landmark fit against the crops with the "
                                                        "renderer (shading + silhouette; slower, better shape)"),
          overlay: bool = typer.Option(True, help="write overlay.mp4 (landmarks + model wireframe)")) -> None:
    """Preprocess a video or a folder of frames (crops, masks, landmarks) and track the head model in it."""
    from headforge.track.pipeline import TrackOptions, track_video

    options = TrackOptions(model, flame_dir, resolution, every, max_frames, val_fraction, preset, overlay, focal,
                           crop, None if masks is None else str(masks), photometric)
    with _Bars() as bars:
        metrics = track_video(video, output, options, log=_progress, progress_factory=bars.factory)
    console.print(f"dataset written to {output}/ (dataset.json, frames/, masks/, overlay.mp4, metrics.json)")
    print(json.dumps(metrics))


@fit_app.command("nha")
def fit_nha(dataset: Path = typer.Argument(..., help="a dataset written by headforge track or synth"),
            output: Path = typer.Option(..., "-o", "--output", help="run folder (resumed when it exists)"),
            preset: str = typer.Option("quick", help="quick (CPU) or paper (GPU-sized)"),
            iterations: Optional[int] = typer.Option(None, help="scale the 3-stage schedule to this many iterations"),
            resolution: Optional[int] = typer.Option(None, help="training resolution (default: preset's)"),
            device: str = typer.Option("auto", help="auto (a CUDA GPU when there is one), cpu or cuda[:N]"),
            set_: Optional[list[str]] = typer.Option(None, "--set", metavar="FIELD=VALUE",
                                                     help="override a preset field, e.g. --set tex_grid=256 (repeatable)")) -> None:
    """Neural Head Avatars: geometry MLP offsets + neural texture on the tracked head model."""
    from headforge.avatars.nha.trainer import NHAConfig, fit
    from headforge.devices import resolve_device

    if preset not in ("quick", "paper"):
        raise HeadforgeError(f"--preset must be quick or paper, got {preset!r}")
    config = NHAConfig.quick() if preset == "quick" else NHAConfig.paper()
    if resolution is not None:
        if resolution < 64:
            raise HeadforgeError(f"--resolution must be >= 64, got {resolution}")
        config.resolution = resolution
    if iterations is not None:
        config.scale_schedule(iterations)
    for assignment in set_ or []:
        config.override(assignment)
    target = resolve_device(device)
    with _Bars() as bars:
        metrics = fit(dataset, output, config, log=_progress, progress=bars.factory("training", config.total_iters),
                      device=target)
    console.print(f"run written to {output}/ (checkpoint, progress.png, val/, metrics.json)")
    print(json.dumps(metrics))


@render_app.command("avatar")
def render_avatar(run: Path = typer.Argument(..., help="a run folder of headforge fit"),
                  output: Path = typer.Option(..., "-o", "--output", help="MP4 to write"),
                  driving: Optional[Path] = typer.Option(None, help="dataset whose tracked expressions/poses drive the avatar"),
                  orbit: bool = typer.Option(False, help="orbit the camera around the head (novel views)"),
                  split: str = typer.Option("val", help="frames of the run's own dataset when not driven: train, val or all"),
                  max_frames: Optional[int] = typer.Option(None, help="at most this many frames"),
                  fps: float = typer.Option(25.0)) -> None:
    """Reenactment and novel views of a trained avatar."""
    import torch
    from safetensors.torch import load_file

    from headforge.avatars.nha.export import render_frames
    from headforge.avatars.nha.model import FRAME_KEYS
    from headforge.avatars.nha.trainer import load_run
    from headforge.data.dataset import read_meta
    from headforge.render.io import write_mp4

    avatar, config, meta = load_run(run)
    if driving is not None:
        dmeta = read_meta(driving)
        if dmeta["model"] != meta["model"] or dmeta.get("n_shape") != meta.get("n_shape"):
            raise HeadforgeError(f"{driving} was tracked with {dmeta['model']}, the avatar uses {meta['model']}")
        tracked = load_file(str(driving / "tracking.safetensors"))
        rows = [r["index"] for r in dmeta["frames"] if r["valid"]]
        seq = {k: v[rows] for k, v in avatar.params_from_tracking(tracked).items()}
        # keep the avatar's own framing: its mean translation, the driver's motion around it
        own = avatar.frames["translation"].detach()
        seq["translation"] = seq["translation"] - seq["translation"].mean(0) + own.mean(0)
    else:
        if split not in ("train", "val", "all"):
            raise HeadforgeError(f"--split must be train, val or all, got {split!r}")
        rows = [r["index"] for r in meta["frames"] if r["valid"] and (split == "all" or r["split"] == split)]
        seq = {k: avatar.frames[k].detach()[rows] for k in FRAME_KEYS}
    if max_frames is not None:
        seq = {k: v[:max_frames] for k, v in seq.items()}
    from headforge.render.camera import scale_intrinsics

    K = scale_intrinsics(torch.tensor(meta["intrinsics"], dtype=torch.float32), config.resolution / meta["resolution"])
    T = seq["translation"].shape[0]
    write_mp4(output, render_frames(avatar, K, config.resolution, seq, orbit=orbit), fps=fps, total=T,
              description=f"rendering {T} frames")
    print(json.dumps({"output": str(output), "frames": T}))


@app.command("export")
def export(run: Path = typer.Argument(..., help="a run folder of headforge fit"),
           output: Path = typer.Option(..., "-o", "--output", help="folder to write"),
           fmt: str = typer.Option("obj", "--format", help="obj, ply or glb"),
           frames: Optional[str] = typer.Option(None, help="also export these tracked frames, e.g. 0,10,20 or 0-99"),
           texture_size: int = typer.Option(512, help="baked texture size in pixels")) -> None:
    """Export the avatar mesh (neutral and per frame) with its baked texture."""
    from headforge.avatars.nha.export import export_run
    from headforge.avatars.nha.trainer import load_run

    avatar, _, _ = load_run(run)
    wanted = None
    if frames:
        try:
            wanted = []
            for part in frames.split(","):
                a, _, b = part.partition("-")
                wanted += list(range(int(a), int(b) + 1)) if b else [int(a)]
        except ValueError:
            raise HeadforgeError(f"--frames must look like 0,10,20 or 0-99, got {frames!r}") from None
    written = export_run(avatar, output, fmt, wanted, texture_size)
    print(json.dumps({"output": str(output), "files": len(written) + 1}))


@app.command("synth")
def synth(output: Path = typer.Option(..., "-o", "--output", help="benchmark folder to write"),
          subjects: int = typer.Option(4, help="number of subjects"),
          train_frames: int = typer.Option(200, help="training frames per subject"),
          val_frames: int = typer.Option(210, help="validation frames per subject (unseen expressions/poses)"),
          resolution: int = typer.Option(512, help="image size in pixels"),
          seed: int = typer.Option(0, help="random seed (subjects and motion)"),
          gt_every: int = typer.Option(5, help="full ground truth (meshes, normals, views, relit, albedo) every N frames"),
          supersample: int = typer.Option(2, help="anti-aliasing: render at N x N samples per pixel")) -> None:
    """Synthetic talking-head subjects (full anny body, hair, skin albedo) with exact ground truth,
    each written as a tracked headforge dataset plus gt/."""
    from headforge.data.synthetic import SynthConfig, synthesize

    config = SynthConfig(subjects=subjects, train_frames=train_frames, val_frames=val_frames, resolution=resolution,
                         seed=seed, gt_every=gt_every, supersample=supersample)
    with _Bars() as bars:
        report = synthesize(output, config, log=_progress, progress_factory=bars.factory)
    console.print(f"benchmark written to {output}/ (contact_sheet.png, benchmark.json, subject_*/)")
    print(json.dumps({k: report[k] for k in ("render_seconds", "track_seconds", "total_seconds")}
                     | {"subjects": len(report["subjects"])}))


@app.command("eval")
def evaluate(pred: Path = typer.Argument(..., help="predicted images, or a tracked dataset / geometry folder"),
             gt: Path = typer.Argument(..., help="ground-truth images (same file names), or a headforge synth subject"),
             masks: Optional[Path] = typer.Option(None, help="folder of masks (same names) for masked metrics"),
             split: str = typer.Option("val", help="geometry mode: val, train or all ground-truth frames"),
             every: int = typer.Option(1, help="geometry mode: use every N-th ground-truth frame"),
             reference: Optional[Path] = typer.Option(
                 None, help="geometry mode: another prediction (e.g. the tracked dataset); adds both normal "
                            "errors on the pixels both cover (paired_*)"),
             output: Path = typer.Option(Path("eval"), "-o", "--output", help="report folder"),
             as_json: bool = typer.Option(False, "--json", help="print the mean metrics as one JSON object")) -> None:
    """Image metrics (L1, PSNR, SSIM, MS-SSIM, CPBD; LPIPS when its weights exist) between two
    folders; or, when GT is a synth subject, geometry metrics (normal angle error, one-sided
    Hausdorff full head / face in mm, normal consistency) of a tracked dataset or exported geometry;
    with --reference, also the normal errors of both predictions on the pixels both cover."""
    if (gt / "gt" / "geometry.safetensors").is_file():
        from headforge.metrics.benchmark import evaluate_geometry, paired_normal_error, write_geometry_report

        if every < 1:
            raise HeadforgeError(f"--every must be >= 1, got {every}")
        # the pair first: it is the quick part, so a wrong --reference fails before the long one
        pair = {} if reference is None else paired_normal_error(pred, reference, gt, split=split, every=every)["mean"]
        result = evaluate_geometry(pred, gt, split=split, every=every)
        result["mean"] |= {f"paired_{k}": v for k, v in pair.items()}
        write_geometry_report(result, output)
        summary = {"frames": result["frames"], "hair": result["hair"], **result["mean"]}
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


@app.command("demo")
def demo(output: Path = typer.Option(Path("headforge-demo"), "-o", "--output", help="report folder"),
         video: Optional[Path] = typer.Option(None, help="use this video (first 300 frames) instead of a synthetic subject"),
         iterations: int = typer.Option(900, help="NHA training iterations (the quick preset's schedule, scaled)"),
         device: str = typer.Option("auto", help="NHA training device: auto (a CUDA GPU when there is one), cpu or cuda[:N]")) -> None:
    """The main job end to end on the embedded default: synth one small subject (or track
    --video) -> fit a Neural Head Avatar (quick) -> render val frames, a novel-view orbit and
    the turntable -> evaluate (images; geometry against GT for the synthetic subject). Writes a
    report folder (PNGs, MP4s, metrics.json, metrics.md)."""
    import shutil

    import matplotlib.cbook
    import torch

    from headforge.avatars.nha.export import export_run, render_frames
    from headforge.avatars.nha.model import FRAME_KEYS
    from headforge.avatars.nha.trainer import NHAConfig, fit
    from headforge.head.fit import fit_image, overlay
    from headforge.render.io import write_mp4, write_png
    from headforge.render.turntable import turntable_frames

    from headforge.devices import resolve_device

    NHAConfig.quick().scale_schedule(iterations)  # checks --iterations before any work
    resolve_device(device)  # and --device
    start_all = time.perf_counter()
    tmp = output.with_name(output.name + ".partial")
    tmp.mkdir(parents=True, exist_ok=True)  # kept between attempts: synth/track/fit resume
    head = _load_model("open-head", None)
    metrics = {"model": head.name}
    with _Bars() as bars:
        if video is None:
            from headforge.data.synthetic import SynthConfig, synthesize

            _progress("1/4 synthesising one talking subject with ground truth (headforge synth)")
            synth_cfg = SynthConfig(subjects=1, train_frames=120, val_frames=40, resolution=256, gt_every=4,
                                    novel_yaws=(25.0,))
            if not (tmp / "synth" / "benchmark.json").is_file():
                synthesize(tmp / "synth", synth_cfg, log=_progress, progress_factory=bars.factory)
            dataset = tmp / "synth" / "subject_00"
        else:
            from headforge.track.pipeline import TrackOptions, track_video

            _progress(f"1/4 tracking the first 300 frames of {video.name} (headforge track)")
            if not (tmp / "track" / "dataset.json").is_file():
                track_video(video, tmp / "track", TrackOptions(max_frames=300), log=_progress,
                            progress_factory=bars.factory)
            dataset = tmp / "track"
        metrics.update({f"track_{k}": v for k, v in json.loads((dataset / "metrics.json").read_text()).items()
                        if k in ("landmark_median_px", "frames_valid", "frames_total")})
        _progress(f"2/4 fitting a Neural Head Avatar ({iterations} iterations, quick preset)")
        config = NHAConfig.quick()
        config.scale_schedule(iterations)
        config.val_every = max(1, iterations // 4)
        # 100 fitting steps per held-out frame took 2.2 of the demo's 14.9 minutes (fresh cache,
        # 2 cores); 40 keep it well inside the 15-minute budget (bench_nha keeps the preset's 100)
        config.tto_steps = 40
        # the demo was measured at 14.4 min (fresh cache) with 10 alignment steps per training
        # frame; the preset's 30 is not yet measured inside the demo's budget
        config.align_steps = 10
        nha = fit(dataset, tmp / "nha", config, log=_progress, progress=bars.factory("training", config.total_iters),
                  device=resolve_device(device))
        metrics.update({f"nha_{k}": v for k, v in nha.items() if k != "dataset"})
    _progress("3/4 rendering: validation frames, a novel-view orbit, the exported mesh, the head model turntable")
    from headforge.avatars.nha.trainer import load_run

    avatar, config, meta = load_run(tmp / "nha")
    from headforge.render.camera import scale_intrinsics

    K = scale_intrinsics(torch.tensor(meta["intrinsics"], dtype=torch.float32), config.resolution / meta["resolution"])
    rows = [r["index"] for r in meta["frames"] if r["valid"] and r["split"] == "val"]
    seq = {k: avatar.frames[k].detach()[rows] for k in FRAME_KEYS}
    write_mp4(tmp / "avatar_val.mp4", render_frames(avatar, K, config.resolution, seq), total=len(rows),
              description="avatar, validation frames")
    write_mp4(tmp / "avatar_orbit.mp4", render_frames(avatar, K, config.resolution, seq, orbit=True),
              total=len(rows), description="avatar, orbit")
    export_run(avatar, tmp / "export", "obj", texture_size=256)
    photo = Path(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))
    pixels = _read_image(photo)
    fit_photo = fit_image(head, pixels)
    write_png(tmp / "fit_grace_hopper.png", overlay(pixels, fit_photo, head.faces.numpy()))
    first = {}

    def frames():
        for i, frame in enumerate(turntable_frames(head, 60, 256, 100_000)):
            first.setdefault("frame", frame)
            yield frame

    write_mp4(tmp / "turntable.mp4", frames(), total=60, description="head model turntable")
    write_png(tmp / "turntable.png", first["frame"])
    metrics["fit_grace_hopper_median_px"] = round(fit_photo.median_px, 3)
    if video is None:
        from headforge.metrics.benchmark import evaluate_geometry, paired_normal_error, write_geometry_report

        _progress("4/4 evaluating geometry against the ground truth: tracked head model vs avatar")
        for name, pred in (("tracked", dataset), ("nha", tmp / "nha")):
            result = evaluate_geometry(pred, dataset, samples=5000)
            write_geometry_report(result, tmp / f"eval_{name}")
            for k in ("normal_error_head_deg", "hausdorff_full_mm", "hausdorff_face_mm", "hausdorff_full_outer_mm",
                      "head_coverage"):
                metrics[f"{name}_{k}"] = round(result["mean"][k], 3)
        pair = paired_normal_error(tmp / "nha", dataset, dataset)["mean"]  # both on the pixels both cover
        for name, prefix in (("tracked", "reference_"), ("nha", "")):
            metrics[f"{name}_paired_normal_error_head_deg"] = round(pair[prefix + "normal_error_head_deg"], 3)
    metrics["demo_minutes"] = round((time.perf_counter() - start_all) / 60, 2)
    (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2))
    table = ["| figure | value |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in metrics.items()]
    (tmp / "metrics.md").write_text("\n".join(table) + "\n")
    if output.exists():
        shutil.rmtree(output)
    tmp.replace(output)
    console.print(f"report written to {output}/ (metrics.md, avatar_val.mp4, avatar_orbit.mp4, nha/progress.png, "
                  f"export/avatar.obj, turntable.mp4, ...)")
    print(json.dumps(metrics))


def main() -> None:
    import warnings

    # mediapipe 0.10.14 calls a protobuf API that warns on every start; nothing for users to act on
    warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype")
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        app()
    except HeadforgeError as exc:
        console.print(f"[red]error:[/] {exc}")
        sys.exit(1)
    except KeyboardInterrupt:
        console.print("[red]interrupted[/]")
        sys.exit(130)


if __name__ == "__main__":
    main()
