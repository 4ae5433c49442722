"""NHA on a real clip: track (unless --dataset is given), fit the quick preset at 256² (or
--preset paper), test-time fit the held-out last 20 %, evaluate; time the trained avatar's
rendering.

    python benchmarks/bench_nha.py [--dataset DS] [--run RUN] [--iterations N] [--preset quick|paper]
                                   [--resolution R] [--device cpu|cuda] [--set FIELD=VALUE ...]

Prints one JSON line: train_minutes, the protocol's held-out figures (val_psnr, val_ssim, val_l1,
val_psnr_head over head pixels only, val_psnr_face, val_akd_px and the eye/mouth-opening errors,
val_ms_ssim, val_cpbd), val_psnr_hard_edge (without the fitted soft matte), matte_sigma_px, render_fps
(the trained avatar at the training resolution on --device; CPU runs use 2 threads, as on the CI
machines). A --run folder that already holds a finished run is refused (its figures would be an
earlier run's) unless --reuse is given, which the JSON line then says.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import render_fps  # noqa: E402

CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "talking_bun.mp4"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--dataset", type=Path, default=None, help="a tracked dataset (default: track talking_bun)")
    parser.add_argument("--run", type=Path, default=Path("bench_nha_run"))
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--preset", choices=("quick", "paper"), default="quick")
    parser.add_argument("--resolution", type=int, default=None, help="training resolution (default: the preset's)")
    parser.add_argument("--device", default="cpu", help="cpu (the CI machines' figure), cuda or auto")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override an NHAConfig field for an A/B run (repeatable), e.g. --set tex_grid=256")
    parser.add_argument("--reuse", action="store_true", help="report a finished --run folder instead of refusing it")
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (2: the CI machines' figure; 1 on a "
                                                                  "machine whose cores are busy, where spinning threads stall)")
    args = parser.parse_args()
    from headforge.avatars.engine import fit
    from headforge.avatars.nha.config import NHAConfig
    from headforge.avatars.run import load_run
    from headforge.devices import resolve_device

    if (args.run / "metrics.json").is_file() and not args.reuse:
        sys.exit(f"{args.run} holds a finished run: pass another --run, or --reuse to report it")

    device = resolve_device(args.device)
    if device.type == "cpu":
        torch.set_num_threads(args.threads)

    dataset = args.dataset
    if dataset is None:
        from headforge.track.pipeline import TrackOptions, track_video

        if not CLIP.is_file():
            sys.exit(f"{CLIP} is not present: pass --dataset")
        dataset = Path("bench_nha_dataset")
        if not (dataset / "dataset.json").is_file():
            track_video(CLIP, dataset, TrackOptions(overlay=False))
    config = NHAConfig.quick() if args.preset == "quick" else NHAConfig.paper()
    if args.resolution:
        config.resolution = args.resolution
    if args.iterations:
        config.scale_schedule(args.iterations)
    for assignment in args.set:
        config.override(assignment)
    reused = (args.run / "metrics.json").is_file()
    metrics = fit("nha", dataset, args.run, config, log=lambda m: print(m, file=sys.stderr), device=device)
    run = load_run(args.run, device)
    fps = render_fps(run, device)
    figures = {k: v for k, v in metrics.items() if k.startswith("val_") or k.startswith("novel_")}
    print(json.dumps({"train_minutes": metrics["train_minutes"], **figures, "matte_sigma_px": metrics["matte_sigma_px"],
                      "iterations": metrics["iterations"], "preset": args.preset, "resolution": run.config.resolution,
                      "device": str(device), "overrides": args.set, f"render_fps_{run.config.resolution}": fps,
                      "lpips": "n/a (no pretrained weights)", "reused_run": reused,
                      "threads": args.threads if device.type == "cpu" else None}))


if __name__ == "__main__":
    from headforge.errors import HeadforgeError

    try:
        main()
    except HeadforgeError as err:  # e.g. --device cuda without a GPU, a wrong dataset: one line
        raise SystemExit(f"error: {err}") from None
