"""Cost of one per-frame alignment step of a trained NHA run (networks frozen, the align
terms' forward and backward for a chunk of training frames), at the training resolution and
at half of it: shows whether rasterisation or the networks bound the alignment.

    python benchmarks/bench_nha_align.py RUN [--frames 8] [--repeats 5]

Prints one JSON line: median milliseconds per step at each resolution, frames per step.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import timed  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path, help="the run's dataset")
    parser.add_argument("--frames", type=int, default=8, help="frames per step (training uses 4 x batch = 8)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    from headforge.avatars.frames import FrameData
    from headforge.avatars.nha.method import losses
    from headforge.avatars.run import load_run
    from headforge.errors import HeadforgeError
    from headforge.metrics.protocol import TrackedHead

    torch.set_num_threads(2)
    try:
        run = load_run(args.run, "cpu")
    except HeadforgeError as err:
        sys.exit(f"error: {err}")
    avatar, config = run.avatar, run.config
    avatar.requires_grad_(False)
    head = TrackedHead(run.assets.head_data(), run.assets.tracking["shape"])
    dataset = args.dataset
    figures = {"frames_per_step": args.frames}
    for res in (config.resolution, config.resolution // 2):
        data = FrameData(dataset, "train", res, head)
        config.resolution = res
        batch = data.batch(torch.arange(args.frames))
        params = {k: v.detach()[batch["index"]].clone().requires_grad_(True) for k, v in avatar.frames.items()}

        def step() -> None:
            sum(losses(avatar, batch, data.K, config, "align", params).values()).backward()

        figures[f"align_step_ms_{res}"] = round(timed(step, repeats=args.repeats), 1)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
