"""Where a prediction's full-head normal error is: per ground-truth label (face, hair, ...).

    python benchmarks/normal_error_by_label.py SUBJECT [PRED ...] [--every 2] [--gt]

SUBJECT is one `headforge synth` subject folder (with gt/); each PRED is what `headforge eval`
takes as a prediction (a tracked dataset, e.g. SUBJECT itself for the tracked head model, or a
folder with geometry.safetensors, e.g. an NHA run); ``--gt`` also scores the GT meshes
themselves. Per label of the GT's full head, over every ``--every``-th validation GT frame
(`headforge.metrics.benchmark.normal_error_by_label`): the pooled angle error on the covered
pixels (degrees), the fraction of the label's pixels covered, and the label's share of the
prediction's covered pixels. Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import normal_error_by_label


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("subject", type=Path)
    parser.add_argument("predictions", type=Path, nargs="*")
    parser.add_argument("--every", type=int, default=2)
    parser.add_argument("--gt", action="store_true", help="also score the GT meshes themselves")
    args = parser.parse_args()
    if not args.predictions and not args.gt:
        raise SystemExit("error: give at least one prediction, or --gt")
    results = {}
    for pred in ([None] if args.gt else []) + args.predictions:
        try:
            split = normal_error_by_label(pred, args.subject, "val", args.every)
        except HeadforgeError as err:
            raise SystemExit(f"error: {err}") from None
        results[str(pred or "gt")] = split
        pooled = sum(r["share"] * r["deg"] for r in split.values())
        print(f"{pred or 'GT meshes'}: pooled full head {pooled:.2f} deg")
        for name, r in split.items():
            print(f"  {name:10s} {r['deg']:6.2f} deg  covered {r['covered']:.3f}  share {r['share']:.3f}")
    print(json.dumps({"subject": str(args.subject), "every": args.every, "predictions": results}))


if __name__ == "__main__":
    main()
