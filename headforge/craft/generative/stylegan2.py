"""StyleGAN2 (Karras et al. 2020) over UV displacement maps, the parts HeadCraft uses (§3.2, A.2).

Written compactly here rather than taken from a pip package: the authors used
stylegan2-ada-lightning (not on PyPI); NVIDIA's stylegan2-ada-pytorch needs custom CUDA ops
and is not a package either; the maintained pip ports pull in training frameworks or lack the
per-layer noise control HeadCraft needs (no noise on the face island, a constant learned-once
noise on the scalp). What is here:

- mapping network: z (z_dim) normalised, ``mapping_layers`` equalised-lr FC layers (lr x 0.01),
  w (w_dim), a tracked average ``w_avg`` for the truncation trick;
- synthesis, "skip" architecture: a learned 4x4 constant, per resolution two modulated 3x3 convs
  with weight demodulation (the first upsamples x2), a modulated 1x1 toRGB whose outputs are
  upsampled and summed; noise: a fixed buffer per layer (drawn once at construction, saved in
  the checkpoint), times a learned strength, times the scalp mask (zero on the face island);
- discriminator, "resnet" architecture: fromRGB, residual blocks (two 3x3 convs, the second
  downsampling, a 1x1 skip, sum / sqrt 2), minibatch standard deviation (group 4), conv, FC, FC.

Deviations from NVIDIA's code (docs/headcraft.md): up/down sampling is bilinear / average
pooling instead of the [1, 3, 3, 1] FIR filter with transposed convolutions; no fp16 or
activation clamping.

Images are (B, C, H, W) model units (metres / :data:`headforge.craft.generative.data.SCALE_M`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from headforge import distributed
from headforge.errors import HeadforgeError

SQRT2 = math.sqrt(2.0)


@dataclass
class StyleGAN2Config:
    resolution: int = 256
    channels: int = 3
    z_dim: int = 512
    w_dim: int = 512
    mapping_layers: int = 8
    channel_base: int = 16384  # channels at resolution r: min(channel_base // r, channel_max)
    channel_max: int = 512
    batch: int = 8
    g_lr: float = 2e-3
    d_lr: float = 1e-3
    r1_gamma: float = 4.0
    r1_interval: int = 16
    pl_weight: float = 2.0
    pl_interval: int = 4
    pl_decay: float = 0.01
    style_mixing: float = 0.9
    mbstd_group: int = 4
    ema_images: float = 10_000.0  # EMA half-life of G in images (StyleGAN2: 10 kimg)
    ema_rampup: float | None = 0.05  # half-life <= this fraction of the images seen so far
    steps: int = 72_000
    noise_on_face: bool = False  # HeadCraft: no noise on the face island
    sample_every: int = 500
    checkpoint_every: int = 500

    @classmethod
    def paper(cls) -> StyleGAN2Config:
        """A.2: latent 512, 8 mapping layers, G lr 2e-3, D lr 1e-3, gamma 4, PL weight 2,
        256 x 256, batch 8, 72K steps."""
        return cls()

    @classmethod
    def quick(cls) -> StyleGAN2Config:
        """64 x 64 on 2 CPU cores, channels sized by the measured seconds per step
        (docs/headcraft.md, part 2)."""
        return cls(resolution=64, z_dim=128, w_dim=128, channel_base=1024, channel_max=64, batch=8,
                   steps=3000, ema_images=2000.0, sample_every=250, checkpoint_every=250)

    def channels_at(self, res: int) -> int:
        return int(min(self.channel_base // res, self.channel_max))


# ---------------------------------------------------------------- layers
class EqualLinear(nn.Module):
    def __init__(self, cin: int, cout: int, bias_init: float = 0.0, lr_mul: float = 1.0, act: bool = False):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin) / lr_mul)
        self.bias = nn.Parameter(torch.full((cout,), float(bias_init)))
        self.scale, self.lr_mul, self.act = lr_mul / math.sqrt(cin), lr_mul, act

    def forward(self, x):
        x = F.linear(x, self.weight * self.scale, self.bias * self.lr_mul)
        return F.leaky_relu(x, 0.2) * SQRT2 if self.act else x


class EqualConv(nn.Module):
    def __init__(self, cin: int, cout: int, k: int, act: bool = True, bias: bool = True, down: bool = False):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin, k, k))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None
        self.scale, self.act, self.down, self.pad = 1 / math.sqrt(cin * k * k), act, down, k // 2

    def forward(self, x):
        x = F.conv2d(x, self.weight * self.scale, self.bias, padding=self.pad)
        if self.down:
            x = F.avg_pool2d(x, 2)
        return F.leaky_relu(x, 0.2) * SQRT2 if self.act else x


class MappingNetwork(nn.Module):
    def __init__(self, cfg: StyleGAN2Config):
        super().__init__()
        dims = [cfg.z_dim] + [cfg.w_dim] * cfg.mapping_layers
        self.layers = nn.Sequential(*[EqualLinear(a, b, lr_mul=0.01, act=True) for a, b in zip(dims[:-1], dims[1:])])
        self.register_buffer("w_avg", torch.zeros(cfg.w_dim))

    def forward(self, z, update_avg: bool = False, beta: float = 0.995):
        z = z * torch.rsqrt(z.square().mean(1, keepdim=True) + 1e-8)
        w = self.layers(z)
        if update_avg:
            self.w_avg.copy_(w.detach().mean(0).lerp(self.w_avg, beta))
        return w


class ModConv(nn.Module):
    """Modulated convolution with optional demodulation and x2 upsampling (before the conv)."""

    def __init__(self, cin: int, cout: int, k: int, w_dim: int, demod: bool = True, up: bool = False):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin, k, k))
        self.affine = EqualLinear(w_dim, cin, bias_init=1.0)
        self.scale, self.demod, self.up, self.pad = 1 / math.sqrt(cin * k * k), demod, up, k // 2

    def forward(self, x, w):
        B, cin, H, W = x.shape
        s = self.affine(w)  # (B, cin)
        weight = self.weight[None] * self.scale * s[:, None, :, None, None]  # (B, cout, cin, k, k)
        if self.demod:
            weight = weight * torch.rsqrt(weight.square().sum([2, 3, 4], keepdim=True) + 1e-8)
        if self.up:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
            H, W = 2 * H, 2 * W
        out = F.conv2d(x.reshape(1, B * cin, H, W), weight.reshape(-1, cin, *weight.shape[3:]), padding=self.pad, groups=B)
        return out.reshape(B, -1, H, W)


class SynthLayer(nn.Module):
    def __init__(self, cin: int, cout: int, w_dim: int, res: int, noise_mask: torch.Tensor, up: bool = False):
        super().__init__()
        self.conv = ModConv(cin, cout, 3, w_dim, up=up)
        self.bias = nn.Parameter(torch.zeros(cout))
        # HeadCraft: a constant noise, drawn once per layer, zero on the face island
        self.register_buffer("noise", torch.randn(1, 1, res, res) * noise_mask)
        self.noise_strength = nn.Parameter(torch.zeros(()))

    def forward(self, x, w):
        x = self.conv(x, w) + self.noise * self.noise_strength
        return F.leaky_relu(x + self.bias[None, :, None, None], 0.2) * SQRT2


class ToRGB(nn.Module):
    def __init__(self, cin: int, cout: int, w_dim: int):
        super().__init__()
        self.conv = ModConv(cin, cout, 1, w_dim, demod=False)
        self.bias = nn.Parameter(torch.zeros(cout))

    def forward(self, x, w):
        return self.conv(x, w) + self.bias[None, :, None, None]


def _noise_mask(face: np.ndarray | None, res: int, noise_on_face: bool) -> torch.Tensor:
    if face is None or noise_on_face:
        return torch.ones(1, 1, res, res)
    f = torch.as_tensor(face, dtype=torch.float32)[None, None]
    f = F.interpolate(f, size=(res, res), mode="area") if res < f.shape[-1] else F.interpolate(f, size=(res, res), mode="nearest")
    return (f < 0.5).float()  # scalp (and empty) texels get noise, the face none


class Generator(nn.Module):
    """z (B, z_dim) -> map (B, channels, R, R). ``face`` (R', R') bool face-island texels."""

    def __init__(self, cfg: StyleGAN2Config, face: np.ndarray | None = None):
        super().__init__()
        if cfg.resolution < 8 or cfg.resolution & (cfg.resolution - 1):
            raise HeadforgeError(f"StyleGAN2 resolution must be a power of two >= 8, got {cfg.resolution}")
        self.cfg = cfg
        self.mapping = MappingNetwork(cfg)
        self.resolutions = [2 ** k for k in range(2, int(math.log2(cfg.resolution)) + 1)]
        c4 = cfg.channels_at(4)
        self.const = nn.Parameter(torch.randn(1, c4, 4, 4))
        self.layers = nn.ModuleList()
        self.torgb = nn.ModuleList()
        cin = c4
        for res in self.resolutions:
            cout = cfg.channels_at(res)
            mask = _noise_mask(face, res, cfg.noise_on_face)
            if res == 4:
                self.layers.append(nn.ModuleList([SynthLayer(cin, cout, cfg.w_dim, res, mask)]))
            else:
                self.layers.append(nn.ModuleList([SynthLayer(cin, cout, cfg.w_dim, res, mask, up=True),
                                                  SynthLayer(cout, cout, cfg.w_dim, res, mask)]))
            self.torgb.append(ToRGB(cout, cfg.channels, cfg.w_dim))
            cin = cout
        self.num_ws = sum(len(block) for block in self.layers) + 1

    def synthesis(self, ws: torch.Tensor) -> torch.Tensor:
        """ws (B, num_ws, w_dim) -> (B, channels, R, R)."""
        x = self.const.expand(ws.shape[0], -1, -1, -1)
        img, k = None, 0
        for block, torgb in zip(self.layers, self.torgb):
            for layer in block:
                x = layer(x, ws[:, k])
                k += 1
            y = torgb(x, ws[:, k])
            img = y if img is None else F.interpolate(img, scale_factor=2, mode="bilinear", align_corners=False) + y
        return img

    def ws(self, z: torch.Tensor, truncation: float = 1.0, mixing: float = 0.0, update_avg: bool = False) -> torch.Tensor:
        w = self.mapping(z, update_avg=update_avg)
        ws = w[:, None].repeat(1, self.num_ws, 1)
        if mixing > 0 and torch.rand(()) < mixing:
            cut = int(torch.randint(1, self.num_ws, ()))
            ws[:, cut:] = self.mapping(torch.randn(z.shape).to(z))[:, None]  # CPU RNG: the same draws on any device
        if truncation != 1.0:
            ws = self.mapping.w_avg.lerp(ws, truncation)
        return ws

    def forward(self, z: torch.Tensor, truncation: float = 1.0) -> torch.Tensor:
        return self.synthesis(self.ws(z, truncation))


class Discriminator(nn.Module):
    """(B, channels, R, R) -> (B, 1) logits, residual architecture."""

    def __init__(self, cfg: StyleGAN2Config):
        super().__init__()
        self.cfg = cfg
        R = cfg.resolution
        self.fromrgb = EqualConv(cfg.channels, cfg.channels_at(R), 1)
        blocks = []
        res = R
        while res > 4:
            cin, cout = cfg.channels_at(res), cfg.channels_at(res // 2)
            blocks.append(nn.ModuleList([EqualConv(cin, cin, 3), EqualConv(cin, cout, 3, down=True),
                                         EqualConv(cin, cout, 1, act=False, bias=False, down=True)]))
            res //= 2
        self.blocks = nn.ModuleList(blocks)
        c4 = cfg.channels_at(4)
        self.conv = EqualConv(c4 + 1, c4, 3)
        self.fc = EqualLinear(c4 * 16, c4, act=True)
        self.out = EqualLinear(c4, 1)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        x = self.fromrgb(img)
        for conv0, conv1, skip in self.blocks:
            x = (skip(x) + conv1(conv0(x))) / SQRT2
        B, C, H, W = x.shape
        g = min(self.cfg.mbstd_group, B)
        while B % g:
            g -= 1
        y = x.reshape(g, -1, C, H, W)
        y = (y - y.mean(0)).square().mean(0).add(1e-8).sqrt().mean([1, 2, 3])  # (B/g,)
        y = y.reshape(-1, 1, 1, 1).repeat(g, 1, H, W)
        x = self.conv(torch.cat([x, y], 1))
        return self.out(self.fc(x.flatten(1)))


# ---------------------------------------------------------------- losses and one training step
def _mine(rows: torch.Tensor) -> torch.Tensor:
    """This rank's strided share of a global batch (B, ...) -> (B / world, ...): items rank,
    rank + world, ... (the whole batch on one process)."""
    return rows[distributed.owned(len(rows))] if distributed.active() else rows


class StyleGAN2Trainer:
    """Non-saturating logistic loss, lazy R1 on reals, lazy path-length regularisation, EMA of G."""

    def __init__(self, cfg: StyleGAN2Config, face: np.ndarray | None = None, seed: int = 0):
        torch.manual_seed(seed)
        self.cfg = cfg
        self.G = Generator(cfg, face)
        self.D = Discriminator(cfg)
        import copy

        self.G_ema = copy.deepcopy(self.G).eval().requires_grad_(False)
        rg, rd = cfg.pl_interval / (cfg.pl_interval + 1), cfg.r1_interval / (cfg.r1_interval + 1)
        self.opt_g = torch.optim.Adam(self.G.parameters(), lr=cfg.g_lr * rg, betas=(0.0, 0.99 ** rg), eps=1e-8)
        self.opt_d = torch.optim.Adam(self.D.parameters(), lr=cfg.d_lr * rd, betas=(0.0, 0.99 ** rd), eps=1e-8)
        self.pl_mean = torch.zeros(())
        self.step = 0
        self.images = 0

    def modules(self) -> dict[str, nn.Module]:
        return {"G": self.G, "D": self.D, "G_ema": self.G_ema}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"opt_g": self.opt_g, "opt_d": self.opt_d}

    def extra_state(self) -> dict[str, torch.Tensor]:
        return {"pl_mean": self.pl_mean.reshape(1)}

    def load_extra_state(self, state: dict[str, torch.Tensor]) -> None:
        self.pl_mean = state["pl_mean"].reshape(()).to(self.G.const.device)

    def train_step(self, real: torch.Tensor) -> dict[str, float]:
        """One D and one G step on the global batch ``real`` (B, C, R, R).

        Under torch.distributed (:mod:`headforge.distributed`) every rank gets the same ``real``
        and draws the same latents (the same seeded global RNG); each works on its strided share
        (items rank, rank + world, ...: a minibatch-std group of the single process then lies on
        one rank whenever the share holds whole groups) and the gradients are averaged before
        each optimiser step, so every term, a mean over items, has the single-process gradient.
        The mapping network runs on the whole batch on every rank (cheap; ``w_avg`` stays the
        single process's); the path-length mean is averaged over the ranks."""
        cfg, G, D = self.cfg, self.G, self.D
        B, dev = real.shape[0], real.device  # latents drawn on the CPU's RNG, then moved: one stream on any device
        world = distributed.world_size()
        if B % world:
            raise HeadforgeError(f"batch {B} cannot be split over {world} processes: --set batch=N with N a multiple of {world}")
        terms = {}
        # --- D: logistic loss (+ lazy R1)
        D.requires_grad_(True)
        G.requires_grad_(False)
        with torch.no_grad():
            fake = G.synthesis(_mine(G.ws(torch.randn(B, cfg.z_dim).to(dev), mixing=cfg.style_mixing)))
        real = _mine(real)
        loss_d = F.softplus(D(fake)).mean() + F.softplus(-D(real)).mean()
        if self.step % cfg.r1_interval == 0:
            r = real.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(D(r).sum(), r, create_graph=True)
            r1 = grad.square().sum([1, 2, 3]).mean()
            loss_d = loss_d + r1 * (cfg.r1_gamma / 2) * cfg.r1_interval
            terms["r1"] = r1.detach()
        self.opt_d.zero_grad(set_to_none=True)
        loss_d.backward()
        distributed.average_gradients(D.parameters())
        self.opt_d.step()
        terms["loss_d"] = loss_d.detach()
        # --- G: non-saturating loss (+ lazy path-length)
        D.requires_grad_(False)
        G.requires_grad_(True)
        ws = G.ws(torch.randn(B, cfg.z_dim).to(dev), mixing=cfg.style_mixing, update_avg=True)
        loss_g = F.softplus(-D(G.synthesis(_mine(ws)))).mean()
        if cfg.pl_weight > 0 and self.step % cfg.pl_interval == 0:
            pb = world * max(1, B // world // 2)  # half of each share (one process: max(1, B // 2))
            ws_pl = G.ws(_mine(torch.randn(pb, cfg.z_dim)).to(dev))
            img = G.synthesis(ws_pl)
            R = cfg.resolution
            noise = _mine(torch.randn(pb, img.shape[1], R, R)).to(dev) / math.sqrt(R * R)
            (gw,) = torch.autograd.grad((img * noise).sum(), ws_pl, create_graph=True)
            lengths = gw.square().sum(2).mean(1).sqrt()
            mean_length = distributed.mean_terms({"l": lengths.mean().detach()})["l"]
            self.pl_mean = self.pl_mean.to(mean_length).lerp(mean_length, cfg.pl_decay)
            pl = (lengths - self.pl_mean).square().mean()
            loss_g = loss_g + pl * cfg.pl_weight * cfg.pl_interval
            terms["pl"] = pl.detach()
        self.opt_g.zero_grad(set_to_none=True)
        loss_g.backward()
        distributed.average_gradients(G.parameters())
        self.opt_g.step()
        terms["loss_g"] = loss_g.detach()
        logs = {k: float(v) for k, v in distributed.mean_terms(terms).items()}
        # --- EMA of G
        self.step += 1
        self.images += B
        half_life = cfg.ema_images
        if cfg.ema_rampup is not None:
            half_life = min(half_life, self.images * cfg.ema_rampup)
        beta = 0.5 ** (B / max(half_life, 1e-8))
        with torch.no_grad():
            for p_ema, p in zip(self.G_ema.parameters(), G.parameters()):
                p_ema.copy_(p.detach().lerp(p_ema, beta))
            for b_ema, b in zip(self.G_ema.buffers(), G.buffers()):
                b_ema.copy_(b)
        return logs

    @torch.no_grad()
    def sample(self, z: torch.Tensor, truncation: float = 1.0) -> torch.Tensor:
        return self.G_ema(z, truncation)
