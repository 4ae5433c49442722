"""Where a trained NHA avatar's image error is: inside the head or on its outline.

    python benchmarks/nha_error_split.py RUN DATASET [--split val|train] [--frames 16]

Takes ``--frames`` evenly spaced frames of the split, fits their per-frame parameters first
(test-time fitting, the run's ``tto_steps``) when the split is ``val``, renders them as
the scoring protocol composites them (on white, inside the tracked head's region) and splits the squared
error over four pixel sets: both foreground, GT foreground only (the avatar misses it), avatar
only (it covers GT background), neither. Prints a table, then one JSON line with each set's
pixel count, share of the squared error and the PSNR the frames would have without that set's
error.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from headforge.avatars.engine import fit_frames
from headforge.avatars.frames import FrameData
from headforge.avatars.run import load_run
from headforge.errors import HeadforgeError
from headforge.metrics.protocol import TrackedHead, composite
from headforge.render.camera import Cameras


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path, help="the run's dataset")
    parser.add_argument("--split", choices=("val", "train"), default="val")
    parser.add_argument("--frames", type=int, default=16)
    args = parser.parse_args()
    run = load_run(args.run)
    avatar, config = run.avatar, run.config
    data = FrameData(args.dataset, args.split, config.resolution, TrackedHead(run.assets.head_data(), run.assets.tracking["shape"]))
    data = data.subset(torch.linspace(0, len(data) - 1, min(args.frames, len(data))).long())
    K = data.K
    if args.split == "val":
        fit_frames(run.method, avatar, data, config, config.tto_steps, config.tto_photometric_steps)
    totals = {name: [0.0, 0] for name in ("both", "gt_only", "avatar_only", "neither")}
    with torch.no_grad():
        for rows in torch.arange(len(data)).split(config.batch):
            batch = data.batch(rows)
            r = avatar.render(avatar.frame_params(batch["index"]), Cameras.at_origin(K, len(rows), config.resolution))
            area = batch["region"]
            pred, gt = composite(r.rgb, batch["image"], batch["mask"], area)
            se = ((pred - gt) ** 2).mean(-1)
            ours, theirs = r.coverage > 0.5, batch["mask"] > 0.5
            sets = {"both": ours & theirs, "gt_only": ~ours & theirs, "avatar_only": ours & ~theirs,
                    "neither": ~ours & ~theirs}
            for name, sel in sets.items():
                totals[name][0] += float(se[sel & area].sum())
                totals[name][1] += int((sel & area).sum())
    pixels = len(data) * config.resolution ** 2
    total = sum(v[0] for v in totals.values())
    result = {"frames": len(data), "split": args.split, "psnr_pooled": round(-10 * math.log10(total / pixels), 3)}
    print(f"{len(data)} {args.split} frames, pooled PSNR {result['psnr_pooled']:.2f} dB")
    print("| pixels | count | share of squared error | PSNR without it |\n| --- | --- | --- | --- |")
    for name, (err, count) in totals.items():
        without = -10 * math.log10(max(total - err, 1e-12) / pixels)
        result[name] = {"pixels": count, "error_share": round(err / total, 3), "psnr_without": round(without, 2)}
        print(f"| {name} | {count} | {err / total:.3f} | {without:.2f} dB |")
    print(json.dumps(result))


if __name__ == "__main__":
    try:
        main()
    except HeadforgeError as err:  # a wrong run folder: one line, no traceback
        raise SystemExit(f"error: {err}") from None
