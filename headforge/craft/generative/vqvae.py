"""VQ-VAE baseline with a PixelCNN prior (HeadCraft Table 2, App. B): ResNet-18-style encoder
and decoder with fewer downsamplings than the VAE (a bottleneck of resolution / 8: 32 x 32 at
256), the vector quantiser of ``vector-quantize-pytorch`` (as the authors), and a gated PixelCNN
(van den Oord et al. 2016) trained on the code indices of the training maps, sampled
autoregressively.

Maps are (B, C, H, W) model units; code maps are (B, h, w) long.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from headforge.craft.generative.vae import decoder, encoder


@dataclass
class VQVAEConfig:
    resolution: int = 256
    channels: int = 3
    widths: list[int] = field(default_factory=lambda: [64, 64, 128, 128, 128, 128, 32, 32])  # paper: 64, 128, 128, 32 per two blocks
    strides: list[int] = field(default_factory=lambda: [1, 1, 2, 1, 2, 1, 2, 1])  # down at every second block from the third
    codebook: int = 512
    commitment: float = 0.25
    lr: float = 3e-4
    batch: int = 8
    steps: int = 10_000
    prior_channels: int = 64
    prior_layers: int = 8
    prior_lr: float = 1e-3
    prior_batch: int = 32
    prior_epochs: int = 200
    sample_every: int = 1000
    checkpoint_every: int = 1000

    @classmethod
    def paper(cls) -> VQVAEConfig:
        return cls()

    @classmethod
    def quick(cls) -> VQVAEConfig:
        return cls(resolution=64, widths=[16, 32, 32, 32, 16, 16], strides=[1, 1, 2, 1, 2, 1], codebook=128,
                   lr=1e-3, steps=1000, prior_channels=32, prior_layers=5, prior_epochs=100,
                   sample_every=250, checkpoint_every=250)

    @property
    def bottom(self) -> int:
        return self.resolution // 2 ** sum(s == 2 for s in self.strides)


class VQVAE(nn.Module):
    def __init__(self, cfg: VQVAEConfig):
        super().__init__()
        from vector_quantize_pytorch import VectorQuantize

        self.cfg = cfg
        self.enc = encoder(cfg.channels, cfg.widths, cfg.strides)
        self.dec = decoder(cfg.channels, cfg.widths, cfg.strides)
        self.vq = VectorQuantize(dim=cfg.widths[-1], codebook_size=cfg.codebook, decay=0.8,
                                 commitment_weight=cfg.commitment, accept_image_fmap=True, kmeans_init=True,
                                 threshold_ema_dead_code=2)

    def forward(self, x: torch.Tensor):
        q, idx, commit = self.vq(self.enc(x))
        return self.dec(q), idx, commit

    @torch.no_grad()
    def codes(self, x: torch.Tensor) -> torch.Tensor:
        _, idx, _ = self.vq(self.enc(x))
        return idx

    @torch.no_grad()
    def decode_codes(self, idx: torch.Tensor) -> torch.Tensor:
        """Maps (B, C, H, W) of codes (B, h, w). The quantiser's own image-layout lookup: its
        ``get_codes_from_indices`` is channel-first for image feature maps, (B, dim, h*w)."""
        return self.dec(self.vq.get_output_from_indices(idx))


# ---------------------------------------------------------------- gated PixelCNN prior
class MaskedConv(nn.Conv2d):
    """Causal k x k convolution: type 'A' hides the centre (first layer), 'B' keeps it."""

    def __init__(self, cin: int, cout: int, k: int, kind: str):
        super().__init__(cin, cout, k, padding=k // 2)
        mask = torch.ones_like(self.weight)
        c = k // 2
        mask[:, :, c, c + (kind == "B"):] = 0
        mask[:, :, c + 1:] = 0
        self.register_buffer("mask", mask)

    def forward(self, x):
        return F.conv2d(x, self.weight * self.mask, self.bias, padding=self.padding)


class GatedLayer(nn.Module):
    def __init__(self, ch: int, k: int = 5):
        super().__init__()
        self.conv = MaskedConv(ch, 2 * ch, k, "B")
        self.out = nn.Conv2d(ch, ch, 1)

    def forward(self, x):
        a, b = self.conv(x).chunk(2, 1)
        return x + self.out(torch.tanh(a) * torch.sigmoid(b))


class PixelCNN(nn.Module):
    """Logits (B, K, h, w) of each code given the codes above and to its left."""

    def __init__(self, codebook: int, ch: int, layers: int):
        super().__init__()
        self.codebook = codebook
        self.embed = nn.Embedding(codebook, ch)
        self.first = MaskedConv(ch, ch, 7, "A")
        self.layers = nn.ModuleList([GatedLayer(ch) for _ in range(layers)])
        self.head = nn.Sequential(nn.ReLU(), nn.Conv2d(ch, ch, 1), nn.ReLU(), nn.Conv2d(ch, codebook, 1))

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        x = self.first(self.embed(idx).permute(0, 3, 1, 2))
        for layer in self.layers:
            x = layer(x)
        return self.head(x)

    @torch.no_grad()
    def sample(self, n: int, h: int, w: int, temperature: float = 1.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """(n, h, w) codes, raster order; temperature 0 takes the most likely code (greedy)."""
        idx = torch.zeros(n, h, w, dtype=torch.long, device=self.embed.weight.device)
        for i in range(h):
            for j in range(w):
                logits = self(idx)[:, :, i, j]
                if temperature <= 0:
                    idx[:, i, j] = logits.argmax(1)
                else:
                    p = torch.softmax(logits / temperature, 1)
                    idx[:, i, j] = torch.multinomial(p.cpu(), 1, generator=generator)[:, 0].to(idx)  # a CPU generator
        return idx


class VQVAETrainer:
    """Stage 1 trains the autoencoder (``steps``); stage 2 the PixelCNN on the training codes
    (``prior_epochs`` epochs)."""

    def __init__(self, cfg: VQVAEConfig, seed: int = 0):
        torch.manual_seed(seed)
        self.cfg = cfg
        self.model = VQVAE(cfg)
        self.prior = PixelCNN(cfg.codebook, cfg.prior_channels, cfg.prior_layers)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.opt_prior = torch.optim.Adam(self.prior.parameters(), lr=cfg.prior_lr)
        self.step = 0

    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model, "prior": self.prior}

    def optimizers(self) -> dict:
        return {"opt": self.opt, "opt_prior": self.opt_prior}

    def train_step(self, real: torch.Tensor) -> dict[str, float]:
        self.model.train()
        rec, _, commit = self.model(real)
        l_rec = (rec - real).square().mean()
        loss = l_rec + commit.sum()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        return {"rec": float(l_rec.detach()), "commit": float(commit.sum().detach())}

    def fit_prior(self, maps: torch.Tensor, progress=None) -> dict[str, float]:
        """PixelCNN on the codes of every training map; returns the last epoch's NLL (nats)."""
        self.model.eval()
        codes = torch.cat([self.model.codes(maps[i:i + 16]) for i in range(0, len(maps), 16)])
        nll = float("nan")
        for epoch in range(self.cfg.prior_epochs):
            perm = torch.randperm(len(codes)).to(codes.device)
            total = 0.0
            for k in range(0, len(codes), self.cfg.prior_batch):
                batch = codes[perm[k:k + self.cfg.prior_batch]]
                loss = F.cross_entropy(self.prior(batch), batch)
                self.opt_prior.zero_grad(set_to_none=True)
                loss.backward()
                self.opt_prior.step()
                total += float(loss.detach()) * len(batch)
            nll = total / len(codes)
            if progress is not None:
                progress(epoch + 1, nll)
        return {"prior_nll": nll, "codes_used": int(codes.unique().numel())}

    @torch.no_grad()
    def sample(self, n: int, truncation: float = 1.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """Truncation is the PixelCNN's sampling temperature (0: greedy, one deterministic map)."""
        self.model.eval()
        b = self.cfg.bottom
        return self.model.decode_codes(self.prior.sample(n, b, b, truncation, generator))
