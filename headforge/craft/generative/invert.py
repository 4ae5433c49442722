"""Fitting a trained model to one displacement map (HeadCraft App. B.1): the whole map of a
registered scan, or the observed texels of a partial map (a depth map's registration).

Maps are (3, R, R) or (1, 3, R, R) tensors in model units (:mod:`headforge.craft.generative.data`);
masks are (R, R) bool, True where a texel is observed.

StyleGAN2 (:func:`invert_full`, :func:`invert_partial`):

- full: W+ latent initialised at the mean of ``w_avg_samples`` mapped z, L1 + perceptual, then
  the scalp noise tensors with the same loss;
- partial: z from N(0, I) on the observed texels, then Delta-w with the "preserve" terms on the
  unobserved texels and the L1 penalty on the inner face, then the scalp noise (+ 1e-5 x the sum
  of the noise tensors' L2 norms).

The perceptual term is the patch LPIPS of B.1 when the ``lpips`` package and its weights are
installed; otherwise 1 - SSIM over the same maps (a weight-free stand-in: ``perceptual_name``).

PCA and the mean map (:func:`fit_pca`, :func:`mean_map`): the maximum a posteriori PCA
coefficients under unit-Gaussian priors and an i.i.d. Gaussian texel noise (``sigma``), in
closed form; the mean training map, which ignores the observation.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from headforge.errors import HeadforgeError


@dataclass
class InvertConfig:
    full_steps: int = 1000  # B.1 full scan: W+ steps
    full_noise_steps: int = 1000
    z_steps: int = 500  # B.1 depth map: z, then Delta-w, then noise
    z_starts: int = 1  # depth fits: z initialisations fitted side by side (B.1: one)
    combine: str = "best"  # z_starts > 1: "best" start by the observed loss after the z step, or the "mean" of all completions
    truncation: float = 1.0  # depth fits: psi of w = w_avg + psi (map(z) - w_avg) in the z and Delta-w steps (B.1 fits without; its samples use 0.7)
    dw_steps: int = 500
    noise_steps: int = 500
    lr: float = 1e-2
    l1: float = 3.0
    perceptual: float = 0.1
    preserve_l1: float = 0.3
    preserve_perceptual: float = 0.01
    face: float = 10 / 256
    face_radius: float = 0.7  # inner-face circle: this share of the face island's equivalent radius (docs/headcraft.md)
    noise_reg: float = 1e-5
    w_avg_samples: int = 100_000
    patches: int = 4  # perceptual term on patches x patches tiles (B.1: sixteen 64 px tiles of 256 px)
    pca_sigma_m: float = 0.001  # PCA fit: texel noise, metres

    def __post_init__(self):
        if not 1 <= self.z_starts <= 64 or self.combine not in ("best", "mean"):
            raise HeadforgeError(f"--z-starts must be 1 to 64 and --combine best or mean, got {self.z_starts} and {self.combine!r}")
        if not 0 < self.truncation <= 1:
            raise HeadforgeError(f"--truncation must be within (0, 1], got {self.truncation}")

    @classmethod
    def paper(cls) -> InvertConfig:
        return cls()

    @classmethod
    def quick(cls) -> InvertConfig:
        """The paper's step counts cost ~1 min at 64 px on 2 cores (docs/headcraft.md, part 3);
        only the w average uses fewer samples."""
        return cls(w_avg_samples=10_000)

    @classmethod
    def preset(cls, name: str) -> InvertConfig:
        if name not in ("quick", "paper"):
            raise HeadforgeError(f"unknown preset {name!r}; choose quick or paper")
        return getattr(cls, name)()


# ---------------------------------------------------------------- losses
class Perceptual:
    """Patch perceptual distance between two (1, 3, R, R) model-unit maps: LPIPS when available,
    else 1 - SSIM (maps shown to both as x / 4 + 0.5: +-2 model units -> [0, 1])."""

    def __init__(self, patches: int):
        self.patches = patches
        self.lpips = _lpips_model()
        self.name = "lpips" if self.lpips is not None else "1-ssim"

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        a, b = a / 4 + 0.5, b / 4 + 0.5
        R = a.shape[-1]
        p = self.patches if R // self.patches >= 16 else max(1, R // 16)
        s = R // p
        tiles = lambda x: x.unfold(2, s, s).unfold(3, s, s).permute(0, 2, 3, 1, 4, 5).reshape(-1, 3, s, s)  # noqa: E731
        ta, tb = tiles(a), tiles(b)
        if self.lpips is not None:
            return self.lpips(ta * 2 - 1, tb * 2 - 1).mean()
        return 1 - _ssim(ta, tb).mean()


def _lpips_model():
    try:
        import lpips as lpips_pkg
    except ImportError:
        return None
    try:
        model = lpips_pkg.LPIPS(net="alex", verbose=False, pretrained=True)
    except Exception:  # weights missing and no network
        return None
    return model.eval().requires_grad_(False)


def _ssim(a: torch.Tensor, b: torch.Tensor, win: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """(T,) differentiable SSIM of (T, C, s, s) tiles (Gaussian window, data range 1)."""
    from headforge.metrics.image import _ssim_maps

    win = min(win, a.shape[-1] - (1 - a.shape[-1] % 2))
    s, _ = _ssim_maps(a, b, win, sigma * win / 11)
    return s.flatten(1).mean(1)


def face_circle(face: np.ndarray, radius_share: float = 0.7) -> np.ndarray:
    """(R, R) bool: a disc at the face island's centroid covering the inner face (eyes, nose,
    mouth) -- ``InvertConfig.face_radius`` of the island's equivalent radius."""
    rows, cols = np.nonzero(face)
    if not len(rows):
        return np.zeros_like(face, bool)
    r0, c0 = rows.mean(), cols.mean()
    radius = math.sqrt(len(rows) / math.pi)
    yy, xx = np.mgrid[0:face.shape[0], 0:face.shape[1]]
    return (yy - r0) ** 2 + (xx - c0) ** 2 <= (radius_share * radius) ** 2


