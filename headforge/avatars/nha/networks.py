"""NHA's networks (App. A.2): SIREN MLPs whose layers are FiLM-conditioned by mapping networks.

A FiLM-SIREN layer computes sin(gamma * (W x + b) + beta), with per-sample frequencies gamma
and phase shifts beta predicted by a mapping network from a condition (pi-GAN style).
"""

from __future__ import annotations

import math

import torch
from torch import nn


class MappingNetwork(nn.Module):
    """Condition (B, C) -> per-layer (gamma, beta), each (B, layers, width).

    ``hidden`` layers of ``hidden_width`` with leaky ReLU (slope 0.2); gamma starts near 1
    (the last layer is initialised small around the identity), beta near 0.
    """

    def __init__(self, cond_dim: int, layers: int, width: int, hidden: int = 3, hidden_width: int = 256):
        super().__init__()
        dims = [cond_dim] + [hidden_width] * hidden
        blocks = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.LeakyReLU(0.2)]
        self.body = nn.Sequential(*blocks)
        self.out = nn.Linear(dims[-1], 2 * layers * width)
        with torch.no_grad():
            self.out.weight.mul_(0.01)
            self.out.bias.zero_()
        self.layers, self.width = layers, width

    def forward(self, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        film = self.out(self.body(cond)).view(-1, 2, self.layers, self.width)
        return 1.0 + film[:, 0], film[:, 1]


class FiLMSiren(nn.Module):
    """SIREN MLP of ``layers`` FiLM layers of ``width``; inputs (B, N, in_dim); FiLM (B, layers, width).

    Initialisation follows SIREN (first layer U(-1/in, 1/in) * omega0 via ``first_omega``).
    """

    def __init__(self, in_dim: int, layers: int, width: int, first_omega: float = 30.0):
        super().__init__()
        self.linears = nn.ModuleList([nn.Linear(in_dim if i == 0 else width, width) for i in range(layers)])
        with torch.no_grad():
            for i, lin in enumerate(self.linears):
                bound = 1 / lin.in_features if i == 0 else math.sqrt(6 / lin.in_features) / first_omega
                lin.weight.uniform_(-bound, bound)
        self.first_omega = first_omega

    def forward(self, x: torch.Tensor, gamma: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
        for i, lin in enumerate(self.linears):
            h = lin(x)
            if i == 0:
                h = h * self.first_omega
            x = torch.sin(gamma[:, None, i] * h + beta[:, None, i])
        return x


class GeometryNet(nn.Module):
    """G: per-vertex offsets from (template position in [-1, 1], learned per-vertex embedding),
    FiLM-conditioned on the neck pose (App. A.2.1). Output: (B, V, 3) metres, bounded by
    ``max_offset`` through tanh."""

    def __init__(self, n_vertices: int, embed_dim: int = 32, layers: int = 6, width: int = 128,
                 cond_dim: int = 3, max_offset: float = 0.08):
        super().__init__()
        self.embedding = nn.Parameter(1e-3 * torch.randn(n_vertices, embed_dim))
        self.mapping = MappingNetwork(cond_dim, layers, width)
        self.siren = FiLMSiren(3 + embed_dim, layers, width)
        self.head = nn.Linear(width, 3)
        with torch.no_grad():
            self.head.weight.mul_(1e-3)
            self.head.bias.zero_()
        self.max_offset = max_offset

    def forward(self, positions: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """positions (V, 3) normalised template; cond (B, cond_dim) -> offsets (B, V, 3)."""
        gamma, beta = self.mapping(cond)
        x = torch.cat([positions, self.embedding], -1)[None].expand(cond.shape[0], -1, -1)
        return self.max_offset * torch.tanh(self.head(self.siren(x, gamma, beta)))


class TextureNet(nn.Module):
    """T: colour of a surface point from its canonical position and a feature sampled from a
    learned UV grid (App. A.2.2), FiLM-conditioned on mouth-related parameters -- used only in
    the mouth region (elsewhere the zero condition: a static texture). Output RGB in [0, 1]."""

    def __init__(self, grid_size: int = 256, grid_channels: int = 64, layers: int = 8, width: int = 256,
                 cond_dim: int = 8):
        super().__init__()
        self.grid = nn.Parameter(1e-2 * torch.randn(1, grid_channels, grid_size, grid_size))
        self.mapping = MappingNetwork(cond_dim, layers, width, hidden_width=128)
        self.siren = FiLMSiren(3 + grid_channels, layers, width)
        self.rgb = nn.Linear(width, 3)
        self.cond_dim = cond_dim

    def sample_grid(self, uv: torch.Tensor) -> torch.Tensor:
        """uv (N, 2) in [0, 1], v up -> (N, C) bilinear features."""
        grid = torch.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], -1)[None, None]
        return torch.nn.functional.grid_sample(self.grid, grid, align_corners=False)[0, :, 0].T

    def forward(self, points: torch.Tensor, uv: torch.Tensor, cond: torch.Tensor, mouth: torch.Tensor) -> torch.Tensor:
        """points (N, 3) canonical in [-1, 1]; uv (N, 2); cond (N, cond_dim) per pixel; mouth (N,)
        bool -> rgb (N, 3). Runs the network once for static pixels and once for mouth pixels."""
        x = torch.cat([points, self.sample_grid(uv)], -1)
        out = torch.empty(len(x), 3, dtype=x.dtype, device=x.device)
        for sel, c in ((~mouth, torch.zeros(1, self.cond_dim, dtype=x.dtype, device=x.device)), (mouth, None)):
            if not sel.any():
                continue
            if c is None:  # mouth pixels: per-pixel condition (their frame's mouth parameters)
                gamma, beta = self.mapping(cond[sel])
                h = self.siren(x[sel][:, None], gamma, beta)[:, 0]
            else:
                gamma, beta = self.mapping(c)
                h = self.siren(x[sel][None], gamma, beta)[0]
            out[sel] = 0.5 + 0.5 * torch.tanh(self.rgb(h))
        return out
