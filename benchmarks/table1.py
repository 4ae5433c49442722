"""NHA Table 1 protocol on a `headforge synth` benchmark: geometry of the tracked head model
(baseline) and, where given, of NHA runs against the ground truth of every subject.

    python benchmarks/table1.py BENCH [--nha RUN_DIR_PREFIX] [--every 2]

RUN_DIR_PREFIX + "subject_00" etc. are the NHA run folders (trained with `headforge fit nha SUBJECT
--supervision gt` for the seed's protocol: NHA Sec. 4.1 trains its synthetic subjects on their GT
normal maps, semantic maps and landmarks; each run's supervision is printed and in the JSON).
Prints a Markdown table and, last,
one JSON line with every figure. With NHA runs it adds the normal error of both methods on the
pixels both cover (``paired_*``; `headforge.metrics.benchmark.paired_normal_error`): the
protocol's own normal error scores each method on its own coverage, so the bald tracked model is
not charged for the hair it leaves uncovered.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from headforge.metrics.benchmark import evaluate_geometry, paired_normal_error

PAIRED = ("normal_error_head_deg", "normal_error_face_deg")
KEYS = ("normal_error_head_deg", "normal_error_face_deg", "hausdorff_full_mm", "hausdorff_face_mm",
        "hausdorff_full_camera_mm", "normal_consistency", "hausdorff_full_outer_mm", "hausdorff_full_scaled_mm",
        "hausdorff_face_scaled_mm", "alignment_scale", "normal_consistency_scaled", "head_coverage")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("bench", type=Path)
    parser.add_argument("--nha", type=str, default=None)
    parser.add_argument("--every", type=int, default=2)
    args = parser.parse_args()
    subjects = sorted(p for p in args.bench.iterdir() if (p / "gt" / "geometry.safetensors").is_file())
    rows, supervision = {}, {}
    for subject in subjects:
        methods = {"tracked head model": subject}
        if args.nha and Path(args.nha + subject.name).is_dir():
            methods["NHA (headforge)"] = Path(args.nha + subject.name)
        for method, pred in methods.items():
            r = evaluate_geometry(pred, subject, every=args.every)
            rows.setdefault(method, {})[subject.name] = {k: r["mean"][k] for k in KEYS} | {
                "frames": r["frames"], "hair": r["hair"]}
        if "NHA (headforge)" in methods:
            saved = json.loads((methods["NHA (headforge)"] / "run.json").read_text())["config"]
            supervision[subject.name] = saved.get("supervision", "predicted")
            pair = paired_normal_error(methods["NHA (headforge)"], subject, subject, every=args.every)["mean"]
            for method, prefix in (("NHA (headforge)", ""), ("tracked head model", "reference_")):
                rows[method][subject.name] |= {f"paired_{k}": pair[prefix + k] for k in PAIRED}
            rows["NHA (headforge)"][subject.name]["paired_common_coverage"] = pair["common_coverage"]  # one per pair
    names = [s.name for s in subjects]
    if supervision:
        print("NHA runs' supervision: " + ", ".join(f"{k} {v}" for k, v in supervision.items()) + "\n")
    print("| metric | method | " + " | ".join(f"{n} ({rows['tracked head model'][n]['hair']})" for n in names) + " |")
    print("| --- | --- |" + " --- |" * len(names))
    for k in KEYS + tuple(f"paired_{k}" for k in PAIRED) + ("paired_common_coverage",):
        for method, per in rows.items():
            print(f"| {k} | {method} | " + " | ".join(f"{per[n][k]:.3f}" if k in per.get(n, {}) else "–"
                                                      for n in names) + " |")
    print(json.dumps(rows | {"supervision": supervision}))


if __name__ == "__main__":
    main()