# ---------------------------------------------------------------- StyleGAN2
@dataclass
class Inversion:
    map: torch.Tensor  # (1, 3, R, R) model units
    ws: torch.Tensor  # (1, num_ws, w_dim); a partial fit's "mean" of K starts: (K, num_ws, w_dim)
    z: torch.Tensor | None  # (1 or K, z_dim) partial fits
    noise: dict[str, torch.Tensor]  # SynthLayer name -> (1, 1, r, r) noise after the fit
    history: dict[str, list[float]]
    perceptual: str
    seconds: float


def _as_batch(x: torch.Tensor | np.ndarray) -> torch.Tensor:
    x = torch.as_tensor(x, dtype=torch.float32)
    return x[None] if x.ndim == 3 else x


def _check_size(G, target: torch.Tensor) -> None:
    R = G.cfg.resolution
    if target.shape[-3:] != (G.cfg.channels, R, R):
        raise HeadforgeError(f"the map is {tuple(target.shape[-3:])} but the generator makes ({G.cfg.channels}, {R}, {R}) "
                             f"maps: fit with a model trained at {target.shape[-1]} px or resample the map")


def mean_w(G, samples: int, seed: int = 0) -> torch.Tensor:
    """(w_dim,) mean of map(z) over ``samples`` standard-normal z (B.1's W+ initialisation)."""
    gen = torch.Generator().manual_seed(seed)
    total, n = torch.zeros(G.cfg.w_dim), 0
    with torch.no_grad():
        while n < samples:
            k = min(10_000, samples - n)
            total += G.mapping(torch.randn(k, G.cfg.z_dim, generator=gen)).sum(0)
            n += k
    return total / n


class _Noise:
    """The generator's constant noise buffers made optimisable on their nonzero (scalp) texels."""

    def __init__(self, G):
        from headforge.craft.generative.stylegan2 import SynthLayer

        self.layers = [(name, m) for name, m in G.named_modules() if isinstance(m, SynthLayer)]
        self.base = [m.noise.detach().clone() for _, m in self.layers]
        self.mask = [(b != 0).float() for b in self.base]
        self.delta = [torch.zeros_like(b, requires_grad=True) for b in self.base]

    def apply(self) -> None:
        for (_, m), b, k, d in zip(self.layers, self.base, self.mask, self.delta):
            m.noise = b + d * k

    def norm(self) -> torch.Tensor:
        return sum(((b + d * k).square().sum()).sqrt() for b, k, d in zip(self.base, self.mask, self.delta))

    def state(self) -> dict[str, torch.Tensor]:
        return {name: (b + d * k).detach().clone() for (name, _), b, k, d in zip(self.layers, self.base, self.mask, self.delta)}


