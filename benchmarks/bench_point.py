"""PointAvatar on a tracked clip: fit the quick preset at 256^2 (or --preset paper), test-time fit
the held-out last 20 %, score with the platform's protocol; time the trained avatar's rendering
at its final point count. With --nha-run RUN (an NHA run on the same dataset) NHA's figures
under the same protocol are reported beside, as nha_*.

    python benchmarks/bench_point.py --dataset DS [--run RUN] [--nha-run RUN] [--iterations N]
                                     [--preset quick|paper] [--device cpu|cuda] [--set FIELD=VALUE ...]

Prints one JSON line: train_minutes, val_psnr, val_psnr_head, val_akd_px, val_ssim, val_l1 (and
the protocol's other val_* figures), render_fps_256, n_points, and nha_* when asked.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import render_fps  # noqa: E402

KEYS = ("val_psnr", "val_psnr_head", "val_psnr_face", "val_akd_px", "val_eye_opening_error_px",
        "val_mouth_opening_error_px", "val_ssim", "val_l1", "val_ms_ssim", "val_frames")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--dataset", type=Path, required=True, help="a tracked dataset (headforge track)")
    parser.add_argument("--run", type=Path, default=Path("bench_point_run"))
    parser.add_argument("--nha-run", type=Path, default=None, help="an NHA run on the same dataset, scored beside")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--preset", choices=("quick", "paper"), default="quick")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--reuse", action="store_true", help="report a finished --run folder instead of refusing it")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    from headforge.avatars.engine import fit
    from headforge.avatars.pointavatar.config import PointAvatarConfig
    from headforge.avatars.run import load_run, read_info
    from headforge.devices import resolve_device

    if (args.run / "metrics.json").is_file() and not args.reuse:
        sys.exit(f"{args.run} holds a finished run: pass another --run, or --reuse to report it")
    device = resolve_device(args.device)
    if device.type == "cpu":
        torch.set_num_threads(args.threads)
    config = PointAvatarConfig.preset(args.preset)
    if args.iterations:
        config.scale_schedule(args.iterations)
    for assignment in args.set:
        config.override(assignment)
    metrics = fit("pointavatar", args.dataset, args.run, config, log=lambda m: print(m, file=sys.stderr), device=device)
    run = load_run(args.run, device)
    fps = render_fps(run, device)
    out = {"train_minutes": metrics["train_minutes"], **{k: metrics[k] for k in KEYS if k in metrics},
           "val_psnr_no_hole_filling": metrics.get("val_psnr_no_hole_filling"),
           f"render_fps_{run.config.resolution}": fps, "n_points": metrics["n_points"], "iterations": metrics["iterations"],
           "preset": args.preset, "device": str(device), "overrides": args.set, "threads": args.threads}
    if args.nha_run is not None:
        nha = json.loads((args.nha_run / "metrics.json").read_text())
        if read_info(args.nha_run)["dataset"]["fingerprint"] != read_info(args.run)["dataset"]["fingerprint"]:
            sys.exit(f"{args.nha_run} was trained on another dataset than {args.run}")
        out |= {"nha_train_minutes": nha["train_minutes"], **{f"nha_{k}": nha[k] for k in KEYS if k in nha}}
    print(json.dumps(out))


if __name__ == "__main__":
    from headforge.errors import HeadforgeError

    try:
        main()
    except HeadforgeError as err:
        raise SystemExit(f"error: {err}") from None
