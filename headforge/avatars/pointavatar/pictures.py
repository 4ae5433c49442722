"""Pictures of a trained PointAvatar: the canonical cloud coloured by albedo, by normal and by
shading (front and side), and the point count over training."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from headforge.avatars.pointavatar.model import SCALE, PointAvatarModel
from headforge.head.pose import FLIP
from headforge.render.camera import Cameras


@torch.no_grad()
def canonical_sheet(avatar: PointAvatarModel, K: torch.Tensor, resolution: int) -> torch.Tensor:
    """(2 * res, 3 * res, 3) image: rows front / left side, columns albedo | normal | shading of
    the canonical cloud (the head model's canonical pose x_o), 0.6 m in front of ``K``."""
    c = avatar.canonical(False)
    x_o = c.q * SCALE + avatar.centre + c.O
    K = K.to(x_o)  # the avatar's device
    n = torch.nn.functional.normalize(c.grad, dim=-1)
    shading = avatar.shading_net(n) if avatar.shading_net is not None else torch.ones_like(n) * 0.5
    rows = []
    for yaw in (0.0, 90.0):
        a = math.radians(yaw)
        R = x_o.new_tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        p = (x_o - avatar.centre) @ R.T * x_o.new_tensor(FLIP) + x_o.new_tensor([0.0, 0.0, 0.6])
        cams = Cameras.at_origin(K[None], 1, resolution)
        radius = K[0, 0] * avatar.radius / p[:, 2].clamp(min=1e-3)
        tiles = []
        for colour in (c.albedo, 0.5 + 0.5 * n @ R.T, shading):
            img = avatar.splat(cams, p[None], colour[None], radius[None], (n @ R.T * n.new_tensor(FLIP))[None])
            tiles.append(img.features[0] + (1 - img.mask[0, ..., None]))
        rows.append(torch.cat(tiles, 1))
    return torch.cat(rows, 0).clamp(0, 1)


def write_pictures(avatar: PointAvatarModel, train, config, state: dict, run: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from headforge.render.io import write_png

    write_png(run / "canonical_points.png", canonical_sheet(avatar, train.K, config.resolution).cpu())
    history = np.array(state.get("points", []), dtype=float).reshape(-1, 3)
    fig, ax = plt.subplots(figsize=(5, 3.2))
    steps = np.concatenate([[0], history[:, 0]])
    counts = np.concatenate([[config.init_points], history[:, 1]])
    ax.step(steps, counts, where="post")
    ax.set(xlabel="iteration", ylabel="points", yscale="log", title="canonical points (prune, then double)")
    fig.tight_layout()
    fig.savefig(run / "points.png", dpi=100)
    plt.close(fig)
