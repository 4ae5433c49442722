"""Seconds per PointAvatar training step against the number of points, for the paper's network
sizes and the quick preset's, on a tracked dataset at 256^2 (batch 2, 2 CPU threads by default):
the cost model that sized the quick preset (docs/pointavatar.md). On a GPU (``--device cuda``)
the steps are synchronised before each clock read.

    python benchmarks/point_cost.py --dataset DS [--points 5000,20000,100000] [--threads 2]
                                    [--device cpu|cuda] [--batch 2] [--resolution 256]

The points are spread over the canonical head model's surface (a trained cloud's layout), so the
splatting sees a realistic coverage. Prints one JSON line: {preset: {points: s/step}}.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--points", default="5000,20000,100000")
    parser.add_argument("--presets", default="paper,quick")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from headforge.devices import resolve_device

    device = resolve_device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    from headforge.avatars import registry
    from headforge.avatars.frames import FrameData
    from headforge.avatars.pointavatar.model import SCALE
    from headforge.avatars.run import RunAssets
    from headforge.metrics.protocol import TrackedHead
    import trimesh

    method = registry.get("pointavatar")
    assets = RunAssets.from_dataset(args.dataset)
    head = TrackedHead(assets.head_data(), assets.tracking["shape"])
    out = {}
    for preset in args.presets.split(","):
        config = method.Config.preset(preset)
        config.resolution, config.batch = args.resolution, args.batch
        for assignment in args.set:
            config.override(assignment)
        train = FrameData(args.dataset, "train", config.resolution, head).to(device)
        batch = train.batch(torch.arange(args.batch) % len(train))
        out[preset] = {}
        for n in [int(v) for v in args.points.split(",")]:
            config.init_points, config.max_points = n, n
            avatar = method.build(assets, config)
            mesh = trimesh.Trimesh(avatar.canonical_vertices.numpy(), avatar.head.faces.numpy(), process=False)
            pts, _ = trimesh.sample.sample_surface(mesh, n, seed=0)
            with torch.no_grad():
                avatar.points.copy_((torch.as_tensor(pts, dtype=torch.float32) - avatar.centre) / SCALE)
            avatar = avatar.to(device)
            opt = method.optimisers(avatar, config)
            times = []
            for step in range(args.steps + 1):
                sync()
                t = time.perf_counter()
                loss = sum(method.losses(avatar, batch, train.K, config, "train").values())
                for o in opt.values():
                    o.zero_grad()
                loss.backward()
                for o in opt.values():
                    o.step()
                sync()
                times.append(time.perf_counter() - t)
            out[preset][n] = round(statistics.median(times[1:]), 3)
            print(f"{preset} {n} points: {out[preset][n]} s/step", file=sys.stderr)
    print(json.dumps({"seconds_per_step": out, "resolution": args.resolution, "threads": args.threads,
                      "batch": args.batch, "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu"}))


if __name__ == "__main__":
    main()
