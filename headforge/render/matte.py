"""Soft alpha mattes: a rendered image's hard (antialiased) silhouette widened into a soft edge.

Video mattes from a segmenter are soft over a few pixels (and jitter by about as much from
frame to frame); a mesh render's edge is one pixel wide. Compared with such a matted frame,
the squared error of any edge misplacement is smallest for an edge as soft as the frame's
uncertainty -- :func:`soft_matte` gives the render that edge, :func:`fit_sigma` finds it.

Images are (B, H, W, C) in [0, 1]; ``sigma`` in pixels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B, H, W, C) separable Gaussian filter of std ``sigma`` px (radius 3 sigma), edges
    replicated; the input itself for sigma <= 0."""
    if sigma <= 0:
        return images
    r = max(1, math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=images.dtype, device=images.device)
    g = torch.exp(-t ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    x = images.permute(0, 3, 1, 2)
    C = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)
    return x.permute(0, 2, 3, 1)


def soft_matte(rgb: torch.Tensor, coverage: torch.Tensor, sigma: float,
               background: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(rgb, alpha) of a render with its edge softened by a Gaussian of ``sigma`` px.

    ``rgb`` (B, H, W, 3) is composited on ``background`` with ``coverage`` (B, H, W) (the
    antialiased silhouette). The new alpha is the blurred coverage; colours stay as rendered
    where the pixel was fully covered and elsewhere are the coverage-weighted blur of the
    nearby foreground colours (normalised convolution), so the soft edge has the colour of the
    surface it fades from, not of the background. The interior is unchanged.
    """
    if sigma <= 0:
        return rgb, coverage
    cov = coverage[..., None]
    premultiplied = rgb - (1 - cov) * background
    alpha = gaussian_blur(cov, sigma)
    spread = gaussian_blur(premultiplied, sigma) / alpha.clamp(min=1e-4)
    colour = torch.where(cov > 0.999, premultiplied / cov.clamp(min=1e-4), spread)
    return colour * alpha + (1 - alpha) * background, alpha[..., 0]


def fit_sigma(rgb: torch.Tensor, coverage: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
              background: float = 1.0, grid: tuple[float, ...] = tuple(i / 4 for i in range(17))) -> tuple[float, list]:
    """The ``grid`` sigma (px) whose :func:`soft_matte` of the renders best matches ``target``
    (B, H, W, 3, frames matted on ``background``) in weighted squared error (``weight``
    (B, H, W), e.g. the evaluated area). Returns (sigma, [(sigma, mse), ...])."""
    w = weight[..., None].to(rgb.dtype)
    scores = []
    for s in grid:
        out, _ = soft_matte(rgb, coverage, s, background)
        scores.append((s, float((((out - target) ** 2) * w).sum() / (3 * w.sum()).clamp(min=1))))
    return min(scores, key=lambda x: x[1])[0], scores
