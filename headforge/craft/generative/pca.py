"""PCA baseline over displacement maps (HeadCraft Tables 1-2): a linear basis fitted to the
flattened training maps, sampled with Gaussian coefficients.

Maps are (N, C, H, W) model units (see :mod:`headforge.craft.generative.data`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from headforge.errors import HeadforgeError


@dataclass
class PCAConfig:
    resolution: int = 256
    channels: int = 3
    components: int = 64  # at most (training maps - 1)
    steps: int = 1  # fitted in closed form

    @classmethod
    def paper(cls) -> PCAConfig:
        return cls()

    @classmethod
    def quick(cls) -> PCAConfig:
        return cls(resolution=64)


class PCAModel(torch.nn.Module):
    def __init__(self, cfg: PCAConfig):
        super().__init__()
        self.cfg = cfg
        D = cfg.channels * cfg.resolution ** 2
        self.register_buffer("mean", torch.zeros(D))
        self.register_buffer("basis", torch.zeros(cfg.components, D))  # rows: unit components
        self.register_buffer("std", torch.zeros(cfg.components))  # per-component standard deviation

    def fit(self, maps: torch.Tensor) -> None:
        N = maps.shape[0]
        if N < 2:
            raise HeadforgeError("PCA needs at least 2 training maps")
        x = maps.reshape(N, -1).double()
        mean = x.mean(0)
        _, s, vt = torch.linalg.svd(x - mean, full_matrices=False)
        k = min(self.cfg.components, N - 1)
        self.mean.copy_(mean.float())
        self.basis.zero_()
        self.std.zero_()
        self.basis[:k] = vt[:k].float()
        self.std[:k] = (s[:k] / (N - 1) ** 0.5).float()

    def decode(self, coeff: torch.Tensor) -> torch.Tensor:
        R, C = self.cfg.resolution, self.cfg.channels
        return (self.mean + (coeff * self.std) @ self.basis).reshape(-1, C, R, R)

    def latent_dim(self) -> int:
        return self.cfg.components

    @torch.no_grad()
    def sample(self, z: torch.Tensor, truncation: float = 1.0) -> torch.Tensor:
        """z (B, components) standard normal -> maps; truncation scales the coefficients."""
        return self.decode(z * truncation)
