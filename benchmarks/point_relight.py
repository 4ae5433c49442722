"""PointAvatar's relighting and albedo against a synth subject's ground truth (PointAvatar §4.2):
for the held-out frames with ``gt/relit`` and ``gt/albedo`` (rendered under the benchmark's
second light, and the albedo alone), at the run's test-time-fitted parameters:

- relit: the avatar under the benchmark's second light (2nd-order SH with the learned albedo and
  normals) vs the relit GT, beside the un-relit render (the learned shading) vs the same relit GT
  -- relighting must score above not relighting;
- albedo: the composited learned albedo vs the GT albedo after one least-squares scale per channel
  (the albedo x shading split is known up to a scale).

PSNR over the protocol's head pixels (both images matted on white by the GT mask).

    python benchmarks/point_relight.py RUN SUBJECT [--picture relit.png]

Prints one JSON line. ``--picture``: the first three frames as rows of relit GT | relit avatar |
un-relit avatar | GT albedo | scaled learned albedo (each matted on white by the GT mask).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("subject", type=Path)
    parser.add_argument("--picture", type=Path, default=None)
    args = parser.parse_args()
    from PIL import Image

    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.bench.synthetic import relight
    from headforge.metrics.protocol import TrackedHead, matte_on_white
    from headforge.render.camera import Cameras

    r = load_run(args.run)
    if not getattr(r.avatar, "relightable", False):
        raise SystemExit(f"{args.run} is a {r.method.name} run: relighting needs a point avatar")
    res = r.config.resolution
    head = TrackedHead(r.assets.head_data(), r.assets.tracking["shape"])
    val = FrameData(args.subject, "val", res, head)
    files = {int(p.stem): p for p in (args.subject / "gt" / "relit").glob("*.png")}
    rows = [i for i, f in enumerate(val.index.tolist()) if f in files]
    if not rows:
        raise SystemExit(f"{args.subject} has no gt/relit images of held-out frames")

    def load(path: Path) -> torch.Tensor:
        return torch.from_numpy(np.asarray(Image.open(path).convert("RGB").resize((res, res), Image.BILINEAR), np.float32) / 255)

    def psnr(a, b, w):
        mse = (((a - b) ** 2) * w[..., None]).sum() / (w.sum() * 3).clamp(min=1)
        return float(10 * torch.log10(1 / mse.clamp(min=1e-10)))

    sums = {"relit": [], "unrelit": [], "albedo": []}
    tiles = []
    with torch.no_grad():
        for row in rows:
            batch = val.batch(torch.tensor([row]))
            f = int(batch["index"][0])
            cams = Cameras.at_origin(val.K, 1, res)
            params = r.avatar.frame_params(batch["index"])
            mask, region = batch["mask"], batch["region"].float()
            relit_gt = matte_on_white(load(files[f])[None], mask)
            albedo_gt = matte_on_white(load(args.subject / "gt" / "albedo" / f"{f:05d}.png")[None], mask)
            lit = r.avatar.render(params, cams, light={"sh": relight()})
            plain = r.avatar.render(params, cams, layers=True)
            sums["relit"].append(psnr(lit.rgb.clamp(0, 1), relit_gt, region))
            sums["unrelit"].append(psnr(plain.rgb.clamp(0, 1), relit_gt, region))
            inside = region * (mask > 0.5) * (plain.coverage > 0.5)
            a, g = plain.albedo, albedo_gt
            scale = (a * g * inside[..., None]).sum((0, 1, 2)) / (a * a * inside[..., None]).sum((0, 1, 2)).clamp(min=1e-8)
            sums["albedo"].append(psnr((a * scale).clamp(0, 1), g, inside))
            if len(tiles) < 3:
                m = mask[..., None]
                covered = (plain.coverage > 0.5)[..., None].float() * m
                tiles.append(torch.cat([relit_gt, lit.rgb * m + 1 - m, plain.rgb * m + 1 - m, g,
                                        (a * scale) * covered + 1 - covered], 2)[0].clamp(0, 1))
    if args.picture is not None:
        from headforge.render.io import write_png

        write_png(args.picture, torch.cat(tiles, 0))
    out = {f"{k}_psnr_head": round(float(np.mean(v)), 3) for k, v in sums.items()}
    out |= {"frames": len(rows), "relit_beats_unrelit": out["relit_psnr_head"] > out["unrelit_psnr_head"]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
