"""HeadCraft's partial registration (App. B.1, "Fitting the latent code to a depth map"): a
depth map or point cloud -> the head model fitted to it -> displacements on the part of the
template the observation covers -> a partial UV map and its mask.

1. **Head-model fit** (:func:`fit_head_to_cloud`): the paper starts from a FLAME fit of the scan;
   a single depth map has no landmarks we could trust on a sparse cloud, so the head model is
   fitted to the points directly: rigid ICP from several yaw hypotheses (the face toward the
   sensor within +-60 deg), then identity, expression and jaw with priors. The energy is robust
   (Geman-McClure) point-to-plane distance from the cloud to the model plus the distance from
   the model's sensor-facing vertices to the cloud, so hair and shoulders the bald model cannot
   explain do not drag it. A fit that covers too little of the model's face is "no face".
2. **Allowed region** m: template vertices inside the convex hull of the points, expanded 1.5x
   from its centre; points below the 30 % height quantile are left out of the hull (shoulders).
3. **Stages** as the full registration (:mod:`headforge.craft.register`) on m only: stage 1 with
   the stronger partial weights and pruning at 10 paper units, stage 2 pruned at 0.1; the
   template -> cloud Chamfer direction counts only m, the vertices outside m stay put.
4. **Mask refinement**: m_final = m and (distance from the registered vertex to the nearest
   cloud point <= t), t = 0.1 paper units (0.83 mm) for a dense cloud, 0.3 (2.5 mm) for a
   sparse one in ``paper``; ``quick`` takes t = max(3 mm, 1.5 x the cloud's median point
   spacing) and lets stage 2 reach 1 unit (8.3 mm), so the visible hair counts as observed
   (docs/headcraft.md, "Visible hair in the partial map"); displacements and mask
   are baked into two maps.

Frames: the observation's points are in observation head axes W (:mod:`headforge.craft.observe`);
the fit's :class:`headforge.craft.register.Alignment` maps W to the canonical head frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from headforge.craft import register as R
from headforge.craft.observe import Observation
from headforge.errors import HeadforgeError
from headforge.head.model import INNER_REGIONS


@dataclass
class CloudFitConfig:
    yaws_deg: tuple = (-60.0, -30.0, 0.0, 30.0, 60.0)  # rigid hypotheses: the face toward the sensor
    fit_points: int = 20_000  # cloud points used by the fit (random subset)
    rigid_steps: int = 60  # per hypothesis
    steps: int = 300  # rigid + identity + expression + jaw
    lr_rotation: float = 0.01  # rad per step (Adam)
    lr_translation: float = 0.004  # m
    lr_shape: float = 0.05
    sigma_mm: tuple = (10.0, 3.0)  # robust kernel scale, annealed from the first to the second
    model_to_cloud: float = 0.5  # weight of the sensor-facing model vertices -> cloud term
    shape_prior: float = 0.02  # on the identity coefficients (unit-variance PCA)
    expression_prior: float = 0.02
    jaw_prior: float = 1.0
    n_shape: int = 50
    face_coverage_min: float = 0.3  # share of sensor-facing face vertices near the points
    face_near_mm: float = 4.0  # "near" for the coverage check (+ the cloud's spacing)
    face_vs_sphere_max: float = 0.5  # the face's points must fit the head model this much better than a sphere


def _partial_stage1() -> R.StageConfig:
    # the paper's partial stage 1 is (2e3, 8e5, 1e5), pruned at 10 units; the Chamfer weight is
    # raised 100x as in the full registration (with 2e3 the template did not move), the Laplacian
    # kept at the full registration's 1e4: with 1e5 the scalp stayed within 1.8 mm of the head
    # model under a bob's 3 cm of visible hair (docs/headcraft.md, part 3)
    return R.StageConfig(steps=1000, lr=3e-2, chamfer=2e5, edge=8e5, laplacian=1e4, prune_units=10.0)


def _partial_stage2() -> R.StageConfig:
    return replace(R._stage2(), prune_units=0.1)


@dataclass
class PartialConfig:
    register: R.RegisterConfig = field(default_factory=R.RegisterConfig)
    fit: CloudFitConfig = field(default_factory=CloudFitConfig)
    hull_expand: float = 1.5
    hull_floor_quantile: float = 0.3
    refine_dense_units: float = 0.1  # mask refinement threshold t, paper units (0.83 mm)
    refine_sparse_units: float = 0.3  # (2.5 mm)
    refine_spacing: float = 0.0  # t at least this many times the cloud's median point spacing (0: off, the paper)
    sparse_spacing_mm: float = 2.0  # a cloud whose points lie farther apart than this is "sparse"
    density: str = "auto"  # auto | dense | sparse

    @classmethod
    def quick(cls) -> PartialConfig:
        reg = R.RegisterConfig.quick()
        reg.stage1_face_margin_mm = None  # stage 1 on scalp + neck only: the outer face was not tried here
        reg.stage1 = replace(_partial_stage1(), steps=400)
        # stage 2 reaching 8.3 mm and t = max(3 mm, 1.5 x spacing): the paper's 0.83 mm kept all but
        # 15-23 scalp texels of a frontal map out, its 2.5 mm all but 0.4 % of a 1 % cloud's texels (docs/headcraft.md)
        reg.stage2 = replace(_partial_stage2(), steps=250, lr=1.5e-3, prune_units=1.0)
        return cls(register=reg, fit=CloudFitConfig(rigid_steps=50, steps=200, fit_points=12_000),
                   refine_dense_units=3e-3 * R.PAPER_UNITS_PER_M, refine_sparse_units=3e-3 * R.PAPER_UNITS_PER_M,
                   refine_spacing=1.5)

    @classmethod
    def paper(cls) -> PartialConfig:
        reg = R.RegisterConfig.paper()
        reg.stage1_face_margin_mm = None
        reg.stage1 = _partial_stage1()
        reg.stage2 = _partial_stage2()
        return cls(register=reg)

    @classmethod
    def preset(cls, name: str) -> PartialConfig:
        if name not in ("quick", "paper"):
            raise HeadforgeError(f"unknown preset {name!r}; choose quick or paper")
        return getattr(cls, name)()


# ---------------------------------------------------------------- 1. head model fitted to the points
def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _robust(d: torch.Tensor, sigma: float) -> torch.Tensor:
    return (d * d / (d * d + sigma * sigma)).mean()


@dataclass
class CloudFit:
    alignment: R.Alignment  # W -> canonical (rotation, translation; scale 1: depth is metric)
    face_coverage: float
    residual_mm: float  # median cloud -> model distance
    hypothesis_deg: float
    seconds: float


def fit_head_to_cloud(template: R.Template, obs: Observation, config: CloudFitConfig, seed: int = 0) -> CloudFit:
    """Rigid + identity + expression + jaw of the head model fitted to an observation's points
    (module doc, step 1). Raises when the best fit does not find a face in the points."""
    import copy

    import roma
    from scipy.spatial import cKDTree

    from headforge.geometry import vertex_normals

    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    pts = obs.points if len(obs.points) <= config.fit_points else obs.points[rng.choice(len(obs.points), config.fit_points, replace=False)]
    cloud = torch.as_tensor(pts, dtype=torch.float64)
    cloud_tree = cKDTree(pts)
    spacing = obs.spacing_m()
    model = copy.deepcopy(template.model).double()  # the shared template's model stays float32
    faces = torch.as_tensor(template.data.faces)
    n_shape = min(config.n_shape, model.n_shape)
    pad = torch.zeros(1, model.n_shape - n_shape, dtype=torch.float64)
    camera = obs.camera_centre
    face_ids = torch.as_tensor(template.data.regions["face"])
    skip = np.zeros(model.num_vertices, bool)  # the inner parts a sensor never sees
    for name in (*INNER_REGIONS, "lower_neck"):
        if name in template.data.regions:
            skip[template.data.regions[name]] = True
    outer = torch.as_tensor(~skip)

    def posed(rot, trans, shape, expr_logit, jaw):
        out = model(shape=torch.cat([shape, pad], 1), expression=torch.sigmoid(expr_logit), jaw_pose=jaw)
        v = out.vertices[0]
        Rm = roma.rotvec_to_rotmat(rot)
        return v @ Rm.T + trans, vertex_normals(v[None], faces)[0] @ Rm.T

    def facing(v, n):
        """Sensor-facing outer vertices: toward the camera centre, or toward +z without one."""
        view = (torch.as_tensor(camera) - v) if camera is not None else torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype).expand_as(v)
        view = view / view.norm(dim=-1, keepdim=True)
        return ((n * view).sum(-1) > 0.2) & outer

    def energy(v, n, sigma):
        vd = v.detach().numpy()
        _, near = cKDTree(vd).query(pts)
        near = torch.as_tensor(near)
        c2m = ((cloud - v[near]) * n[near]).sum(-1).abs()  # point-to-plane
        front = facing(v.detach(), n.detach())
        d, idx = cloud_tree.query(vd[front.numpy()])
        m2c = (v[front] - cloud[torch.as_tensor(idx)]).norm(dim=-1)
        sigma_m2c = max(sigma, 1.5 * spacing)
        return _robust(c2m, sigma) + config.model_to_cloud * _robust(m2c, sigma_m2c), c2m

    zeros = lambda k: torch.zeros(1, k, dtype=torch.float64)  # noqa: E731
    expr0 = torch.full((1, model.n_expr), -4.0, dtype=torch.float64)
    with torch.no_grad():
        v0, n0 = posed(torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), zeros(n_shape), expr0, zeros(3))
    best = None
    sigma0 = config.sigma_mm[0] / 1000
    for yaw in config.yaws_deg:
        Ry = torch.as_tensor(_rot_y(yaw))
        vy, ny = v0 @ Ry.T, n0 @ Ry.T
        front = (ny[:, 2] > 0.3) & outer
        t0 = cloud.mean(0) - vy[front].mean(0)
        rot = roma.rotmat_to_rotvec(Ry).clone().requires_grad_(True)
        trans = t0.clone().requires_grad_(True)
        opt = torch.optim.Adam([{"params": [rot], "lr": config.lr_rotation}, {"params": [trans], "lr": config.lr_translation}])
        for _ in range(config.rigid_steps):
            opt.zero_grad()
            v, n = posed(rot, trans, zeros(n_shape), expr0, zeros(3))
            loss, _ = energy(v, n, sigma0)
            loss.backward()
            opt.step()
        with torch.no_grad():
            v, n = posed(rot, trans, zeros(n_shape), expr0, zeros(3))
            final, _ = energy(v, n, sigma0)
        if best is None or float(final) < best[0]:
            best = (float(final), yaw, rot.detach().clone(), trans.detach().clone())
    _, yaw, rot0, trans0 = best
    rot = rot0.clone().requires_grad_(True)
    trans = trans0.clone().requires_grad_(True)
    shape = zeros(n_shape).requires_grad_(True)
    expr_logit = expr0.clone().requires_grad_(True)
    jaw = zeros(3).requires_grad_(True)
    opt = torch.optim.Adam([{"params": [rot], "lr": config.lr_rotation}, {"params": [trans], "lr": config.lr_translation},
                            {"params": [shape, expr_logit, jaw], "lr": config.lr_shape}])
    s_hi, s_lo = (s / 1000 for s in config.sigma_mm)
    for step in range(config.steps):
        sigma = s_hi * (s_lo / s_hi) ** (step / max(1, config.steps - 1))
        opt.zero_grad()
        v, n = posed(rot, trans, shape, expr_logit, jaw)
        loss, _ = energy(v, n, sigma)
        loss = loss + config.shape_prior * shape.pow(2).mean() + config.expression_prior * torch.sigmoid(expr_logit).mean() \
            + config.jaw_prior * jaw.pow(2).sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        v, n = posed(rot, trans, shape, expr_logit, jaw)
        _, c2m = energy(v, n, s_lo)
        front = facing(v, n)
        fids = face_ids[front[face_ids]]
        d, _ = cloud_tree.query(v[fids].numpy()) if len(fids) else (np.zeros(0), None)
        is_face = np.zeros(model.num_vertices, bool)
        is_face[face_ids.numpy()] = True
        on_face = is_face[cKDTree(v.numpy()).query(pts)[1]]  # cloud points the model's face explains
    coverage = float((d <= config.face_near_mm / 1000 + spacing).mean()) if len(d) else 0.0
    residual = float(1000 * np.median(c2m.numpy()))
    face_mm = float(1000 * np.median(c2m.numpy()[on_face])) if on_face.sum() >= 50 else float("inf")
    sphere_mm = 1000 * _sphere_residual(pts[on_face]) if on_face.sum() >= 50 else 0.0
    if coverage < config.face_coverage_min or face_mm > config.face_vs_sphere_max * sphere_mm:
        raise HeadforgeError(f"no face found in {obs.name}: the best head-model fit covers {100 * coverage:.0f} % of its "
                             f"sensor-facing face (need {100 * config.face_coverage_min:.0f} %) and explains those points "
                             f"to {face_mm:.2f} mm against {sphere_mm:.2f} mm for a sphere; the observation must show "
                             "the face (within 60 deg of frontal)")
    Rm = roma.rotvec_to_rotmat(rot.detach()).numpy()
    params = {"shape": torch.cat([shape.detach(), pad], 1).float(), "expression": torch.sigmoid(expr_logit.detach()).float(),
              "jaw_pose": jaw.detach().float()}
    # Alignment: x_c = rotation @ (x - translation) / scale, with x_W = Rm x_c + t
    alignment = R.Alignment(1.0, 1.0, Rm.T, trans.detach().numpy(), params, float("nan"))
    return CloudFit(alignment, coverage, residual, yaw, time.perf_counter() - start)


def _sphere_residual(points: np.ndarray) -> float:
    """Median distance (m) of points to their least-squares sphere (algebraic fit): a face's
    nose, eyes and mouth lie centimetres off any sphere, a ball or a wall does not."""
    A = np.concatenate([2 * points, np.ones((len(points), 1))], 1)
    sol, *_ = np.linalg.lstsq(A, (points ** 2).sum(1), rcond=None)
    centre = sol[:3]
    radius = np.sqrt(max(sol[3] + centre @ centre, 0.0))
    return float(np.median(np.abs(np.linalg.norm(points - centre, axis=1) - radius)))


# ---------------------------------------------------------------- 2.-4. the partial registration
@dataclass
class PartialRegistration:
    """A partial registration in the canonical head frame (metres)."""

    fit: CloudFit
    base: torch.Tensor  # (Vd, 3) smoothed dense template of the fit
    vertices: torch.Tensor  # (Vd, 3) after the two stages (outside the allowed region: the base)
    displacement: torch.Tensor  # (Vd, 3) vertices - base
    allowed: np.ndarray  # (Vd,) bool: m, inside the expanded hull
    observed: np.ndarray  # (Vd,) bool: m_final
    points_canonical: np.ndarray  # (N, 3) the observation in the canonical frame
    density: str  # dense | sparse
    threshold_mm: float
    seconds: float
    history: dict


def hull_mask(points: np.ndarray, vertices: np.ndarray, expand: float, floor_quantile: float) -> np.ndarray:
    """(V,) bool: vertices inside the convex hull of the points above the ``floor_quantile``
    height quantile (y), expanded by ``expand`` from the hull points' centre."""
    from scipy.spatial import Delaunay, QhullError

    keep = points[points[:, 1] >= np.quantile(points[:, 1], floor_quantile)]
    centre = keep.mean(0)
    try:
        hull = Delaunay(centre + expand * (keep - centre))
    except QhullError as exc:
        raise HeadforgeError(f"the observation's points are degenerate (flat or collinear): {str(exc).splitlines()[0]}") from None
    return hull.find_simplex(vertices) >= 0