def _generator(trainer):
    G = copy.deepcopy(trainer.G_ema).eval().requires_grad_(False)
    return G


def _loop(params, steps: int, lr: float, loss_fn, history: list, progress=None, label: str = "") -> None:
    if steps <= 0:
        return
    opt = torch.optim.Adam(params, lr=lr)
    for step in range(steps):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
        if progress is not None and (step % 100 == 0 or step == steps - 1):
            progress(f"{label} {step + 1}/{steps}  loss {float(loss.detach()):.4f}")


def _noise_step(G, ws: torch.Tensor, loss_fn, reg: float, steps: int, lr: float, history: list, progress):
    """B.1's noise step: ``loss_fn()`` (+ ``reg`` x the sum of the noise tensors' L2 norms) over
    the scalp noise with ``ws`` fixed; returns (the final map, the noise tensors)."""
    nz = _Noise(G)

    def noise_loss():
        nz.apply()
        return loss_fn() + (reg * nz.norm() if reg else 0.0)

    _loop(nz.delta, steps, lr, noise_loss, history, progress, "noise")
    nz.apply()
    with torch.no_grad():
        return G.synthesis(ws), nz.state()


def invert_full(trainer, target, config: InvertConfig, noise: bool = True, seed: int = 0, progress=None) -> Inversion:
    """B.1 "fitting the latent code to a full scan": W+ from the mean w, then the scalp noise."""
    start = time.perf_counter()
    G = _generator(trainer)
    U = _as_batch(target)
    _check_size(G, U)
    perc = Perceptual(config.patches)
    w0 = mean_w(G, config.w_avg_samples, seed)
    ws = w0[None, None].repeat(1, G.num_ws, 1).clone().requires_grad_(True)
    hist = {"w": [], "noise": []}

    def loss_fn():
        out = G.synthesis(ws)
        return config.perceptual * perc(out, U) + config.l1 * (out - U).abs().mean()

    _loop([ws], config.full_steps, config.lr, loss_fn, hist["w"], progress, "W+")
    ws = ws.detach().requires_grad_(False)
    out, state = _noise_step(G, ws, loss_fn, 0.0, config.full_noise_steps if noise else 0, config.lr, hist["noise"], progress)
    return Inversion(out, ws, None, state, hist, perc.name, time.perf_counter() - start)


