"""How far a finished run's frame parameters moved the head from where the tracker put it: the
tracked head model's 478 landmarks, posed at the tracker's parameters and at the run's (the
training frames' as trained, or the held-out frames' as test-time fitted), projected and
compared with the frame's MediaPipe detections. Per frame the mean displacement (a shift of the
whole face) is split from the rest: a run whose frames drifted draws its avatar a few pixels off
in each frame, which the canonical appearance then averages into a blur.

    python benchmarks/frame_drift.py RUN DATASET [--split train|val] [--every N]

Prints one JSON line: for ``tracked`` and ``run`` parameters, ``*_akd_px`` (mean landmark
distance), ``*_shift_px`` (mean length of the per-frame mean displacement), ``*_shift_spread_px``
(its standard deviation over frames, x and y), and ``param_change`` (mean |run - tracked| per
frame parameter: radians, metres, expression units). Pixels at the run's resolution.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def shift_figures(projected: np.ndarray, detected: np.ndarray) -> dict[str, float | list[float]]:
    """(B, L, 2) projected and detected landmarks (px; NaN where none was found) -> AKD and the mean
    length of the per-frame mean displacement (the protocol's ``landmark_scores``), and that
    displacement's spread (std over frames of x and y)."""
    from headforge.metrics.protocol import landmark_scores

    ok = np.isfinite(projected - detected).all((1, 2))
    if not ok.any():
        raise ValueError("no frame has landmarks on both sides")
    scores = landmark_scores(projected[ok], detected[ok], by_region=True)
    shift = (projected[ok] - detected[ok]).mean(1)
    return {"akd_px": float(scores["akd_px"].mean()), "shift_px": float(scores["landmark_shift_px"].mean()),
            "shift_spread_px": [float(s) for s in shift.std(0)]}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--split", choices=("train", "val"), default="train")
    parser.add_argument("--every", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.errors import HeadforgeError
    from headforge.head.pose import FRAME_KEYS, head_to_camera
    from headforge.metrics.protocol import TrackedHead
    from headforge.render.camera import project_points

    try:
        r = load_run(args.run, "cpu")
        head = TrackedHead(r.assets.head_data(), r.assets.tracking["shape"])
        data = FrameData(args.dataset, args.split, r.config.resolution, head)
    except HeadforgeError as exc:
        sys.exit(f"error: {exc}")
    data = data.subset(torch.arange(0, len(data), max(1, args.every)))
    batch = data.batch(torch.arange(len(data)))
    idx, detected = batch["index"], batch["landmarks"].numpy()
    tracked = {k: r.assets.tracking[k][idx].float() for k in FRAME_KEYS}
    trained = {k: r.avatar.frames[k].detach()[idx].float() for k in FRAME_KEYS}

    @torch.no_grad()
    def projected(params: dict[str, torch.Tensor]) -> np.ndarray:
        B = len(idx)
        out = head.model(shape=head.shape.expand(B, -1), **{k: params[k] for k in FRAME_KEYS if k != "translation"})
        if out.landmarks is None:
            sys.exit("error: the head model has no landmarks")
        return project_points(head_to_camera(out.landmarks, params["translation"]), data.K).numpy()

    result: dict = {"run": str(args.run), "split": args.split, "frames": len(idx)}
    for name, params in (("tracked", tracked), ("run", trained)):
        result |= {f"{name}_{k}": v for k, v in shift_figures(projected(params), detected).items()}
    result["param_change"] = {k: float((trained[k] - tracked[k]).abs().mean()) for k in FRAME_KEYS}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
