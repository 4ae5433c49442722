"""Where a finished run's landmark error (AKD) comes from: MediaPipe's 478 landmarks on the
avatar's render against those on the frame, as the platform's protocol scores them, split by
face region (eyes, irises, brows, lips, nose, face oval, the rest), on the held-out frames (at
their test-time-fitted parameters) or on the training frames (at their trained parameters).
Training frames tell a representation that cannot draw the features (their error is as large)
from a fitting that does not find the held-out frames' expression (theirs is small).

    python benchmarks/akd_breakdown.py RUN DATASET [--split val|train] [--every N] [--threads 2]

Prints one JSON line: run, split, frames, landmark_frames (both detections found), akd_px (all
478; with --split val --every 1 the run's own val_akd_px), akd_<region>_px
(headforge.metrics.protocol.landmark_regions), eye / mouth opening errors, and the split of AKD
into each frame's mean displacement (landmark_shift_px) and the rest (akd_unshifted_px).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--split", choices=("val", "train"), default="val")
    parser.add_argument("--every", type=int, default=1, help="score every N-th frame of the split")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from headforge.avatars.engine import score
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.errors import HeadforgeError
    from headforge.metrics.protocol import TrackedHead

    try:
        r = load_run(args.run, "cpu")
        data = FrameData(args.dataset, args.split, r.config.resolution,
                         TrackedHead(r.assets.head_data(), r.assets.tracking["shape"]))
    except HeadforgeError as exc:
        sys.exit(f"error: {exc}")
    data = data.subset(torch.arange(0, len(data), max(1, args.every)))
    summary, _ = score(r.method, r.avatar, data, r.config, landmarks=True, by_region=True)
    keys = ["frames", "landmark_frames"] + [k for k in summary if k.startswith("akd_") or "opening" in k or "shift" in k]
    print(json.dumps({"run": str(args.run), "split": args.split} | {k: summary[k] for k in keys}))


if __name__ == "__main__":
    main()
