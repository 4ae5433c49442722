"""Held-out PSNR against wall-clock training minutes for several runs (their val.csv: the
engine's in-training validation, a few held-out frames after a short test-time fit), with each
run's final protocol PSNR (metrics.json) as a marker at its training time.

    python benchmarks/plot_val_psnr.py RUN [RUN ...] -o psnr_vs_minutes.png [--labels A,B]

Prints one JSON line: per run, the minutes and PSNR of its last validation and its final PSNR.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--labels", default=None, help="comma-separated legend labels (default: method, run name)")
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = args.labels.split(",") if args.labels else [None] * len(args.runs)
    fig, ax = plt.subplots(figsize=(6, 4))
    out = {}
    for run, label in zip(args.runs, labels):
        val = np.array([[float(v) for v in line.split(",")] for line in (run / "val.csv").read_text().splitlines() if line])
        metrics = json.loads((run / "metrics.json").read_text())
        label = label or f"{metrics['method']} ({run.name})"
        line, = ax.plot(val[:, 1] / 60, val[:, 2], marker="o", label=f"{label}: in-training validation")
        ax.scatter([metrics["train_minutes"]], [metrics["val_psnr"]], marker="*", s=160, color=line.get_color(),
                   label=f"{label}: all held-out frames, final")
        out[label] = {"last_val_minutes": round(val[-1, 1] / 60, 2), "last_val_psnr": val[-1, 2],
                      "final_psnr": metrics["val_psnr"], "train_minutes": metrics["train_minutes"]}
    ax.set(xlabel="training wall-clock minutes", ylabel="held-out PSNR (dB)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.output, dpi=110)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
