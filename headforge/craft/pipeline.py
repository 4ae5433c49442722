"""One scan in, one registered template and baked displacement map out (a batch item).

Item folder (``MAPS/<key>/``): ``map.png`` (uint16 RGB, post-processed, every texel filled),
``map_mask.png`` (coverage of the raw bake), ``registered.ply`` (dense registered mesh,
canonical frame), ``params.json`` (head model parameters, alignment), ``metrics.json``,
``preview.png`` (scan | registered | registered->scan distance heat map, 0-5 mm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from headforge.craft import register as reg_mod
from headforge.craft import uvmap
from headforge.craft.scans import (
    Scan,
    detect_scan_landmarks,
    load_generated,
    read_scan,
    render_mesh,
    write_ply,
    write_png,
)
from headforge.errors import HeadforgeError

SCAN_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")


@dataclass
class ItemOptions:
    preset: str = "quick"
    map_size: int = 256
    units: str = "auto"
    up: str = "+y"
    forward: str = "+z"
    head_model: str = "open-head"
    flame_dir: str | None = None
    ablation: str = "both"  # both | stage1 | stage2 | stage1_weights2
    steps_scale: float = 1.0  # multiplies every step count (smoke runs, tests)


@lru_cache(maxsize=2)
def template_for(head_model: str, levels: int, flame_dir: str | None = None):
    from headforge.head import load_data
    from headforge.head.uv import craft_layout

    data = load_data(head_model, flame_dir)
    template = reg_mod.build_template(data, levels)
    layout = craft_layout(data)
    duv = uvmap.dense_uv(layout, levels, data.faces, template.subdivision.faces)
    return template, duv


def config_for(options: ItemOptions) -> reg_mod.RegisterConfig:
    from dataclasses import replace

    cfg = reg_mod.RegisterConfig.preset(options.preset)
    if options.ablation == "stage1":
        cfg.stage2 = replace(cfg.stage2, enabled=False)
    elif options.ablation == "stage2":
        cfg.stage1 = replace(cfg.stage1, enabled=False)
    elif options.ablation == "stage1_weights2":
        cfg.stage1 = replace(cfg.stage1, chamfer=cfg.stage2.chamfer, edge=cfg.stage2.edge, laplacian=cfg.stage2.laplacian)
        cfg.stage2 = replace(cfg.stage2, enabled=False)
    elif options.ablation != "both":
        raise HeadforgeError(f"unknown ablation {options.ablation!r}")
    if not 0 < options.steps_scale <= 10:
        raise HeadforgeError(f"--steps-scale must be within (0, 10], got {options.steps_scale}")
    if options.steps_scale != 1.0:
        k = options.steps_scale
        cfg.landmark_steps = max(20, int(cfg.landmark_steps * k))
        cfg.stage1 = replace(cfg.stage1, steps=max(1, int(cfg.stage1.steps * k)))
        cfg.stage2 = replace(cfg.stage2, steps=max(1, int(cfg.stage2.steps * k)))
        cfg.scan_points = max(5_000, int(cfg.scan_points * min(1.0, k)))
    return cfg


def list_scans(folder: str | Path) -> list[tuple[str, str]]:
    """(key, path) of every scan in a folder: generated scan folders and mesh files."""
    folder = Path(folder)
    if not folder.is_dir():
        raise HeadforgeError(f"no scan folder at {folder}")
    items = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith((".", "_")) or p.name.endswith(".partial"):  # a scan still being written (or killed)
            continue
        if p.is_dir() and (p / "scan.ply").exists():
            items.append((p.name, str(p)))
        elif p.is_file() and p.suffix.lower() in SCAN_SUFFIXES and not p.name.endswith(".partial.ply"):
            items.append((p.stem, str(p)))
    if not items:
        raise HeadforgeError(f"{folder} holds no scans (scan folders with scan.ply, or OBJ/PLY/GLB/STL files)")
    return items


def load_any(path: str | Path, options: ItemOptions) -> tuple[Scan, dict | None]:
    """A generated scan folder (with its ground truth) or an external mesh file."""
    path = Path(path)
    if path.is_dir():
        scan, spec, gt = load_generated(path)
        return scan, {"spec": spec, **gt}
    landmark_file = None
    for cand in (path.with_suffix(".ljson"), path.with_suffix(".landmarks.json")):
        if cand.exists():
            landmark_file = cand
    scan = read_scan(path, options.units, options.up, options.forward, landmark_file)
    if scan.landmarks is None:
        scan.landmarks = detect_scan_landmarks(scan)
        scan.meta["landmarks"] = "detected (MediaPipe on renders, lifted by ray casting)"
    else:
        scan.meta["landmarks"] = str(landmark_file)
    return scan, None


def heat_colours(d_m: np.ndarray, max_mm: float = 5.0) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["turbo"](np.clip(1000 * d_m / max_mm, 0, 1))[:, :3]


def preview(template, registration, scan: Scan, distances: np.ndarray, size: int = 256) -> np.ndarray:
    faces = template.faces.numpy()
    v = registration.vertices.numpy()
    target = v[template.regions["face"]].mean(0) + np.array([0.0, -0.02, -0.06])
    grey = lambda n: np.tile([0.75, 0.75, 0.78], (n, 1))
    row = []
    for yaw in (25.0, 150.0):
        row.append(render_mesh(registration.scan_canonical, scan.faces, grey(len(scan.vertices)), size, yaw, target))
        row.append(render_mesh(v, faces, grey(len(v)), size, yaw, target))
        row.append(render_mesh(v, faces, heat_colours(distances), size, yaw, target))
    img = np.concatenate([np.concatenate(row[:3], 1), np.concatenate(row[3:], 1)], 0)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def _atomic_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(data, indent=1, default=float))
    tmp.replace(path)


def register_item(key: str, payload: dict, workdir: Path) -> dict:
    """Batch item: ``payload`` = {"path": ..., **ItemOptions fields}. Writes the item folder."""
    options = ItemOptions(**{k: v for k, v in payload.items() if k != "path"})
    config = config_for(options)
    template, duv = template_for(options.head_model, config.levels, options.flame_dir)
    scan, gt = load_any(payload["path"], options)
    registration = reg_mod.register(template, scan, config)
    labels = None if gt is None else gt["labels"]
    lmk_gt = None if gt is None else gt["landmarks"]
    metrics = reg_mod.evaluate(template, registration, registration.vertices, scan, labels, lmk_gt)
    if gt is not None and config.stage1.enabled and config.stage2.enabled:
        m1 = reg_mod.evaluate(template, registration, registration.stage1, scan, labels)
        metrics["stage1"] = {"scan_to_reg": m1["scan_to_reg"], "max_edge_ratio": m1["max_edge_ratio"]}
    # bake, post-process, write, read back, apply: the round trip
    raw, mask = uvmap.bake(registration.displacement, duv, options.map_size)
    filled = uvmap.postprocess_seams(raw, mask, duv, blend=0)
    uvmap.write_map(workdir / "map.png", filled, mask)
    back = uvmap.read_map(workdir / "map.png", options.map_size)
    applied = uvmap.apply_map(template, back, duv, registration.alignment.params, config.smooth_iterations)
    rt = (applied - registration.vertices).norm(dim=-1).numpy()
    free = np.union1d(template.regions["face"], template.regions["scalp"])
    metrics["roundtrip"] = {"median_mm": float(1000 * np.median(rt)), "p95_mm": float(1000 * np.percentile(rt, 95)),
                            "free_median_mm": float(1000 * np.median(rt[free])), "map_size": options.map_size,
                            "quantum_um": 1e6 * uvmap.QUANTUM_M}
    metrics["seconds"] = registration.seconds
    metrics["vertices"] = template.n_vertices
    metrics["scan"] = {"name": scan.name, "vertices": len(scan.vertices), **{k: str(v) for k, v in scan.meta.items()}}
    if gt is not None:
        metrics["hair_style"], metrics["variant"] = gt["spec"]["hair_style"], gt["spec"]["variant"]
        metrics["expression"] = bool(gt["spec"]["expression"])
    write_ply(workdir / "registered.ply", registration.vertices.numpy(), template.faces.numpy())
    d = reg_mod.surface_distance(registration.vertices.numpy(), registration.scan_canonical, scan.faces)
    write_png(workdir / "preview.png", preview(template, registration, scan, d))
    a = registration.alignment
    _atomic_json(workdir / "params.json", {
        "head_model": options.head_model, "levels": config.levels,
        "params": {k: v.tolist() for k, v in a.params.items()},
        "alignment": {"scale": a.scale, "scale_found": a.scale_found, "rotation": a.rotation.tolist(),
                      "translation": a.translation.tolist(), "landmark_median_mm": a.landmark_median_mm},
        "config": reg_mod.config_dict(config), "options": payload})
    _atomic_json(workdir / "metrics.json", metrics)
    return {**reg_mod.summary(metrics), "roundtrip_mm": metrics["roundtrip"]["median_mm"], "seconds": registration.seconds}


def map_sheet(folders: list[Path], columns: int = 4, size: int = 192) -> np.ndarray:
    """A sheet of baked maps (previews of map.png), named."""
    import cv2

    tiles = []
    for f in folders:
        m = uvmap.read_map(f / "map.png")
        img = cv2.resize(uvmap.map_preview(m), (size, size), interpolation=cv2.INTER_AREA).copy()
        cv2.putText(img, f.name, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    if not tiles:
        raise HeadforgeError("no maps to show")
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    sheet = np.zeros((rows * size, columns * size, 3), np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * size:(r + 1) * size, c * size:(c + 1) * size] = t
    return sheet


def torch_threads() -> None:
    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
