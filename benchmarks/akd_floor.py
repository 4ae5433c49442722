"""How much AKD a render's blur alone costs: the held-out frames, as the protocol scores them
(cut to the mask inside the head region, on white), degraded by a Gaussian blur of sigma px or
by down- and up-sampling, scored against themselves undegraded by MediaPipe's 478 landmarks
(AKD, the eye / mouth opening errors), with each degradation's CPBD sharpness (higher: sharper)
beside the run's own renders' so a render's figures can be read against a blur of its sharpness.
A floor, not a model: a render that is as blurred as sigma cannot expect a lower AKD than
sigma's row (MediaPipe's own jitter on the same face included).

    python benchmarks/akd_floor.py RUN DATASET [--every N] [--sigmas 0.5,1,2,3,4,6] [--threads 2]

Prints one line per degradation and a final JSON line: frames, landmark_frames, and for each
degradation akd_px / eye_opening_error_px / mouth_opening_error_px / cpbd / psnr (dB, the
whole image against the undegraded frame, as val_psnr); ``avatar``: the run's
renders (at their fitted parameters) against the frames, scored alike.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def resample(images: torch.Tensor, factor: int) -> torch.Tensor:
    """(B, H, W, 3) images down-sampled by ``factor`` (area) and up again (bilinear)."""
    chw = images.permute(0, 3, 1, 2)
    small = torch.nn.functional.interpolate(chw, scale_factor=1 / factor, mode="area")
    return torch.nn.functional.interpolate(small, size=chw.shape[-2:], mode="bilinear",
                                           align_corners=False).permute(0, 2, 3, 1)


def sigma_list(text: str) -> list[float]:
    """``--sigmas``: comma-separated positive floats (argparse reports anything else in one line)."""
    try:
        sigmas = [float(s) for s in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text!r}") from None
    if not sigmas or min(sigmas) <= 0:
        raise argparse.ArgumentTypeError(f"blur sigmas must be > 0, got {text!r}")
    return sigmas


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--every", type=int, default=5, help="score every N-th held-out frame")
    parser.add_argument("--sigmas", type=sigma_list, default="0.5,1,2,3,4,6", help="comma-separated blur std (px)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.errors import HeadforgeError
    from headforge.metrics.image import cpbd, psnr
    from headforge.metrics.protocol import TrackedHead, composite, image_landmarks, landmark_scores
    from headforge.render.camera import Cameras
    from headforge.render.matte import gaussian_blur

    try:
        r = load_run(args.run, "cpu")
        data = FrameData(args.dataset, "val", r.config.resolution,
                         TrackedHead(r.assets.head_data(), r.assets.tracking["shape"]))
    except HeadforgeError as exc:
        sys.exit(f"error: {exc}")
    data = data.subset(torch.arange(0, len(data), max(1, args.every)))
    frames, renders = [], []
    with torch.no_grad():
        for rows in torch.arange(len(data)).split(r.config.batch):
            batch = data.batch(rows)
            cams = Cameras.at_origin(data.K, len(rows), r.config.resolution)
            out = r.method.render_for_scoring(r.avatar, r.avatar.frame_params(batch["index"]), cams)
            pred, gt = composite(out.rgb, batch["image"], batch["mask"], batch["region"])
            frames.append(gt.clamp(0, 1))
            renders.append(pred.clamp(0, 1))
    frames_t, renders_t = torch.cat(frames), torch.cat(renders)
    truth = image_landmarks(frames_t)

    def scored(images: torch.Tensor, landmarks: np.ndarray | None = None) -> dict:
        """The figures of ``images`` against the frames; ``landmarks``: their detections when known."""
        s = landmark_scores(image_landmarks(images) if landmarks is None else landmarks, truth)
        row = {k: round(float(np.nanmean(v)), 3) for k, v in s.items()}
        row["cpbd"] = round(float(np.mean([cpbd(im.numpy()) for im in images])), 4)
        row["psnr"] = round(float(np.mean([psnr(images[b:b + 1], frames_t[b:b + 1]).item()
                                           for b in range(len(images))])), 2)
        return row

    result = {"run": str(args.run), "frames": len(frames_t),
              "landmark_frames": int(np.isfinite(truth[:, 0, 0]).sum())}
    result["none"] = scored(frames_t, truth)  # the frames' own detections: no second MediaPipe pass
    print("none", json.dumps(result["none"]), flush=True)
    degradations = {f"blur_{s:g}": gaussian_blur(frames_t, s) for s in args.sigmas}
    degradations |= {"resample_2": resample(frames_t, 2), "resample_4": resample(frames_t, 4), "avatar": renders_t}
    for name, images in degradations.items():
        result[name] = scored(images)
        print(name, json.dumps(result[name]), flush=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
