"""Where a finished run's landmark error (AKD) comes from: MediaPipe's 478 landmarks on the
avatar's render against those on the frame, as the platform's protocol scores them, split by
face region (eyes, irises, brows, lips, nose, face oval, the rest), on the held-out frames (at
their test-time-fitted parameters) or on the training frames (at their trained parameters).
Training frames tell a representation that cannot draw the features (their error is as large)
from a fitting that does not find the held-out frames' expression (theirs is small).

    python benchmarks/akd_breakdown.py RUN DATASET [--split val|train] [--every N] [--threads 2]

Prints one JSON line: run, split, frames, akd_px (all 478; with --split val --every 1 the run's
own val_akd_px), akd_<region>_px, eye / mouth opening errors.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def regions() -> dict[str, np.ndarray]:
    """MediaPipe face-mesh landmark indices (of 478) per region; "rest" is every other one."""
    from mediapipe.python.solutions import face_mesh_connections as c

    def ids(*sets) -> set[int]:
        return {i for s in sets for edge in s for i in edge}

    out = {"eyes": ids(c.FACEMESH_LEFT_EYE, c.FACEMESH_RIGHT_EYE), "irises": set(range(468, 478)),
           "brows": ids(c.FACEMESH_LEFT_EYEBROW, c.FACEMESH_RIGHT_EYEBROW), "lips": ids(c.FACEMESH_LIPS),
           "nose": ids(c.FACEMESH_NOSE), "oval": ids(c.FACEMESH_FACE_OVAL)}
    taken = set().union(*out.values())
    out["rest"] = set(range(478)) - taken
    return {k: np.array(sorted(v)) for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--split", choices=("val", "train"), default="val")
    parser.add_argument("--every", type=int, default=1, help="score every N-th frame of the split")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.head.landmarks import EYELID_PAIRS
    from headforge.metrics.protocol import MOUTH_PAIRS, TrackedHead, composite, image_landmarks, openings
    from headforge.render.camera import Cameras

    r = load_run(args.run, "cpu")
    config = r.config
    data = FrameData(args.dataset, args.split, config.resolution, TrackedHead(r.assets.head_data(), r.assets.tracking["shape"]))
    data = data.subset(torch.arange(0, len(data), max(1, args.every)))
    pred_lmk, gt_lmk = [], []
    with torch.no_grad():
        for rows in torch.arange(len(data)).split(config.batch):
            batch = data.batch(rows)
            cams = Cameras.at_origin(data.K, len(rows), config.resolution)
            out = r.method.render_for_scoring(r.avatar, r.avatar.frame_params(batch["index"]), cams)
            pred, gt = composite(out.rgb, batch["image"], batch["mask"], batch["region"])
            pred_lmk.append(image_landmarks(pred))
            gt_lmk.append(image_landmarks(gt))
    a, g = np.concatenate(pred_lmk), np.concatenate(gt_lmk)
    dist = np.linalg.norm(a - g, axis=-1)  # (T, 478), NaN where either image had no face
    found = np.isfinite(dist).all(1)
    figures = {"run": str(args.run), "split": args.split, "frames": len(data), "frames_with_faces": int(found.sum()),
               "akd_px": round(float(np.nanmean(dist.mean(1))), 4)}
    for name, idx in regions().items():
        figures[f"akd_{name}_px"] = round(float(np.nanmean(dist[:, idx].mean(1))), 4)
    figures["eye_opening_error_px"] = round(float(np.nanmean(np.abs(openings(a, EYELID_PAIRS) - openings(g, EYELID_PAIRS)))), 4)
    figures["mouth_opening_error_px"] = round(float(np.nanmean(np.abs(openings(a, MOUTH_PAIRS) - openings(g, MOUTH_PAIRS)))), 4)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
