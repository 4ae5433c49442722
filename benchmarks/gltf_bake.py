"""What the glTF bake loses: three.js's render of an avatar's animatable .glb (in headless
Chromium) against headforge's own render of the same frames from the same camera.

The .glb is the one ``headforge export RUN --format glb`` writes (here through the viewer's scene,
the run's own frames as its animation). For each of the first ``--frames`` frames of the run
(all splits), the viewer shows the animation's frame from the clip's camera at ``--size`` px,
once on white and once on black (their difference is the drawn pixels' coverage); headforge
renders the frame with the avatar's full model (dynamic texture, neck-pose dependent offsets,
joints moving with the expression, soft matte) on white at the intrinsics scaled to ``--size``.

Figures: ``iou`` the silhouette IoU (coverage > 0.5 on both sides; target >= 0.95), ``psnr``
the full image on white, ``psnr_head`` over the union of both silhouettes; mean and minimum over
frames. To tell the texture's share of the loss from the rest (geometry, the two renderers),
NHA avatars are also rendered by headforge with the baked static texture on their full
geometry (``static``): ``static_vs_full_psnr_head`` is what baking the texture alone loses,
``glb_vs_static_psnr_head`` the rest.

Usage: python benchmarks/gltf_bake.py RUN [--frames 20] [--size 256] [--texture-size 512]
Needs chromium and playwright (the dev extra). Prints progress to stderr and one JSON line at the end.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--texture-size", type=int, default=512)
    args = ap.parse_args()

    from headforge.avatars.reenact import driving_clip, truncate
    from headforge.avatars.run import load_run
    from headforge.metrics.image import psnr
    from headforge.render.camera import Cameras, scale_intrinsics
    from headforge.viewer import browser
    from headforge.viewer.scene import build_scene
    from headforge.viewer.server import ViewerServer

    start = time.perf_counter()
    r = load_run(args.run)
    seq, fps = driving_clip(r.avatar, r.assets, None, "all")
    seq = truncate(seq, args.frames)
    T = int(seq["translation"].shape[0])
    K = scale_intrinsics(r.assets.intrinsics(r.config.resolution), args.size / r.config.resolution)
    scene = build_scene(args.run, args.texture_size, max_frames=T)
    baked = None
    if r.method.name == "nha":
        from headforge.avatars.nha.export import bake_texture

        baked = torch.from_numpy(bake_texture(r.avatar, args.texture_size))[None]
    server = ViewerServer(scene, port=0).start()
    rows = []
    try:
        with browser.page(args.size + 400, max(args.size, 400)) as page:
            browser.open_viewer(page, server.url, args.size)
            for t in range(T):
                on_white = browser.frame(page, t).astype(np.float32) / 255
                page.evaluate("window.viewer.background('#000000')")
                on_black = browser.canvas(page).astype(np.float32) / 255
                page.evaluate("window.viewer.background('#ffffff')")
                coverage = 1 - (on_white - on_black).mean(-1)
                with torch.no_grad():
                    ours = r.avatar.render({k: v[t:t + 1] for k, v in seq.items()}, Cameras.at_origin(K, 1, args.size),
                                           background=1.0)
                want_rgb, want_cov = ours.rgb[0].clamp(0, 1), ours.coverage[0]
                got_rgb, got_cov = torch.from_numpy(on_white), torch.from_numpy(coverage)
                a, b = got_cov > 0.5, want_cov > 0.5
                head = (a | b)[None]
                rows.append({"iou": float((a & b).sum() / (a | b).sum().clamp(min=1)),
                             "psnr": float(psnr(got_rgb[None], want_rgb[None])),
                             "psnr_head": float(psnr(got_rgb[None], want_rgb[None], head))})
                if baked is not None:
                    static = static_render(r.avatar, {k: v[t:t + 1] for k, v in seq.items()},
                                           Cameras.at_origin(K, 1, args.size), baked)[0]
                    rows[-1]["static_vs_full_psnr_head"] = float(psnr(static[None], want_rgb[None], head))
                    rows[-1]["glb_vs_static_psnr_head"] = float(psnr(got_rgb[None], static[None], head))
                print(f"frame {t}: {rows[-1]}", file=sys.stderr)
            errors = list(page.errors)
    finally:
        server.stop()

    def stat(key: str) -> dict:
        values = np.array([row[key] for row in rows])
        return {"mean": round(float(values.mean()), 4), "min": round(float(values.min()), 4)}

    split = {k: stat(k) for k in ("static_vs_full_psnr_head", "glb_vs_static_psnr_head") if k in rows[0]}
    print(json.dumps({"run": str(args.run), "method": r.method.name, "frames": T, "size": args.size,
                      "texture_size": args.texture_size, "glb_bytes": len(scene.files["avatar.glb"]),
                      "iou": stat("iou"), "psnr": stat("psnr"), "psnr_head": stat("psnr_head"), **split,
                      "page_errors": errors, "seconds": round(time.perf_counter() - start, 1)}))


@torch.no_grad()
def static_render(avatar, params: dict, cameras, texture: torch.Tensor) -> torch.Tensor:
    """(1, H, W, 3) on white: an NHA avatar's full geometry (the frame's offsets and joints) with
    the baked static ``texture`` (1, S, S, 3) in place of its texture network, antialiased."""
    from headforge.render import mesh

    verts = avatar.pose(params)[0]
    faces = avatar.head.faces
    frags = mesh.rasterize(cameras, verts, faces)
    uv = mesh.interpolate(avatar.uv_corners, frags, faces, per_corner=True)
    hit = frags.face_id >= 0
    rgb = torch.where(hit[..., None], mesh.texture(uv, texture), torch.ones(3))
    out = mesh.antialias(torch.cat([rgb, hit[..., None].float()], -1), frags, cameras, verts, faces)
    return out[..., :3].clamp(0, 1)


if __name__ == "__main__":
    main()