def invert_partial(trainer, target, mask: np.ndarray, face: np.ndarray, config: InvertConfig, noise: bool = True,
                   seed: int = 0, progress=None) -> Inversion:
    """B.1 "fitting the latent code to a depth map": z, then Delta-w, then noise, on the
    observed texels ``mask`` (R, R); ``face`` (R, R) the face island (for the inner-face disc).

    With ``config.z_starts`` K > 1, K z drawn from N(0, I) are fitted side by side (one batch);
    ``combine="best"`` continues with the start whose observed loss is lowest after the z step,
    ``"mean"`` carries all K through Delta-w and the (shared) noise step and returns the mean of
    their maps -- an estimate of the completion's posterior mean rather than one draw of it.
    ``ws`` and ``z`` then hold every start kept: (K', num_ws, w_dim), (K', z_dim).

    ``config.truncation`` psi < 1 maps each z to ``w_avg + psi (map(z) - w_avg)``: the z step then
    searches a shrunken latent region around the average map (the truncation trick of the paper's
    sampling, not of its fitting)."""
    start = time.perf_counter()
    G = _generator(trainer)
    U = _as_batch(target)
    _check_size(G, U)
    R = G.cfg.resolution
    if mask.shape != (R, R) or face.shape != (R, R):
        raise HeadforgeError(f"masks must be {R}x{R}, got {mask.shape} and {face.shape}")
    if not mask.any():
        raise HeadforgeError("the partial map has no observed texel")
    M = torch.as_tensor(mask, dtype=torch.float32)[None, None]
    Mf = torch.as_tensor(face_circle(face, config.face_radius), dtype=torch.float32)[None, None]
    perc = Perceptual(config.patches)
    hist = {"z": [], "dw": [], "noise": []}
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(config.z_starts, G.cfg.z_dim, generator=gen).requires_grad_(True)

    def observed_terms(out):
        # Summed over the batch: each start's gradient is its own loss's (Adam is scale-free anyway).
        return sum(config.perceptual * perc(o * M, U * M) + config.l1 * ((o - U) * M).abs().mean() for o in out.split(1))

    def ws_of(zz):
        return G.ws(zz, truncation=config.truncation)

    def z_loss():
        return observed_terms(G.synthesis(ws_of(z)))

    _loop([z], config.z_steps, config.lr, z_loss, hist["z"], progress, "z")
    z = z.detach()
    if config.z_starts > 1 and config.combine == "best":
        with torch.no_grad():
            losses = torch.stack([observed_terms(G.synthesis(ws_of(zk[None]))) for zk in z])
        hist["z_start_losses"] = losses.tolist()
        z = z[int(losses.argmin())][None]
    with torch.no_grad():
        w_z = ws_of(z)
        ref = G.synthesis(w_z)
    dw = torch.zeros_like(w_z, requires_grad=True)

    def dw_loss():
        out = G.synthesis(w_z + dw)
        keep = 1 - M
        preserve = sum(config.preserve_perceptual * perc(o * keep, r * keep) + config.preserve_l1 * ((o - r) * keep).abs().mean()
                       for o, r in zip(out.split(1), ref.split(1)))
        face_term = config.face * (out * Mf).abs().sum() / Mf.sum().clamp(min=1)
        return observed_terms(out) + preserve + face_term

    _loop([dw], config.dw_steps, config.lr, dw_loss, hist["dw"], progress, "delta-w")
    ws = (w_z + dw).detach()
    out, state = _noise_step(G, ws, lambda: observed_terms(G.synthesis(ws)), config.noise_reg,
                             config.noise_steps if noise else 0, config.lr, hist["noise"], progress)
    return Inversion(out.mean(0, keepdim=True), ws, z, state, hist, perc.name, time.perf_counter() - start)


# ---------------------------------------------------------------- PCA and the mean map
def fit_pca(model, target, mask: np.ndarray | None, sigma_units: float) -> tuple[torch.Tensor, torch.Tensor]:
    """MAP PCA coefficients (k,) of a :class:`headforge.craft.generative.pca.PCAModel` for the
    observed texels (``mask`` None: all), texel noise ``sigma_units`` (model units); returns
    ((1, 3, R, R) map, coefficients)."""
    U = _as_batch(target).double()
    R = model.cfg.resolution
    if U.shape[-1] != R:
        raise HeadforgeError(f"the map is {U.shape[-1]} px but the PCA model is {R} px")
    k = int((model.std > 0).sum())
    A = (model.basis[:k].double() * model.std[:k, None].double())  # (k, D)
    sel = torch.ones(3, R, R, dtype=torch.bool) if mask is None else torch.as_tensor(mask)[None].expand(3, R, R)
    sel = sel.reshape(-1)
    Ao = A[:, sel]
    r = (U.reshape(-1) - model.mean.double())[sel]
    lhs = Ao @ Ao.T / sigma_units ** 2 + torch.eye(k, dtype=torch.float64)
    c = torch.linalg.solve(lhs, Ao @ r / sigma_units ** 2)
    full = torch.zeros(model.cfg.components, dtype=torch.float32)
    full[:k] = c.float()
    with torch.no_grad():
        return model.decode(full[None]), full


def mean_map(train_maps: torch.Tensor) -> torch.Tensor:
    """(1, 3, R, R): the mean of a run's training maps (model units)."""
    return train_maps.mean(0, keepdim=True)


def resample_to(x: torch.Tensor, size: int) -> torch.Tensor:
    """(N, 3, r, r) -> (N, 3, size, size): area down, bilinear up."""
    if x.shape[-1] == size:
        return x
    if size < x.shape[-1]:
        return F.interpolate(x, size=(size, size), mode="area")
    return F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)