def density_of(obs: Observation, config: PartialConfig) -> str:
    if config.density in ("dense", "sparse"):
        return config.density
    if config.density != "auto":
        raise HeadforgeError(f"--density must be auto, dense or sparse, got {config.density!r}")
    return "sparse" if 1000 * obs.spacing_m() > config.sparse_spacing_mm else "dense"


def register_partial(template: R.Template, obs: Observation, config: PartialConfig, progress=None,
                     fit: CloudFit | None = None) -> PartialRegistration:
    """Module doc, steps 1-4 (``fit`` given: step 1 is skipped)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(config.register.threads)
    try:
        return _register_partial(template, obs, config, progress, fit)
    finally:
        torch.set_num_threads(threads)


def _register_partial(template, obs, config, progress, fit) -> PartialRegistration:
    from scipy.spatial import cKDTree

    start = time.perf_counter()
    rc = config.register
    fit = fit or fit_head_to_cloud(template, obs, config.fit, rc.seed)
    canon = fit.alignment.to_canonical(obs.points)
    base = R.dense_base(template, fit.alignment.params, rc.smooth_iterations)
    allowed = hull_mask(canon, base.numpy(), config.hull_expand, config.hull_floor_quantile)
    if not allowed.any():
        raise HeadforgeError(f"{obs.name}: no template vertex lies inside the points' hull (is the head in the observation?)")
    m = torch.as_tensor(allowed)
    losses = R.Losses(template.faces, template.n_vertices, canon, rc, template_mask=m)
    x = base * R.PAPER_UNITS_PER_M
    ref = x.clone()
    history = {}
    if rc.stage1.enabled:
        x, history["stage1"] = R.run_stage(x, losses, rc.stage1, R.free_mask(template, rc.stage1_regions) & m, None, progress, ref)
    if rc.stage2.enabled:
        normals = R.vertex_normals(x, template.faces)
        x, history["stage2"] = R.run_stage(x, losses, rc.stage2, R.free_mask(template, rc.stage2_regions) & m, normals, progress, ref)
    base_u = base * R.PAPER_UNITS_PER_M
    disp = (x - base_u).clamp(-rc.clip_units, rc.clip_units)
    final = (base_u + disp) / R.PAPER_UNITS_PER_M
    density = density_of(obs, config)
    t_units = config.refine_sparse_units if density == "sparse" else config.refine_dense_units
    if config.refine_spacing:
        t_units = max(t_units, config.refine_spacing * obs.spacing_m() * R.PAPER_UNITS_PER_M)
    d, _ = cKDTree(canon).query(final.numpy())
    observed = allowed & (d <= t_units / R.PAPER_UNITS_PER_M)
    if not observed.any():
        raise HeadforgeError(f"{obs.name}: no registered vertex lies within {1000 * t_units / R.PAPER_UNITS_PER_M:.2f} mm "
                             "of the points after the partial registration")
    return PartialRegistration(fit, base, final, disp / R.PAPER_UNITS_PER_M, allowed, observed, canon, density,
                               1000 * t_units / R.PAPER_UNITS_PER_M, time.perf_counter() - start, history)


def partial_map(reg: PartialRegistration, duv, size: int, bake_size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(size, size, 3) displacement map (metres) and (size, size) bool mask of the observed
    texels. Both are baked at ``bake_size`` (default 4x ``size``, at most 256) and area-averaged
    down: a texel is observed when at least half of its area is."""
    from headforge.craft import uvmap

    bake_size = bake_size or min(256, 4 * size)
    disp, cover = uvmap.bake(reg.displacement.numpy(), duv, bake_size)
    m, _ = uvmap.bake(reg.observed[:, None].astype(np.float64), duv, bake_size)
    mask = cover & (m[..., 0] > 0.5)
    if bake_size == size:
        return np.where(mask[..., None], disp, 0.0), mask
    k = bake_size // size
    w = mask.reshape(size, k, size, k).mean((1, 3))
    summed = (disp * mask[..., None]).reshape(size, k, size, k, 3).sum((1, 3))
    count = mask.reshape(size, k, size, k).sum((1, 3))
    out = np.where(count[..., None] > 0, summed / np.maximum(count, 1)[..., None], 0.0)
    keep = (w >= 0.5) & (uvmap.texel_islands(duv, size) >= 0)  # a border texel the layout leaves out at this size stays out
    return np.where(keep[..., None], out, 0.0), keep
