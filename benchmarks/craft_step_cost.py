"""Seconds per HeadCraft StyleGAN2 training step (one D step + one G step with their lazy R1 and
path-length terms, in the proportions the schedule runs them) for a preset at a resolution, on
random maps: the cost model behind the quick preset's channels (docs/headcraft.md) and the
paper preset's time on a GPU.

    python benchmarks/craft_step_cost.py [--preset paper] [--resolution 256] [--device cuda]
                                         [--steps 32] [--threads 1] [--set FIELD=VALUE ...]

The first 16 steps (one R1 period) warm up; the next ``--steps`` are timed, synchronised on a GPU.
Prints one JSON line: seconds_per_step (mean over the timed steps, so the lazy terms count at their
share), the preset's full schedule in hours at that rate, G's parameter count.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", choices=("quick", "paper"), default="paper")
    parser.add_argument("--resolution", type=int, default=None, help="map size (default: the preset's)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=32)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    args = parser.parse_args()
    from headforge.craft.generative import train as T
    from headforge.craft.generative.stylegan2 import StyleGAN2Trainer
    from headforge.devices import resolve_device

    device = resolve_device(args.device)
    settings = dict(kv.split("=", 1) for kv in args.set)
    if args.resolution:
        settings["resolution"] = str(args.resolution)
    cfg = T.make_config("stylegan2", args.preset, settings)
    torch.set_num_threads(args.threads)
    trainer = StyleGAN2Trainer(cfg)
    T.move(trainer, device)
    gen = torch.Generator().manual_seed(0)
    maps = (torch.randn(64, cfg.channels, cfg.resolution, cfg.resolution, generator=gen) * 0.5).to(device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    warm = cfg.r1_interval
    for step in range(warm + args.steps):
        if step == warm:
            sync()
            start = time.perf_counter()
        trainer.train_step(maps[torch.randint(len(maps), (cfg.batch,), generator=gen)])
    sync()
    per_step = (time.perf_counter() - start) / args.steps
    out = {"preset": args.preset, "resolution": cfg.resolution, "batch": cfg.batch, "device": str(device),
           "gpu": torch.cuda.get_device_name() if device.type == "cuda" else None, "seconds_per_step": round(per_step, 4),
           "schedule_steps": cfg.steps, "schedule_hours": round(per_step * cfg.steps / 3600, 2),
           "g_parameters": sum(p.numel() for p in trainer.G.parameters())}
    print(f"stylegan2 {args.preset} {cfg.resolution} px on {device}: {per_step:.4f} s/step", file=sys.stderr)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
