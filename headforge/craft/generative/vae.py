"""VAE baseline (HeadCraft Table 2, App. B): ResNet-18-style encoder and decoder (blocks of two
3x3 convs, stride 2 in the encoder / nearest x2 upsampling in the decoder), FC heads for mu and
log sigma^2, latent 512 (paper). Lightning Bolts' layout, written here in plain PyTorch.

Maps are (B, C, H, W) model units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from headforge import distributed


@dataclass
class VAEConfig:
    resolution: int = 256
    channels: int = 3
    latent: int = 512
    widths: list[int] = field(default_factory=lambda: [64, 64, 128, 256, 256, 256, 512, 512])  # one per block
    strides: list[int] = field(default_factory=lambda: [1, 2, 2, 2, 2, 2, 2, 1])  # encoder downsampling per block
    kl_weight: float = 1e-2  # weight of the per-dimension KL against the per-texel squared error
    lr: float = 1e-4
    batch: int = 8
    steps: int = 10_000
    sample_every: int = 500
    checkpoint_every: int = 500

    @classmethod
    def paper(cls) -> VAEConfig:
        return cls()

    @classmethod
    def quick(cls) -> VAEConfig:
        return cls(resolution=64, latent=128, widths=[16, 32, 64, 64, 128], strides=[1, 2, 2, 2, 2], lr=1e-3,
                   steps=1500, sample_every=250, checkpoint_every=250)


class ResBlock(nn.Module):
    """Two 3x3 convs with batch norm; ``down`` strides the first, ``up`` upsamples before it."""

    def __init__(self, cin: int, cout: int, down: bool = False, up: bool = False):
        super().__init__()
        self.up = up
        self.c1 = nn.Conv2d(cin, cout, 3, 2 if down else 1, 1, bias=False)
        self.b1 = nn.BatchNorm2d(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.b2 = nn.BatchNorm2d(cout)
        self.skip = None
        if down or cin != cout:
            self.skip = nn.Sequential(nn.Conv2d(cin, cout, 1, 2 if down else 1, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        if self.up:
            x = F.interpolate(x, scale_factor=2, mode="nearest")
        y = F.relu(self.b1(self.c1(x)))
        y = self.b2(self.c2(y))
        return F.relu(y + (x if self.skip is None else self.skip(x)))


def encoder(channels: int, widths: list[int], strides: list[int]) -> nn.Sequential:
    layers = [nn.Conv2d(channels, widths[0], 3, 1, 1), nn.ReLU()]
    cin = widths[0]
    for w, s in zip(widths, strides):
        layers.append(ResBlock(cin, w, down=s == 2))
        cin = w
    return nn.Sequential(*layers)


def decoder(channels: int, widths: list[int], strides: list[int]) -> nn.Sequential:
    layers = []
    rw, rs = widths[::-1], strides[::-1]
    cin = rw[0]
    for w, s in zip(rw, rs):
        layers.append(ResBlock(cin, w, up=s == 2))
        cin = w
    layers.append(nn.Conv2d(cin, channels, 3, 1, 1))
    return nn.Sequential(*layers)


class VAE(nn.Module):
    def __init__(self, cfg: VAEConfig):
        super().__init__()
        self.cfg = cfg
        self.enc = encoder(cfg.channels, cfg.widths, cfg.strides)
        down = 2 ** sum(s == 2 for s in cfg.strides)
        self.bottom = cfg.resolution // down
        flat = cfg.widths[-1] * self.bottom ** 2
        self.mu = nn.Linear(flat, cfg.latent)
        self.logvar = nn.Linear(flat, cfg.latent)
        self.fc = nn.Linear(cfg.latent, flat)
        self.dec = decoder(cfg.channels, cfg.widths, cfg.strides)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        h = self.fc(z).reshape(-1, self.cfg.widths[-1], self.bottom, self.bottom)
        return self.dec(h)

    def forward(self, x: torch.Tensor):
        h = self.enc(x).flatten(1)
        mu, logvar = self.mu(h), self.logvar(h).clamp(-10, 10)
        z = mu + torch.randn(mu.shape).to(mu) * (0.5 * logvar).exp()  # CPU RNG: one stream on any device
        return self.decode(z), mu, logvar

    def latent_dim(self) -> int:
        return self.cfg.latent

    @torch.no_grad()
    def sample(self, z: torch.Tensor, truncation: float = 1.0) -> torch.Tensor:
        return self.decode(z * truncation)


class VAETrainer:
    def __init__(self, cfg: VAEConfig, seed: int = 0):
        torch.manual_seed(seed)
        self.cfg = cfg
        self.model = VAE(cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.step = 0

    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model}

    def optimizers(self) -> dict:
        return {"opt": self.opt}

    def train_step(self, real: torch.Tensor) -> dict[str, float]:
        """One step on the global batch ``real`` (B, C, R, R). Under torch.distributed each rank
        takes its share (:func:`headforge.distributed.shard`) and the gradients are averaged;
        batch norm's statistics are then the share's, not the batch's."""
        self.model.train()
        real = distributed.shard(real)
        rec, mu, logvar = self.model(real)
        l_rec = (rec - real).square().mean()
        kl = (-0.5 * (1 + logvar - mu.square() - logvar.exp())).mean()  # per latent dimension
        loss = l_rec + self.cfg.kl_weight * kl
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        distributed.average_gradients(self.model.parameters())
        self.opt.step()
        self.step += 1
        terms = distributed.mean_terms({"rec": l_rec.detach(), "kl": kl.detach()})
        return {k: float(v) for k, v in terms.items()}

    @torch.no_grad()
    def sample(self, z: torch.Tensor, truncation: float = 1.0) -> torch.Tensor:
        self.model.eval()
        return self.model.sample(z, truncation)
