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
    """SIREN MLP of ``layers`` FiLM layers of ``width`` (the last ``last_width`` wide, default
    ``width``); inputs (B, N, in_dim); FiLM (B, layers, >= width) -> (B, N, last_width).

    Initialisation follows SIREN (first layer U(-1/in, 1/in) * omega0 via ``first_omega``).
    """

    def __init__(self, in_dim: int, layers: int, width: int, first_omega: float = 30.0, last_width: int | None = None):
        super().__init__()
        widths = [width] * (layers - 1) + [last_width or width]
        self.linears = nn.ModuleList([nn.Linear(in_dim if i == 0 else width, widths[i]) for i in range(layers)])
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
            n = h.shape[-1]
            x = torch.sin(gamma[:, None, i, :n] * h + beta[:, None, i, :n])
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

    def forward(self, positions: torch.Tensor, cond: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """positions (V, 3) normalised template; cond (B, cond_dim) -> offsets (B, V, 3), or with
        ``rows`` (R,) vertex indices those vertices' offsets (B, R, 3) only (the same values as
        the full evaluation's rows)."""
        gamma, beta = self.mapping(cond)
        x = torch.cat([positions, self.embedding], -1)
        x = (x if rows is None else x[rows])[None].expand(cond.shape[0], -1, -1)
        return self.max_offset * torch.tanh(self.head(self.siren(x, gamma, beta)))


class NormalEncoder(nn.Module):
    """NHA's normal encoder (App. A.2.2): fully convolutional, 3x3 stride-1 convolutions with
    periodic activations over the rendered normal map, FiLM-conditioned like the linear layers.
    (B, 3, H, W) camera-space normals (zero on the background) -> (B, channels[-1], H, W): a
    feature of each pixel's local normal patch (receptive field 7x7 for three layers)."""

    def __init__(self, channels: tuple[int, ...] = (128, 128, 32), omega: float = 3.0):
        super().__init__()
        dims = (3,) + tuple(channels)
        self.convs = nn.ModuleList([nn.Conv2d(a, b, 3, padding=1) for a, b in zip(dims[:-1], dims[1:])])
        with torch.no_grad():
            for conv in self.convs[1:]:
                bound = math.sqrt(6 / (conv.in_channels * 9))
                conv.weight.uniform_(-bound, bound)
        self.omega = omega  # unit normals vary slowly across pixels: a low first frequency

    def _activate(self, i: int, h: torch.Tensor, gamma: torch.Tensor | None, beta: torch.Tensor | None) -> torch.Tensor:
        """sin(FiLM(h)) of layer ``i``; h (B, C, ...) with channels in dim 1."""
        h = h * (self.omega if i == 0 else 1.0)
        if gamma is not None:
            shape = (-1, h.shape[1]) + (1,) * (h.ndim - 2)
            h = gamma[:, i, : h.shape[1]].reshape(shape) * h + beta[:, i, : h.shape[1]].reshape(shape)
        return torch.sin(h)

    def forward(self, normals: torch.Tensor, gamma: torch.Tensor | None = None,
                beta: torch.Tensor | None = None) -> torch.Tensor:
        """gamma/beta (B, layers, max(channels)) or None (identity FiLM)."""
        x = normals
        for i, conv in enumerate(self.convs):
            x = self._activate(i, conv(x), gamma, beta)
        return x

    def forward_uniform(self, normals: torch.Tensor, gamma: torch.Tensor | None = None,
                        beta: torch.Tensor | None = None) -> torch.Tensor:
        """The feature of a constant patch: (N, 3) normals -> (N, channels[-1]). Equal to
        :meth:`forward` away from image borders; a 3x3 convolution of a constant image is a linear
        map with the kernel summed over space. gamma/beta (1, layers, max(channels)) or None."""
        x = normals
        for i, conv in enumerate(self.convs):
            x = self._activate(i, x @ conv.weight.sum((2, 3)).T + conv.bias, gamma, beta)
        return x


class TextureNet(nn.Module):
    """T (App. A.2.2): colour of a surface point from its canonical position and a feature
    sampled from a learned UV grid (a separate, smaller grid for the inner mouth), FiLM-conditioned
    on mouth-related parameters -- used only in the mouth region (elsewhere the zero condition: a
    static texture). Two heads summed before the tanh: a linear one on the SIREN feature, and one
    that concatenates it with the normal encoder's feature of the pixel's normal patch (a linear
    FiLM layer, then linear) -- the path for view- and expression-dependent shading, and through
    which the photometric term reaches the geometry's normals. Output RGB in [0, 1].

    App. A.2.2's sizes: ``layers`` 8 x ``width`` 256 with ``last_width`` 128, a mapping network of
    3 x ``mapping_width`` 256 (as G's), normal encoder 128-128-32, ``head_width`` 128."""

    def __init__(self, grid_size: int = 256, grid_channels: int = 64, layers: int = 8, width: int = 256,
                 cond_dim: int = 8, mouth_grid_size: int = 64, normal_channels: tuple[int, ...] = (128, 128, 32),
                 head_width: int = 128, mapping_width: int = 128, last_width: int | None = None):
        super().__init__()
        self.grid = nn.Parameter(1e-2 * torch.randn(1, grid_channels, grid_size, grid_size))
        self.mouth_grid = nn.Parameter(1e-2 * torch.randn(1, grid_channels, mouth_grid_size, mouth_grid_size))
        film_width = max(width, head_width, last_width or 0)
        # FiLM of the SIREN layers, the head's FiLM layer, and the normal encoder's convolutions
        self.mapping = MappingNetwork(cond_dim, layers + 1 + len(normal_channels), film_width, hidden_width=mapping_width)
        self.siren = FiLMSiren(3 + grid_channels, layers, width, last_width=last_width)
        out = last_width or width  # the SIREN feature's width
        self.rgb = nn.Linear(out, 3)
        self.normal_encoder = NormalEncoder(normal_channels)
        self.head_film = nn.Linear(out + normal_channels[-1], head_width)
        self.head_rgb = nn.Linear(head_width, 3)
        with torch.no_grad():
            bound = math.sqrt(6 / self.head_film.in_features)
            self.head_film.weight.uniform_(-bound, bound)
            self.head_rgb.weight.mul_(0.1)  # starts as a small correction of the first head
            self.head_rgb.bias.zero_()
        self.cond_dim, self.layers, self.head_width = cond_dim, layers, head_width
        self.width = max(width, last_width or 0)  # the SIREN's FiLM width (its widest layer)

    @staticmethod
    def _sample(grid: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """uv (N, 2) in [0, 1], v up -> (N, C) bilinear features of ``grid`` (1, C, S, S)."""
        xy = torch.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], -1)[None, None]
        return torch.nn.functional.grid_sample(grid, xy, align_corners=False)[0, :, 0].T

    def sample_grid(self, uv: torch.Tensor, inner_mouth: torch.Tensor | None = None) -> torch.Tensor:
        """(N, C) features: the main grid, or the inner-mouth grid where ``inner_mouth`` (N,) is set."""
        feats = self._sample(self.grid, uv)
        if inner_mouth is not None and inner_mouth.any():
            feats = feats.index_put((torch.nonzero(inner_mouth)[:, 0],), self._sample(self.mouth_grid, uv[inner_mouth]))
        return feats

    def film(self, cond: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, cond_dim) -> FiLM parameters of the SIREN, the second head and the normal encoder."""
        gamma, beta = self.mapping(cond)
        L, W = self.layers, self.width
        return {"siren": (gamma[:, :L, :W], beta[:, :L, :W]), "head": (gamma[:, L, : self.head_width], beta[:, L, : self.head_width]),
                "normals": (gamma[:, L + 1:], beta[:, L + 1:])}

    def _normal_film(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The normal encoder's FiLM, from the zero condition (the mouth condition steers the
        colour heads; the encoder sees geometry only)."""
        return self.film(torch.zeros(1, self.cond_dim, dtype=like.dtype, device=like.device))["normals"]

    def encode_normals(self, normals: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) rendered normals -> (B, H, W, C) patch features."""
        gamma, beta = self._normal_film(normals)
        feats = self.normal_encoder(normals.permute(0, 3, 1, 2), gamma.expand(len(normals), -1, -1),
                                    beta.expand(len(normals), -1, -1))
        return feats.permute(0, 2, 3, 1)

    def encode_uniform_normals(self, normals: torch.Tensor) -> torch.Tensor:
        """(N, 3) normals -> (N, C) features of flat patches (texture baking)."""
        return self.normal_encoder.forward_uniform(normals, *self._normal_film(normals))

    def forward(self, points: torch.Tensor, uv: torch.Tensor, cond: torch.Tensor, mouth: torch.Tensor,
                normal_features: torch.Tensor, inner_mouth: torch.Tensor | None = None) -> torch.Tensor:
        """points (N, 3) canonical in [-1, 1]; uv (N, 2); cond (N, cond_dim) per pixel; mouth (N,)
        bool; normal_features (N, C) from :meth:`encode_normals`; inner_mouth (N,) bool ->
        rgb (N, 3). Runs the network once for static pixels and once for mouth pixels."""
        x = torch.cat([points, self.sample_grid(uv, inner_mouth)], -1)
        out = torch.empty(len(x), 3, dtype=x.dtype, device=x.device)
        for sel, c in ((~mouth, torch.zeros(1, self.cond_dim, dtype=x.dtype, device=x.device)), (mouth, None)):
            if not sel.any():
                continue
            if c is None:  # mouth pixels: per-pixel condition (their frame's mouth parameters)
                f = self.film(cond[sel])
                h = self.siren(x[sel][:, None], *f["siren"])[:, 0]
                g, b = f["head"]
            else:
                f = self.film(c)
                h = self.siren(x[sel][None], *f["siren"])[0]
                g, b = f["head"][0][0], f["head"][1][0]
            second = torch.sin(g * self.head_film(torch.cat([h, normal_features[sel]], -1)) + b)
            out[sel] = 0.5 + 0.5 * torch.tanh(self.rgb(h) + self.head_rgb(second))
        return out
