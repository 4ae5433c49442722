"""The normal consistency a perfect point set reaches on a synthetic subject: the metric's ceiling.

    python benchmarks/normal_consistency_ceiling.py SUBJECT [--points 4000 40000] [--every 10]

SUBJECT is one `headforge synth` subject folder (with gt/). For each count, that many points are
sampled area-uniformly on the GT head's outer surface itself with its smooth normals
(:func:`headforge.metrics.benchmark.sample_gt_head`, radius 1.5 x the spacing) and scored by
`headforge eval`'s protocol on every ``--every``-th held-out GT frame. What such a set misses of
1 is what the GT's own detail (flat strand faces against smooth normals) leaves any prediction.
Prints a line per count, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import evaluate_geometry, load_subject_gt, sample_gt_head


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("subject", type=Path)
    parser.add_argument("--points", type=int, nargs="+", default=[4000, 40000])
    parser.add_argument("--every", type=int, default=10)
    args = parser.parse_args()
    try:
        gt, info = load_subject_gt(args.subject)
        result = {"subject": str(args.subject), "every": args.every}
        for n in args.points:
            points, normals, spacing, _ = sample_gt_head(gt, info, n)
            with tempfile.TemporaryDirectory() as folder:
                save_file({"frames": gt["frames"].astype(np.int64), "points": points, "normals": normals,
                           "radius": np.full(points.shape[:2], 1.5 * spacing, np.float32)},
                          str(Path(folder) / "geometry.safetensors"))
                m = evaluate_geometry(folder, args.subject, every=args.every)["mean"]
            row = {k: round(m[k], 4) for k in ("normal_consistency", "normal_consistency_scaled", "hausdorff_full_mm")}
            print(f"{n} points (spacing {1000 * spacing:.2f} mm): {row}")
            result[f"points_{n}"] = row | {"spacing_mm": round(1000 * spacing, 3)}
    except HeadforgeError as err:
        raise SystemExit(f"error: {err}") from None
    print(json.dumps(result))


if __name__ == "__main__":
    main()
