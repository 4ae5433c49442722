"""``headforge craft fit``: a trained HeadCraft model fitted to one observation (App. B.1) -- a
full scan (registration, then the whole map) or a depth map / point cloud (partial
registration, then the observed texels) -- and the completed head written out; hair transfer
between two fits (§4.3).

Output folder (written as ``OUT.partial`` and renamed when complete):

- ``completed.ply`` -- the completed head in the observation's own frame and units (metres);
  ``completed_canonical.ply`` in the canonical head frame;
- ``map.png`` -- the completed displacement map (uint16, post-processed as a generated map);
- ``partial_map.png`` + ``partial_map_mask.png`` -- the observation's partial map and its
  observed texels (depth / cloud inputs); full scans: ``registered_map.png``;
- ``latent.safetensors`` -- StyleGAN2: ``ws`` (1, num_ws, w_dim), ``z`` and the noise
  tensors; PCA: ``coefficients``;
- ``params.json`` -- head-model parameters, the alignment (observation -> canonical), the
  method, the configs; ``metrics.json``; ``picture.png`` -- observation | completion |
  ground truth (``--gt``) | error, front and back.

Frames: canonical head frame (metres, y up, face toward +z); observation head axes W
(:mod:`headforge.craft.observe`); the alignment maps W to canonical.
"""

from __future__ import annotations

import json
import shutil
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from headforge.craft import uvmap
from headforge.craft.generative import data as D
from headforge.craft.generative import invert as I
from headforge.errors import HeadforgeError

METHODS = ("stylegan2", "pca", "mean", "bare")
LOWER_NECK_MARGIN_M = 0.01  # predicted points this far below the lowest GT point are left out of the scores


@dataclass
class FitOptions:
    method: str = "stylegan2"
    preset: str = "quick"
    camera: str | None = None  # depth maps: camera JSON (default: beside the depth map)
    depth_scale: float | None = None
    density: str = "auto"  # auto | dense | sparse (partial observations)
    up: str | None = None  # the file's axes and units; None: a cloud's default (a sensor's camera frame: -y, -z,
    forward: str | None = None  # metres) or a scan's (+y, +z, units guessed)
    units: str | None = None
    noise: bool = True  # the optional noise step
    seed: int = 0
    z_starts: int = 1  # StyleGAN2 depth fits: z initialisations (B.1: one); see InvertConfig
    combine: str = "best"  # with z_starts > 1: best | mean
    truncation: float = 1.0  # StyleGAN2 depth fits: psi of the z step (B.1: none, i.e. 1); see InvertConfig
    steps_scale: float = 1.0  # multiplies every optimisation step count (smoke runs, tests)


@dataclass
class Model:
    """What a fit needs of a run: the trained model (or none), its meta, template and layout."""

    method: str
    trainer: object | None
    meta: dict
    template: object
    duv: object
    train_maps: torch.Tensor | None = None

    @property
    def resolution(self) -> int:
        return int(self.meta["resolution"])

    @property
    def levels(self) -> int:
        return int(self.meta["levels"])

    def face(self) -> np.ndarray:
        return D.face_texels(self.meta["head_model"], self.levels, self.resolution)


def load_model(run: str | Path, method: str) -> Model:
    from headforge.craft.generative import sample as S
    from headforge.craft.generative import train as T

    if method not in METHODS:
        raise HeadforgeError(f"unknown --method {method!r}; choose {', '.join(METHODS)}")
    if method in ("stylegan2", "pca"):
        trainer, meta = T.load_trained(run, method)
    else:
        trainer, meta = None, T.read_run(run)
    template, duv = S.template(meta)
    maps = T.train_maps(run) if method == "mean" else None
    return Model(method, trainer, meta, template, duv, maps)


# ---------------------------------------------------------------- fitting a map
@dataclass
class MapFit:
    map_units: torch.Tensor  # (1, 3, R, R) model units, before post-processing
    map_m: np.ndarray  # (R, R, 3) metres, post-processed
    latent: dict[str, torch.Tensor]
    seconds: float
    history: dict = field(default_factory=dict)
    perceptual: str | None = None


