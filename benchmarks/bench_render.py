"""Renderer benchmark: forward + backward milliseconds on 2 CPU threads (median of runs).

Cases (loss = L1 to a fixed target image, backward to every differentiable input):
  mesh_{256,512}_ms     open-head with the lower neck cut and 4-way subdivided (TRIS triangles,
                        more than the ~20K the issue names): rasterize (numba) -> barycentrics ->
                        interpolate vertex colours + mask -> silhouette antialias -> loss -> backward
  sphere20k_256_ms      the same on a 20,480-triangle icosphere (PyTorch3D's CPU takes 5.3 s here)
  points_{256,512}_ms   100K surface points, K=8, radius 1.5 px: splat -> composite -> loss -> backward
                        (PyTorch3D's CPU takes 13 s at 256^2)
  *_raster_ms           the non-differentiable visibility kernel alone
  splat_vis_256_20k_{numba,torch}_ms
                        point visibility alone (K=8 nearest per pixel), 20K surface points, radius
                        1.5 px, 256^2, from screen-space points on the CPU: the numba kernel vs
                        kernels.splat_torch (the CUDA path, run here on the CPU)
  splat_vis_256_20k_cuda_{torch,numba}_ms
                        only with a CUDA GPU, from CUDA tensors: splat_torch on the device vs the
                        numba kernel with its host round trip (synchronised before and after)
  mesh_256_embree_ms    the same visibility by Embree ray casting (trimesh), for the engine choice
  peak_rss_mb           peak resident memory of the benchmark process

Usage: python benchmarks/bench_render.py [--repeats 7] [--threads 2] [--only mesh,points,splat_vis]
Prints progress to stderr and one JSON line at the end.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys

import numpy as np
import torch
from timing import timed
import trimesh


def mesh_case(vertices: torch.Tensor, faces: torch.Tensor, res: int):
    from headforge.render import mesh
    from headforge.render.camera import Cameras, look_at_head

    cams = Cameras.from_pinhole([look_at_head(res, res, distance=0.55, yaw_deg=20)])
    colours = torch.rand(vertices.shape[1], 3)
    target = torch.rand(1, res, res, 4)
    verts = vertices.clone().requires_grad_()

    def step():
        frags = mesh.rasterize(cams, verts, faces)
        bary = mesh.barycentrics(frags, cams, verts, faces)
        rgb = mesh.interpolate(colours, frags, faces, bary)
        image = torch.cat([rgb, frags.mask[..., None].to(rgb.dtype)], -1)
        image = mesh.antialias(image, frags, cams, verts, faces)
        loss = (image - target).abs().mean()
        verts.grad = None
        loss.backward()

    def raster_only():
        mesh.rasterize(cams, verts, faces)

    return step, raster_only


def points_case(n: int, res: int):
    from headforge.render import points
    from headforge.render.camera import Cameras, look_at_head

    cams = Cameras.from_pinhole([look_at_head(res, res, distance=0.55, yaw_deg=20)])
    sphere = trimesh.creation.icosphere(4, radius=0.1)
    pos, _ = trimesh.sample.sample_surface(sphere, n, seed=0)
    pos = torch.tensor(pos, dtype=torch.float32)[None].requires_grad_()
    feats = torch.rand(1, n, 3).requires_grad_()
    target = torch.rand(1, res, res, 3)

    def step():
        out = points.splat(cams, pos, feats, radius=1.5, K=8)
        loss = (out.features - target).abs().mean() + out.mask.mean()
        pos.grad = feats.grad = None
        loss.backward()

    def raster_only():
        from headforge.render.kernels import splat_numba

        with torch.no_grad():
            xyz = cams.project(pos).double().numpy()
        splat_numba(xyz, np.full((1, n), 1.5), res, res, 8)

    return step, raster_only


def splat_vis_cases(n: int, res: int, device: str):
    """Visibility-only steps from screen-space points on ``device``: {"numba": fn, "torch": fn}."""
    from headforge.render.camera import Cameras, look_at_head
    from headforge.render.kernels import splat_numba, splat_torch

    cams = Cameras.from_pinhole([look_at_head(res, res, distance=0.55, yaw_deg=20)])
    pos, _ = trimesh.sample.sample_surface(trimesh.creation.icosphere(4, radius=0.1), n, seed=0)
    with torch.no_grad():
        xyz = cams.project(torch.tensor(pos, dtype=torch.float32)[None]).to(device)
    radius = torch.full((1, n), 1.5, device=device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def numba_step():
        sync()
        idx, depth = splat_numba(xyz.double().cpu().numpy(), radius.double().cpu().numpy(), res, res, 8)
        _ = torch.from_numpy(idx).to(device), torch.from_numpy(depth).to(device)
        sync()

    def torch_step():
        sync()
        splat_torch(xyz, radius, res, res, 8)
        sync()

    idx_n, _ = splat_numba(xyz.double().cpu().numpy(), radius.double().cpu().numpy(), res, res, 8)
    assert np.array_equal(splat_torch(xyz, radius, res, res, 8)[0].cpu().numpy(), idx_n), "paths disagree"
    return {"numba": numba_step, "torch": torch_step}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--only", default="mesh,points,splat_vis", help="comma-separated case groups")
    args = parser.parse_args()
    groups = set(args.only.split(","))
    if not groups <= {"mesh", "points", "splat_vis"}:
        parser.error(f"--only takes mesh, points, splat_vis; got {args.only}")
    torch.set_num_threads(args.threads)
    import numba

    numba.set_num_threads(args.threads)
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731

    result = {"threads": args.threads, "repeats": args.repeats}
    if "mesh" in groups:
        from headforge.head import HeadModel
        from headforge.head.open_head import load_open_head
        from headforge.head.topology import remove_region, subdivide_head

        head = HeadModel(subdivide_head(remove_region(load_open_head(progress=log), "lower_neck")))
        with torch.no_grad():
            head_verts = head(jaw_pose=torch.tensor([[0.1, 0, 0]])).vertices
        sphere = trimesh.creation.icosphere(5, radius=0.1)
        sphere_verts = torch.tensor(sphere.vertices, dtype=torch.float32)[None]
        sphere_faces = torch.tensor(sphere.faces)
        result["mesh_triangles"] = int(head.faces.shape[0])
        for res in (256, 512):
            log(f"mesh {res}^2")
            step, raster = mesh_case(head_verts, head.faces, res)
            result[f"mesh_{res}_ms"] = round(timed(step, args.repeats), 2)
            result[f"mesh_{res}_raster_ms"] = round(timed(raster, args.repeats), 2)
        log("embree ray casting 256^2 (visibility only)")
        from headforge.render.camera import look_at_head
        from headforge.render.raycast import raycast

        pin = look_at_head(256, 256, distance=0.55, yaw_deg=20)
        verts64, faces64 = head_verts[0].double().numpy(), head.faces.numpy()
        result["mesh_256_embree_ms"] = round(timed(lambda: raycast(verts64, faces64, pin), args.repeats), 2)
        log("sphere 20,480 triangles 256^2")
        step, _ = mesh_case(sphere_verts, sphere_faces, 256)
        result["sphere20k_256_ms"] = round(timed(step, args.repeats), 2)
    if "points" in groups:
        result.update(points=100_000, K=8)
        for res in (256, 512):
            log(f"points {res}^2")
            step, raster = points_case(100_000, res)
            result[f"points_{res}_ms"] = round(timed(step, args.repeats), 2)
            result[f"points_{res}_raster_ms"] = round(timed(raster, args.repeats), 2)
    if "splat_vis" in groups:
        for device in ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",):
            log(f"splat visibility 20K points 256^2 on {device}: numba vs torch")
            tag = "" if device == "cpu" else "cuda_"
            for name, fn in splat_vis_cases(20_000, 256, device).items():
                result[f"splat_vis_256_20k_{tag}{name}_ms"] = round(timed(fn, args.repeats), 2)
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
