"""NHA on a real clip: track (unless --dataset is given), fit the quick preset at 256², test-time
fit the held-out last 20 %, evaluate; time the trained avatar's rendering.

    python benchmarks/bench_nha.py [--dataset DS] [--run RUN] [--iterations N]

Prints one JSON line: train_minutes, val_psnr, val_ssim, val_l1, render_fps_256 (CPU, 2 threads).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import timed  # noqa: E402

CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "talking_bun.mp4"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--dataset", type=Path, default=None, help="a tracked dataset (default: track talking_bun)")
    parser.add_argument("--run", type=Path, default=Path("bench_nha_run"))
    parser.add_argument("--iterations", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(2)
    from headforge.avatars.nha.trainer import FrameData, NHAConfig, _cameras, fit, load_run

    dataset = args.dataset
    if dataset is None:
        from headforge.track.pipeline import TrackOptions, track_video

        if not CLIP.is_file():
            sys.exit(f"{CLIP} is not present: pass --dataset")
        dataset = Path("bench_nha_dataset")
        if not (dataset / "dataset.json").is_file():
            track_video(CLIP, dataset, TrackOptions(overlay=False))
    config = NHAConfig.quick()
    if args.iterations:
        config.scale_schedule(args.iterations)
    metrics = fit(dataset, args.run, config, log=lambda m: print(m, file=sys.stderr))
    avatar, config, _ = load_run(args.run)
    data = FrameData(dataset, "val", config.resolution)
    params = avatar.frame_params(data.index[:1])
    cams = _cameras(data.K, 1, config.resolution)
    with torch.no_grad():
        ms = timed(lambda: avatar.render(params, cams), repeats=10)
    print(json.dumps({"train_minutes": metrics["train_minutes"], "val_psnr": metrics["val_psnr"],
                      "val_ssim": metrics["val_ssim"], "val_l1": metrics["val_l1"], "val_frames": metrics["val_frames"],
                      "iterations": metrics["iterations"], "render_fps_256": round(1000 / ms, 2),
                      "lpips": "n/a (no pretrained weights)"}))


if __name__ == "__main__":
    main()
