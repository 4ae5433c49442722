"""NHA Table 1 protocol on a `headforge synth` benchmark: geometry of the tracked head model
(baseline) and, where given, of NHA runs against the ground truth of every subject.

    python benchmarks/table1.py BENCH [--nha RUN_DIR_PREFIX] [--every 2]

RUN_DIR_PREFIX + "subject_00" etc. are the NHA run folders. Prints a Markdown table and, last,
one JSON line with every figure.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from headforge.metrics.benchmark import evaluate_geometry

KEYS = ("normal_error_head_deg", "normal_error_face_deg", "hausdorff_full_mm", "hausdorff_face_mm",
        "hausdorff_full_camera_mm", "normal_consistency", "hausdorff_full_outer_mm", "head_coverage")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("bench", type=Path)
    parser.add_argument("--nha", type=str, default=None)
    parser.add_argument("--every", type=int, default=2)
    args = parser.parse_args()
    subjects = sorted(p for p in args.bench.iterdir() if (p / "gt" / "geometry.safetensors").is_file())
    rows = {}
    for subject in subjects:
        methods = {"tracked head model": subject}
        if args.nha and Path(args.nha + subject.name).is_dir():
            methods["NHA (headforge)"] = Path(args.nha + subject.name)
        for method, pred in methods.items():
            r = evaluate_geometry(pred, subject, every=args.every)
            rows.setdefault(method, {})[subject.name] = {k: r["mean"][k] for k in KEYS} | {
                "frames": r["frames"], "hair": r["hair"]}
    names = [s.name for s in subjects]
    print("| metric | method | " + " | ".join(f"{n} ({rows['tracked head model'][n]['hair']})" for n in names) + " |")
    print("| --- | --- |" + " --- |" * len(names))
    for k in KEYS:
        for method, per in rows.items():
            print(f"| {k} | {method} | " + " | ".join(f"{per[n][k]:.3f}" if n in per else "–" for n in names) + " |")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
