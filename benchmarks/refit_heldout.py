"""Re-run the test-time fitting of a finished run's held-out frames with other settings (the
networks as trained), from the tracked parameters, and score them with the platform's protocol:
an A/B of the fitting energies without retraining.

    python benchmarks/refit_heldout.py RUN DATASET [--set FIELD=VALUE ...] [--threads 2]

A PointAvatar run fitted with its landmark terms (w_landmarks / w_eyelids > 0) gets its landmark
bias measured on its training frames first, as training does at its end. The run folder is not
changed. Prints one JSON line: the settings, val_* figures (as metrics.json).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from headforge.avatars.engine import fit_frames, score
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.metrics.protocol import TrackedHead

    r = load_run(args.run, "cpu")
    config = r.config
    for assignment in args.set:
        config.override(assignment)
    head = TrackedHead(r.assets.head_data(), r.assets.tracking["shape"])
    val = FrameData(args.dataset, "val", config.resolution, head)
    if r.method.name == "pointavatar":
        from headforge.avatars.pointavatar.method import landmark_bias, uses_landmarks

        if uses_landmarks(config):
            r.avatar.landmark_bias.copy_(landmark_bias(r.avatar, FrameData(args.dataset, "train", config.resolution, head)))
    tracked = r.avatar.params_from_tracking(r.assets.tracking)  # the frames as the run started
    with torch.no_grad():
        for k in r.avatar.frames:
            r.avatar.frames[k][val.index] = tracked[k][val.index]
    start = time.perf_counter()
    fit_frames(r.method, r.avatar, val, config, config.tto_steps, config.tto_photometric_steps)
    seconds = time.perf_counter() - start
    summary, _ = score(r.method, r.avatar, val, config, None, landmarks=True)
    print(json.dumps({"run": str(args.run), "settings": args.set, "fit_seconds": round(seconds, 1)}
                     | {f"val_{k}": v for k, v in summary.items()}))


if __name__ == "__main__":
    main()