def fit_map(model: Model, target_m: np.ndarray, mask: np.ndarray | None, config: I.InvertConfig,
            noise: bool = True, seed: int = 0, progress=None) -> MapFit:
    """The model's map for a (R, R, 3) metre map, observed where ``mask`` (None: everywhere)."""
    from headforge.craft.generative import sample as S

    start = time.perf_counter()
    R = model.resolution
    if target_m.shape[:2] != (R, R):
        raise HeadforgeError(f"the map is {target_m.shape[0]} px but the model was trained at {R} px")
    U = D.to_model(target_m[None])
    latent, hist, perc = {}, {}, None
    if model.method == "stylegan2":
        if mask is None:
            inv = I.invert_full(model.trainer, U, config, noise, seed, progress)
        else:
            inv = I.invert_partial(model.trainer, U, mask, model.face(), config, noise, seed, progress)
        out, hist, perc = inv.map, inv.history, inv.perceptual
        latent = {"ws": inv.ws, **({"z": inv.z} if inv.z is not None else {}), **{f"noise.{k}": v for k, v in inv.noise.items()}}
    elif model.method == "pca":
        out, coeff = I.fit_pca(model.trainer.model, U, mask, config.pca_sigma_m / D.SCALE_M)
        latent = {"coefficients": coeff}
    elif model.method == "mean":
        out = I.mean_map(model.train_maps)
    else:
        out = torch.zeros_like(U)
    map_m = S.postprocess(D.from_model(out), model.meta)[0] if model.method != "bare" else np.zeros((R, R, 3))
    return MapFit(out, map_m, latent, time.perf_counter() - start, hist, perc)


def mesh_of(model: Model, map_m: np.ndarray, params: dict, smooth: dict) -> np.ndarray:
    """(Vd, 3) canonical mesh: the head model of ``params`` + the map's displacements."""
    return uvmap.apply_map(model.template, map_m, model.duv, params, smooth).numpy()


# ---------------------------------------------------------------- scores against ground truth
def visible_in_depth(points: np.ndarray, camera, depth: np.ndarray, tol_m: float = 0.004) -> np.ndarray:
    """(N,) bool: world points the depth map saw (their depth within ``tol_m`` of the map's)."""
    cam = points @ camera.R.T + camera.t
    z = cam[:, 2]
    uv = cam @ camera.K.T
    col = np.round(uv[:, 0] / np.maximum(uv[:, 2], 1e-9)).astype(np.int64)
    row = np.round(uv[:, 1] / np.maximum(uv[:, 2], 1e-9)).astype(np.int64)
    inside = (z > 0) & (col >= 0) & (row >= 0) & (col < depth.shape[1]) & (row < depth.shape[0])
    out = np.zeros(len(points), bool)
    d = depth[row[inside], col[inside]]
    out[inside] = (d > 0) & (np.abs(d - z[inside]) <= tol_m)
    return out


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0,
                   vertex_values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(n, 3) area-uniform surface samples and, given per-vertex values, the value of each
    sample's nearest triangle corner."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    pts, fid = trimesh.sample.sample_surface(mesh, n, seed=seed)
    if vertex_values is None:
        return pts, None
    tri = vertices[faces[fid]]
    corner = np.argmin(((tri - pts[:, None]) ** 2).sum(-1), 1)
    return pts, vertex_values[faces[fid, corner]]


def completion_scores(pred_v: np.ndarray, pred_f: np.ndarray, gt_v: np.ndarray, gt_f: np.ndarray, gt_labels: np.ndarray,
                      regions: dict[str, np.ndarray] | None = None, samples: int = 30_000, seed: int = 0) -> dict:
    """Chamfer (the mean of the two one-sided means) and the one-sided distances, mm, of a
    completed head to the ground-truth scan, overall and on GT regions. ``regions``: name ->
    (samples,) bool over the GT samples this function draws (callables of the samples are
    accepted too: ``f(points, labels) -> bool``). Predicted points lower than the GT scan's
    lowest point (+ 1 cm) are left out (the template's neck runs further down than a scan)."""
    from scipy.spatial import cKDTree

    from headforge.metrics.geometry import points_to_mesh

    gt_pts, gt_lab = sample_surface(gt_v, gt_f, samples, seed, gt_labels)
    pred_pts, _ = sample_surface(pred_v, pred_f, samples, seed + 1)
    floor = gt_v[:, 1].min() + LOWER_NECK_MARGIN_M
    pred_pts = pred_pts[pred_pts[:, 1] >= floor]
    g2p = points_to_mesh(gt_pts, pred_v, pred_f)
    p2g = points_to_mesh(pred_pts, gt_v, gt_f)
    near = cKDTree(gt_pts).query(pred_pts)[1]  # each predicted point's region: its nearest GT sample's
    out = {"all": _pair(g2p, p2g)}
    for name, sel in (regions or {}).items():
        sel = np.asarray(sel(gt_pts, gt_lab) if callable(sel) else sel, bool)
        out[name] = _pair(g2p[sel], p2g[sel[near]])
        out[name]["share"] = float(sel.mean())
    return out


