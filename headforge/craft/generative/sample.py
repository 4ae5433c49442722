"""Sampling a trained run: maps, their seam post-processing (A.2, before every lookup), meshes
on a head-model identity, sheets of renders (front / side / back), latent interpolation.

Outputs of :func:`write_samples` (``OUT/``): ``sample_NNN/map.png`` (uint16, the
post-processed map), ``sample_NNN/mesh.ply`` (dense mesh, canonical frame, metres),
``sample_NNN/params.json`` (the identity it was applied to), ``sheet.png``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from headforge.craft import uvmap
from headforge.craft.generative import data as D
from headforge.craft.generative import train as T
from headforge.errors import HeadforgeError

BARE = "bare"  # the bare head model: a zero map


@dataclass
class Model:
    """A trained model of a run (or the bare head model) and what sampling needs."""

    method: str
    trainer: object | None
    meta: dict

    @property
    def resolution(self) -> int:
        return int(self.meta["resolution"])


def load(run: str | Path, method: str) -> Model:
    if method == BARE:
        return Model(BARE, None, T.read_run(run))
    trainer, meta = T.load_trained(run, method)
    return Model(method, trainer, meta)


def template(meta: dict):
    from headforge.craft.pipeline import template_for

    return template_for(meta["head_model"], meta["levels"])


def sample_maps(model: Model, n: int, truncation: float = 1.0, seed: int = 0, z: torch.Tensor | None = None) -> np.ndarray:
    """(n, R, R, 3) raw generated maps in metres (before post-processing)."""
    if n < 1:
        raise HeadforgeError(f"-n must be positive, got {n}")
    if not 0 <= truncation <= 1.5:
        raise HeadforgeError(f"--truncation must be within [0, 1.5], got {truncation}")
    R = model.resolution
    if model.method == BARE:
        return np.zeros((n, R, R, 3))
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    return D.from_model(T.sample_latents(model.method, model.trainer, n, truncation, gen, z))


def postprocess(maps: np.ndarray, meta: dict, blend: int = uvmap.BLEND_TEXELS) -> np.ndarray:
    """A.2's seam post-processing of generated maps (N, R, R, 3): equalise the seam sides, blend
    within ``blend`` texels (scaled from the paper's 10 texels at 256 px to the map size), fill
    every empty texel from the nearest covered one."""
    _, duv = template(meta)
    R = maps.shape[1]
    mask = uvmap.texel_islands(duv, R) >= 0
    b = max(1, round(blend * R / 256)) if blend > 0 else 0
    return np.stack([uvmap.postprocess_seams(m, mask, duv, blend=b) for m in maps])


def sample_identities(meta: dict, n: int, seed: int, expressions: bool = False) -> list[dict]:
    """Head-model parameters for ``n`` meshes: identity (and, with ``expressions``, expression
    and jaw) drawn from per-dimension Gaussians of the training registrations' statistics
    (expressions clipped to [0, 1], the head model's range). Zero parameters when the run has
    no statistics (maps without params.json)."""
    stats = meta.get("shape_stats") or {}
    rng = np.random.default_rng([seed, 17])
    out = []
    for _ in range(n):
        p = {}
        for key in ("shape",) + (("expression", "jaw_pose") if expressions else ()):
            if key in stats:
                mean, std = (np.asarray(a) for a in stats[key])
                v = mean + std * rng.standard_normal(mean.shape)
                if key == "expression":
                    v = np.clip(v, 0, 1)
                p[key] = v[None].astype(np.float32)
        out.append(p)
    return out


def meshes(meta: dict, maps: np.ndarray, params: list[dict]) -> list[np.ndarray]:
    """Post-processed maps applied to the identities: neutral identity + looked-up
    displacements, re-oriented by the TBN transfer to each parameter set's expression/jaw."""
    from headforge.craft.animate import Animator

    tpl, duv = template(meta)
    out = []
    for m, p in zip(maps, params):
        anim = Animator(tpl, duv, m, p)
        frame = {k: torch.as_tensor(v) for k, v in p.items() if k != "shape"}
        out.append((anim.posed_mesh(frame) if frame else anim.neutral_mesh()).numpy())
    return out


def sheet(vertices: list[np.ndarray], faces: np.ndarray, size: int = 160, labels: list[str] | None = None) -> np.ndarray:
    """uint8 sheet, one row per mesh: front | side | back."""
    import cv2

    from headforge.craft.animate import render_views

    rows = []
    for i, v in enumerate(vertices):
        img = (np.clip(render_views(v, faces, size, (0.0, 90.0, 180.0)), 0, 1) * 255).astype(np.uint8).copy()
        if labels:
            cv2.putText(img, labels[i], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
        rows.append(img)
    return np.concatenate(rows, 0)


def sheet_grid(vertices: list[np.ndarray], faces: np.ndarray, columns: int = 2, size: int = 160,
               labels: list[str] | None = None) -> np.ndarray:
    """Meshes in ``columns`` columns, each a front | side | back triple."""
    strips = [sheet([v], faces, size, [labels[i]] if labels else None) for i, v in enumerate(vertices)]
    while len(strips) % columns:
        strips.append(np.full_like(strips[0], 255))
    return np.concatenate([np.concatenate(strips[i:i + columns], 1) for i in range(0, len(strips), columns)], 0)


def write_samples(run: str | Path, method: str, output: str | Path, n: int, truncation: float = 1.0, seed: int = 0,
                  identity: str | Path | None = None, log=print) -> list[Path]:
    """``n`` samples of a run's model as maps, meshes and a sheet (module doc)."""
    from headforge.craft.scans import write_ply, write_png

    model = load(run, method)
    maps = postprocess(sample_maps(model, n, truncation, seed), model.meta)
    if identity is not None:
        p = json.loads(Path(identity).read_text())
        p = p.get("params", p)
        if "shape" not in p:
            raise HeadforgeError(f"{identity} has no 'shape' parameters (a params.json of headforge craft register)")
        params = [{"shape": np.asarray(p["shape"], np.float32).reshape(1, -1)}] * n
    else:
        params = sample_identities(model.meta, n, seed)
    verts = meshes(model.meta, maps, params)
    tpl, _ = template(model.meta)
    faces = tpl.faces.numpy()
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    folders = []
    for i, (m, v, p) in enumerate(zip(maps, verts, params)):
        f = output / f"sample_{i:03d}"
        f.mkdir(exist_ok=True)
        uvmap.write_map(f / "map.png", m)
        write_ply(f / "mesh.ply", v, faces)
        T.write_json(f / "params.json", {"head_model": model.meta["head_model"], "levels": model.meta["levels"],
                                         "params": {k: np.asarray(x).tolist() for k, x in p.items()},
                                         "run": str(Path(run).resolve()), "method": method, "seed": seed,
                                         "truncation": truncation, "index": i})
        folders.append(f)
    write_png(output / "sheet.png", sheet_grid(verts, faces, columns=min(4, n), labels=[f"{method} {i}" for i in range(n)]))
    log(f"{n} samples of {method} (truncation {truncation}, seed {seed}) in {output}; sheet {output / 'sheet.png'}")
    return folders


def interpolate(run: str | Path, method: str, output: str | Path, steps: int = 6, seeds: tuple[int, int] = (0, 1),
                truncation: float = 1.0, log=print) -> Path:
    """Maps and meshes along a straight line between two latents (StyleGAN2: in Z, the mapping
    follows; VAE/PCA: their latent), on the mean identity; writes ``strip.png`` and the maps."""
    from headforge.craft.scans import write_png

    model = load(run, method)
    if model.method in (BARE, "vqvae"):
        raise HeadforgeError(f"{method} has no continuous latent to interpolate (use stylegan2, vae or pca)")
    if steps < 2:
        raise HeadforgeError(f"--steps must be at least 2, got {steps}")
    dim = T.latent_dim(model.method, model.trainer)
    za = torch.randn(1, dim, generator=torch.Generator().manual_seed(seeds[0]))
    zb = torch.randn(1, dim, generator=torch.Generator().manual_seed(seeds[1]))
    t = torch.linspace(0, 1, steps)[:, None]
    z = (1 - t) * za + t * zb
    maps = postprocess(sample_maps(model, steps, truncation, 0, z), model.meta)
    mean_id = sample_identities({"shape_stats": {k: (v[0], [0.0] * len(v[1])) for k, v in model.meta.get("shape_stats", {}).items()}},
                                steps, 0)
    verts = meshes(model.meta, maps, mean_id)
    tpl, _ = template(model.meta)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    for i, m in enumerate(maps):
        uvmap.write_map(output / f"map_{i:02d}.png", m)
    strip = np.concatenate([sheet([v], tpl.faces.numpy(), 160, [f"t={float(t[i]):.2f}"]) for i, v in enumerate(verts)], 0)
    write_png(output / "strip.png", strip)
    log(f"{steps} maps from seed {seeds[0]} to seed {seeds[1]} in {output}; strip {output / 'strip.png'}")
    return output / "strip.png"
