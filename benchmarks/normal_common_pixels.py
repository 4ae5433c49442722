"""Full-head normal error of two predictions on the pixels both cover, against a synthetic subject.

    python benchmarks/normal_common_pixels.py SUBJECT PRED_A PRED_B [--every 2]

SUBJECT is one `headforge synth` subject folder (with gt/); PRED_A and PRED_B are what
`headforge eval` takes as a prediction (a tracked dataset, e.g. SUBJECT itself for the tracked
head model, or a folder with geometry.safetensors, e.g. an NHA run). Table 1's normal error
scores each prediction on the GT full-head pixels *it* covers, so two predictions that cover
different parts of the hair are scored on different pixels. Here, for every ``--every``-th GT
frame of the validation split (mean over frames, degrees):

- ``common_deg``: each prediction's angle error on the GT full-head pixels both cover, and
  ``common_hair_deg`` on the hair among them;
- ``only_deg``: each prediction's error on the pixels only it covers, and ``only_share``: their
  share of the pixels it covers.

Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import load_prediction, load_subject_gt, prediction_rows, read_gt_maps, render_normals


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def mean_or_nan(values: np.ndarray) -> float:
    return float(values.mean()) if values.size else float("nan")


def compare(subject: Path, pred_a: Path, pred_b: Path, every: int) -> dict:
    gt, info = load_subject_gt(subject)
    frames = gt["frames"][gt["frames"] >= info["train_frames"]][::every]
    if len(frames) == 0:
        raise HeadforgeError(f"{subject} has no ground-truth frames in its validation split")
    K, res = np.asarray(info["intrinsics"]), int(info["resolution"])
    preds = {}
    for key, path in (("a", pred_a), ("b", pred_b)):
        pred = load_prediction(path, frames)
        preds[key] = (pred, prediction_rows(pred, frames, path))
    per_frame = []
    for j, f in enumerate(frames):
        gt_n, labels = read_gt_maps(subject, int(f), res)
        gt_n /= np.maximum(np.linalg.norm(gt_n, axis=-1, keepdims=True), 1e-6)
        head, hair = np.isin(labels, info["head_labels"]), labels == info["labels"]["hair"]
        err, cov = {}, {}
        for key, (pred, pred_rows) in preds.items():
            n = render_normals(pred.vertices[pred_rows[j]], pred.faces, K, res)
            cov[key] = head & (np.linalg.norm(n, axis=-1) > 0.5)
            err[key] = angle_deg(n, gt_n)
        both = cov["a"] & cov["b"]
        row = {}
        for key, other in (("a", "b"), ("b", "a")):
            only = cov[key] & ~cov[other]
            row[key] = {"common_deg": mean_or_nan(err[key][both]), "common_hair_deg": mean_or_nan(err[key][both & hair]),
                        "only_deg": mean_or_nan(err[key][only]), "only_share": float(only.sum() / max(cov[key].sum(), 1))}
        per_frame.append(row)
    out = {"subject": str(subject), "frames": len(per_frame)}
    for key, path in (("a", pred_a), ("b", pred_b)):
        out[key] = {"prediction": str(path)} | {
            k: round(float(np.nanmean([r[key][k] for r in per_frame])), 3) for k in per_frame[0][key]}
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("subject", type=Path)
    parser.add_argument("pred_a", type=Path)
    parser.add_argument("pred_b", type=Path)
    parser.add_argument("--every", type=int, default=2)
    args = parser.parse_args()
    try:
        if args.every < 1:
            raise HeadforgeError(f"--every must be >= 1, got {args.every}")
        print(json.dumps(compare(args.subject, args.pred_a, args.pred_b, args.every)))
    except HeadforgeError as err:  # a wrong subject or prediction folder: one line, no traceback
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