def _pair(g2p: np.ndarray, p2g: np.ndarray) -> dict:
    a = float(1000 * g2p.mean()) if len(g2p) else float("nan")
    b = float(1000 * p2g.mean()) if len(p2g) else float("nan")
    return {"chamfer_mm": (a + b) / 2, "gt_to_pred_mm": a, "pred_to_gt_mm": b}


# ---------------------------------------------------------------- pictures
def picture(rows: list[list[np.ndarray]], labels: list[str]) -> np.ndarray:
    """uint8 sheet of float (S, S, 3) tiles: rows of equal length, column labels on the first row."""
    import cv2

    img = np.concatenate([np.concatenate(r, 1) for r in rows], 0)
    img = (np.clip(img, 0, 1) * 255).astype(np.uint8).copy()
    S = rows[0][0].shape[1]
    for i, t in enumerate(labels):
        cv2.putText(img, t, (4 + i * S, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
    return img


def _grey(n: int) -> np.ndarray:
    return np.tile([0.75, 0.75, 0.78], (n, 1))


def point_render(points: np.ndarray, size: int, yaw: float, target: np.ndarray, distance: float = 0.75) -> np.ndarray:
    """(S, S, 3) float picture of a point cloud (z-buffered splats, depth-shaded)."""
    from headforge.render.camera import look_at_head

    cam = look_at_head(size, size, distance=distance, yaw_deg=yaw, target=target)
    c = points @ cam.R.T + cam.t
    uv = cam.project(points)
    img = np.ones((size, size, 3))
    ok = c[:, 2] > 0
    col, row, z = np.round(uv[ok, 0]).astype(int), np.round(uv[ok, 1]).astype(int), c[ok, 2]
    if not len(z):
        return img
    shade = 0.35 + 0.6 * np.clip(1 - (z - z.min()) / max(np.ptp(z), 1e-6), 0, 1)
    colour = shade[:, None] * np.array([0.95, 0.78, 0.62])
    r = np.concatenate([row + dr for dr in (0, 1) for dc in (0, 1)])  # 2 x 2 splats
    cc = np.concatenate([col + dc for dr in (0, 1) for dc in (0, 1)])
    zz, colour = np.tile(z, 4), np.tile(colour, (4, 1))
    inside = (r >= 0) & (r < size) & (cc >= 0) & (cc < size)
    order = np.nonzero(inside)[0][np.argsort(-zz[inside])]  # far first: nearer splats overwrite (numpy keeps the last write)
    img[r[order], cc[order]] = colour[order]
    return img


# ---------------------------------------------------------------- the command
def _scaled(n: int, k: float) -> int:
    return max(1, int(round(n * k))) if n > 0 else 0


def _partial_config(model: Model, options: FitOptions):
    from dataclasses import replace

    from headforge.craft.partial import PartialConfig

    cfg = PartialConfig.preset(options.preset)
    cfg.register.levels = model.levels  # the run's template
    cfg.density = options.density
    k = options.steps_scale
    if k != 1.0:
        cfg.register.stage1 = replace(cfg.register.stage1, steps=_scaled(cfg.register.stage1.steps, k))
        cfg.register.stage2 = replace(cfg.register.stage2, steps=_scaled(cfg.register.stage2.steps, k))
        cfg.fit = replace(cfg.fit, steps=_scaled(cfg.fit.steps, k), rigid_steps=max(10, _scaled(cfg.fit.rigid_steps, k)))
    return cfg


def invert_config(options: FitOptions) -> I.InvertConfig:
    from dataclasses import replace

    if not 0 < options.steps_scale <= 10:
        raise HeadforgeError(f"--steps-scale must be within (0, 10], got {options.steps_scale}")
    cfg = I.InvertConfig.preset(options.preset)
    k = options.steps_scale
    cfg = replace(cfg, z_starts=options.z_starts, combine=options.combine, truncation=options.truncation)  # validated by InvertConfig
    return replace(cfg, **{f: _scaled(getattr(cfg, f), k) for f in ("full_steps", "full_noise_steps", "z_steps", "dw_steps", "noise_steps")})


def _write_outputs(tmp: Path, model: Model, fitres: MapFit, canon_v: np.ndarray, to_obs, extra_maps: dict,
                   params_json: dict, metrics: dict, pic: np.ndarray) -> None:
    from safetensors.torch import save_file

    from headforge.craft.generative.train import write_json
    from headforge.craft.scans import write_ply, write_png

    faces = model.template.faces.numpy()
    write_ply(tmp / "completed_canonical.ply", canon_v, faces)
    write_ply(tmp / "completed.ply", to_obs(canon_v), faces)
    uvmap.write_map(tmp / "map.png", fitres.map_m)
    for name, (m, mask) in extra_maps.items():
        uvmap.write_map(tmp / f"{name}.png", m, mask)
    if fitres.latent:
        save_file({k: v.detach().contiguous().float() for k, v in fitres.latent.items()}, str(tmp / "latent.safetensors"))
    write_json(tmp / "params.json", params_json)
    write_json(tmp / "metrics.json", metrics)
    write_png(tmp / "picture.png", pic)


@contextmanager
def _atomic_folder(output: Path):
    """Yield ``OUT.partial`` to write into; renamed to ``OUT`` when the block completes, removed
    when it raises (nothing half-written is left that looks complete)."""
    output = Path(output)
    tmp = output.with_name(output.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
    except OSError as exc:
        raise HeadforgeError(f"cannot create {tmp}: {exc.strerror}") from None
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if output.exists():
        shutil.rmtree(output)
    tmp.rename(output)


def is_observation(path: Path) -> bool:
    """A depth map or a point cloud (else a full scan: a mesh file or a scan folder)."""
    from headforge.craft.observe import CLOUD_SUFFIXES, DEPTH_SUFFIXES

    path = Path(path)
    if path.suffix.lower() in DEPTH_SUFFIXES or path.suffix.lower() == ".pcd":
        return True
    if path.suffix.lower() in CLOUD_SUFFIXES and path.is_file():
        import trimesh

        try:
            obj = trimesh.load(path, process=False)
        except Exception:
            return False  # read_scan reports the error
        return not (isinstance(obj, trimesh.Trimesh) and len(obj.faces))
    return False


def fit(input_path: str | Path, run: str | Path, output: str | Path, options: FitOptions, gt: str | Path | None = None,
        log=print) -> dict:
    """Fit a run's model to a scan, a depth map or a point cloud (module doc); returns metrics."""
    input_path, output = Path(input_path), Path(output)
    config = invert_config(options)
    model = load_model(run, options.method)
    if is_observation(input_path):
        return _fit_partial(input_path, model, output, options, config, gt, log)
    return _fit_full(input_path, model, output, options, config, log)


def _fit_partial(path: Path, model: Model, output: Path, options: FitOptions, config, gt, log) -> dict:
    from headforge.craft.observe import depth_preview, read_observation
    from headforge.craft.partial import partial_map, register_partial
    from headforge.craft.scans import render_mesh

    start = time.perf_counter()
    obs = read_observation(path, options.camera, options.depth_scale, options.up or "-y", options.forward or "-z",
                           options.units or "m")
    log(f"{obs.name}: {len(obs.points)} points ({obs.kind}); partial registration ...")
    pcfg = _partial_config(model, options)
    reg = register_partial(model.template, obs, pcfg)
    log(f"  head model fitted (face coverage {100 * reg.fit.face_coverage:.0f} %, median {reg.fit.residual_mm:.2f} mm); "
        f"{int(reg.observed.sum())} of {len(reg.observed)} vertices observed ({reg.density}, t = {reg.threshold_mm:.2f} mm)")
    pm, pmask = partial_map(reg, model.duv, model.resolution)
    if not pmask.any():
        raise HeadforgeError(f"{obs.name}: the partial registration observed no texel of the {model.resolution} px map")
    fitres = fit_map(model, pm, pmask, config, options.noise, options.seed, progress=lambda m: log("  " + m))
    params = reg.fit.alignment.params
    smooth = pcfg.register.smooth_iterations
    canon_v = mesh_of(model, fitres.map_m, params, smooth)
    align = reg.fit.alignment
    to_obs = lambda v: align.to_scan(v) @ obs.to_source.T  # noqa: E731  canonical -> W -> the file's axes
    from headforge.metrics.geometry import points_to_mesh

    faces = model.template.faces.numpy()
    d_obs = points_to_mesh(reg.points_canonical, canon_v, faces)
    metrics = {"input": str(path), "kind": obs.kind, "points": len(obs.points), "method": model.method,
               "preset": options.preset, "density": reg.density, "refine_threshold_mm": reg.threshold_mm,
               "face_coverage": reg.fit.face_coverage, "head_fit_median_mm": reg.fit.residual_mm,
               "observed_vertices": float(reg.observed.mean()), "observed_texels": float(pmask.mean()),
               "observation_to_completed_mm": {"median": float(1000 * np.median(d_obs)), "mean": float(1000 * d_obs.mean())},
               "perceptual": fitres.perceptual, "seconds": {"registration": reg.seconds, "latent": fitres.seconds,
                                                            "total": time.perf_counter() - start}}
    target = canon_v[model.template.regions["face"]].mean(0) + np.array([0.0, -0.02, -0.06])
    S = 256
    cols = [[], []]
    labels = ["observation", f"completion ({model.method})"]
    for r, yaw in enumerate((20.0, 160.0)):
        cols[r].append(point_render(reg.points_canonical, S, yaw, target))
        cols[r].append(render_mesh(canon_v, faces, _grey(len(canon_v)), S, yaw, target))
    if gt is not None:
        gt_scores, gt_tiles = _score_gt(gt, canon_v, faces, align, obs, target, S)
        metrics["ground_truth"] = gt_scores
        labels += ["ground truth", "error (0-5 mm)"]
        for r in range(2):
            cols[r] += gt_tiles[r]
    else:
        from headforge.craft.pipeline import heat_colours

        d_v = _vertex_to_points(canon_v, reg.points_canonical)
        labels.append("completion -> observation (0-5 mm)")
        for r, yaw in enumerate((20.0, 160.0)):
            cols[r].append(render_mesh(canon_v, faces, np.where(reg.observed[:, None], heat_colours(d_v), 0.85), S, yaw, target))
    if obs.depth is not None:
        import cv2

        cols[1][0] = cv2.resize(depth_preview(obs.depth), (S, S), interpolation=cv2.INTER_AREA) / 255.0  # the map itself
    pic = picture(cols, labels)
    params_json = {"head_model": model.meta["head_model"], "levels": model.levels, "method": model.method,
                   "params": {k: v.tolist() for k, v in params.items()},
                   "alignment": {"rotation": align.rotation.tolist(), "translation": align.translation.tolist(),
                                 "observation_to_file_axes": obs.to_source.tolist()},
                   "options": asdict(options), "invert": asdict(config)}
    with _atomic_folder(output) as tmp:
        _write_outputs(tmp, model, fitres, canon_v, to_obs, {"partial_map": (pm, pmask)}, params_json, metrics, pic)
    log(f"completed head in {output} ({metrics['seconds']['total']:.0f} s; picture {output / 'picture.png'})")
    return metrics


def _vertex_to_points(v: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(points).query(v)[0]


def _score_gt(gt, canon_v, faces, align, obs, target, S):
    """Scores and picture tiles against a generated ground-truth scan folder. The depth map's
    camera JSON must hold the scan-to-camera pose (``R``, ``t``; ``headforge craft depth`` writes
    it); a cloud must be in the scan's frame (``--up +y --forward +z``)."""
    from headforge.craft.pipeline import heat_colours
    from headforge.craft.scans import load_generated, render_mesh

    scan, _, g = load_generated(gt)
    to_scan = _observation_to_scan(obs)
    pred_scan = to_scan(align.to_scan(canon_v))
    regions = {}
    if obs.kind == "depth":
        cam = obs.camera.pinhole()
        regions["observed"] = lambda p, lab: visible_in_depth(p, cam, obs.depth)
        regions["unseen"] = lambda p, lab: ~visible_in_depth(p, cam, obs.depth)
        regions["unseen_back_hair"] = lambda p, lab: ~visible_in_depth(p, cam, obs.depth) & np.isin(lab, (2, 3))
    scores = completion_scores(pred_scan, faces, scan.vertices, scan.faces, g["labels"], regions)
    # tiles in the canonical frame
    gt_canon = align.to_canonical(_scan_to_observation(obs)(scan.vertices))
    from headforge.metrics.geometry import points_to_mesh

    d = points_to_mesh(canon_v, gt_canon, scan.faces)
    tiles = [[], []]
    for r, yaw in enumerate((20.0, 160.0)):
        tiles[r].append(render_mesh(gt_canon, scan.faces, _grey(len(gt_canon)), S, yaw, target))
        tiles[r].append(render_mesh(canon_v, faces, heat_colours(d), S, yaw, target))
    return scores, tiles


def _observation_to_scan(obs):
    """W -> the ground truth scan's frame."""
    if obs.kind == "depth":
        if obs.camera is None or obs.camera.R is None:
            raise HeadforgeError(f"--gt needs the scan-to-camera pose (R, t) in {obs.name}'s camera JSON "
                                 "(headforge craft depth writes it)")
        R, t = obs.camera.R, obs.camera.t
        return lambda x: (x @ obs.to_source.T - t) @ R  # W -> camera -> scan
    return lambda x: x @ obs.to_source.T  # clouds: the file's axes are the scan's


def _scan_to_observation(obs):
    if obs.kind == "depth":
        R, t = obs.camera.R, obs.camera.t
        return lambda x: (x @ R.T + t) @ obs.to_source
    return lambda x: x @ obs.to_source


def _fit_full(path: Path, model: Model, output: Path, options: FitOptions, config, log) -> dict:
    from headforge.craft import register as reg_mod
    from headforge.craft.pipeline import ItemOptions, config_for, heat_colours, load_any
    from headforge.craft.scans import render_mesh
    from headforge.metrics.geometry import points_to_mesh

    start = time.perf_counter()
    item = ItemOptions(preset=options.preset, map_size=model.resolution, head_model=model.meta["head_model"],
                       units=options.units or "auto", up=options.up or "+y", forward=options.forward or "+z",
                       steps_scale=options.steps_scale)
    rcfg = config_for(item)
    rcfg.levels = model.levels  # the run's template
    scan, gt = load_any(path, item)
    log(f"{scan.name}: {len(scan.vertices)} vertices; registration ...")
    reg = reg_mod.register(model.template, scan, rcfg)
    raw, mask = uvmap.bake(reg.displacement, model.duv, model.resolution)
    target_m = uvmap.postprocess_seams(raw, mask, model.duv, blend=0)
    fitres = fit_map(model, target_m, None, config, options.noise, options.seed, progress=lambda m: log("  " + m))
    params = reg.alignment.params
    canon_v = mesh_of(model, fitres.map_m, params, rcfg.smooth_iterations)
    registered_v = mesh_of(model, target_m, params, rcfg.smooth_iterations)
    faces = model.template.faces.numpy()
    labels = gt["labels"] if gt is not None else np.zeros(len(scan.vertices), np.uint8)
    regions = {"face": lambda p, lab: lab == 1, "hair_scalp": lambda p, lab: np.isin(lab, (2, 3))} if gt is not None else {}
    fitted = completion_scores(canon_v, faces, reg.scan_canonical, scan.faces, labels, regions)
    registered = completion_scores(registered_v, faces, reg.scan_canonical, scan.faces, labels, regions)
    metrics = {"input": str(path), "kind": "scan", "method": model.method, "preset": options.preset,
               "fitted_to_scan": fitted, "registered_to_scan": registered,
               "reconstruction_gap_mm": fitted["all"]["chamfer_mm"] - registered["all"]["chamfer_mm"],
               "map_l1_mm": float(1000 * np.abs(fitres.map_m - target_m)[mask].mean()),
               "perceptual": fitres.perceptual,
               "seconds": {"registration": reg.seconds, "latent": fitres.seconds, "total": time.perf_counter() - start}}
    target = canon_v[model.template.regions["face"]].mean(0) + np.array([0.0, -0.02, -0.06])
    S = 256
    d = points_to_mesh(canon_v, reg.scan_canonical, scan.faces)
    rows = [[], []]
    for r, yaw in enumerate((20.0, 160.0)):
        rows[r] += [render_mesh(reg.scan_canonical, scan.faces, _grey(len(scan.vertices)), S, yaw, target),
                    render_mesh(registered_v, faces, _grey(len(canon_v)), S, yaw, target),
                    render_mesh(canon_v, faces, _grey(len(canon_v)), S, yaw, target),
                    render_mesh(canon_v, faces, heat_colours(d), S, yaw, target)]
    pic = picture(rows, ["scan", "registration", f"fitted ({model.method})", "fitted -> scan (0-5 mm)"])
    a = reg.alignment
    params_json = {"head_model": model.meta["head_model"], "levels": model.levels, "method": model.method,
                   "params": {k: v.tolist() for k, v in params.items()},
                   "alignment": {"scale": a.scale, "rotation": a.rotation.tolist(), "translation": a.translation.tolist()},
                   "options": asdict(options), "invert": asdict(config)}
    with _atomic_folder(output) as tmp:
        _write_outputs(tmp, model, fitres, canon_v, a.to_scan, {"registered_map": (target_m, mask)}, params_json, metrics, pic)
    log(f"fitted head in {output}: {fitted['all']['chamfer_mm']:.2f} mm Chamfer to the scan "
        f"(registration {registered['all']['chamfer_mm']:.2f} mm; {metrics['seconds']['total']:.0f} s)")
    return metrics


# ---------------------------------------------------------------- hair transfer (§4.3)
def read_fit(folder: str | Path) -> tuple[np.ndarray, dict]:
    """(map metres, params.json) of a ``craft fit`` output (or a ``craft register`` item)."""
    folder = Path(folder)
    if not (folder / "map.png").is_file() or not (folder / "params.json").is_file():
        raise HeadforgeError(f"{folder} is not a craft fit (or craft register) folder: map.png and params.json needed")
    meta = json.loads((folder / "params.json").read_text())
    return uvmap.read_map(folder / "map.png"), meta


def transfer_hair(face_folder: str | Path, hair_folder: str | Path, output: str | Path, log=print) -> Path:
    """A's face island and identity with B's scalp island (hair), the seam blended as a
    generated map (A.2); writes ``map.png``, ``mesh.ply``, ``params.json`` and ``sheet.png``
    (A | B | A with B's hair; front, side, back)."""
    from headforge.craft.generative import sample as S
    from headforge.craft.generative.train import write_json
    from headforge.craft.pipeline import template_for
    from headforge.craft.scans import write_ply, write_png

    map_a, meta_a = read_fit(face_folder)
    map_b, meta_b = read_fit(hair_folder)
    if map_a.shape != map_b.shape:
        raise HeadforgeError(f"the two maps differ in size: {map_a.shape[0]} and {map_b.shape[0]} px")
    for k in ("head_model", "levels"):
        if meta_a.get(k) != meta_b.get(k):
            raise HeadforgeError(f"the two fits use different {k}: {meta_a.get(k)} and {meta_b.get(k)}")
    meta = {"head_model": meta_a["head_model"], "levels": meta_a["levels"]}
    tpl, duv = template_for(meta["head_model"], meta["levels"])
    islands = uvmap.texel_islands(duv, map_a.shape[0])
    mixed = np.where((islands == 0)[..., None], map_b, map_a)  # scalp from B; face and inner parts from A
    mixed = S.postprocess(mixed[None], meta)[0]
    neutral = lambda m: {"shape": np.asarray(m["params"]["shape"], np.float32).reshape(1, -1)}  # noqa: E731
    pa, pb = neutral(meta_a), neutral(meta_b)
    verts = S.meshes(meta, [map_a, map_b, mixed], [pa, pb, pa])
    output = Path(output)
    with _atomic_folder(output) as tmp:
        uvmap.write_map(tmp / "map.png", mixed)
        write_ply(tmp / "mesh.ply", verts[2], tpl.faces.numpy())
        write_json(tmp / "params.json", {"head_model": meta["head_model"], "levels": meta["levels"],
                                         "params": {k: v.tolist() for k, v in pa.items()},
                                         "face_from": str(Path(face_folder).resolve()), "hair_from": str(Path(hair_folder).resolve())})
        write_png(tmp / "sheet.png", S.sheet(verts, tpl.faces.numpy(), 192, ["A (face)", "B (hair)", "A with B's hair"]))
    log(f"A's face with B's hair in {output} (sheet {output / 'sheet.png'})")
    return output
