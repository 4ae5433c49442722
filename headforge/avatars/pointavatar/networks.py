"""PointAvatar's three MLPs (paper supp. Fig. 3): the canonical network (point -> SDF + albedo),
the deformer (point -> canonical offset, expression blendshapes, pose correctives, skinning
weights) and the shading network (deformed normal -> shading).

All take canonical points in the avatar's normalised frame ``q = (x - centre) / scale`` (unit-less,
about [-1, 1] over the head); outputs are documented per network.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn.utils.parametrizations import weight_norm


def positional_encoding(q: torch.Tensor, frequencies: int) -> torch.Tensor:
    """(N, 3) -> (N, 3 + 6 * frequencies): q, then sin / cos of 2^k q (NeRF's encoding)."""
    if frequencies == 0:
        return q
    scales = 2.0 ** torch.arange(frequencies, dtype=q.dtype, device=q.device)
    x = (q[..., None, :] * scales[:, None]).reshape(*q.shape[:-1], -1)
    return torch.cat([q, torch.sin(x), torch.cos(x)], -1)


def _linear(n_in: int, n_out: int, norm: bool) -> nn.Module:
    lin = nn.Linear(n_in, n_out)
    return weight_norm(lin) if norm else lin


class CanonicalNet(nn.Module):
    """MLP_c (Eq. 3): q (N, 3) -> (sdf (N,), albedo (N, 3) in (0, 1)). Softplus(beta=100) layers
    with a skip connection, geometric initialisation to the SDF of a sphere of radius
    ``init_radius`` (normalised units), so training starts from a consistent field."""

    def __init__(self, width: int, layers: int, skip: int, frequencies: int, init_radius: float, norm: bool = True):
        super().__init__()
        self.frequencies, self.skip = frequencies, skip
        d_in = 3 + 6 * frequencies
        dims = [d_in] + [width] * layers + [1 + 3]
        self.layers = nn.ModuleList()
        for i in range(len(dims) - 1):
            n_out = dims[i + 1] - (d_in if i + 1 == skip else 0)
            lin = nn.Linear(dims[i], n_out)
            # geometric init (SAL / IDR): the network starts as |q| - init_radius
            if i == len(dims) - 2:
                nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(dims[i]), std=1e-4)
                nn.init.constant_(lin.bias, -init_radius)
            elif i == 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.constant_(lin.weight[:, 3:], 0.0)
                nn.init.normal_(lin.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(n_out))
            elif i == skip:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(n_out))
                nn.init.constant_(lin.weight[:, -(d_in - 3):], 0.0)
            else:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(n_out))
            self.layers.append(weight_norm(lin) if norm else lin)
        self.act = nn.Softplus(beta=100)

    def forward(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = inp = positional_encoding(q, self.frequencies)
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                x = torch.cat([x, inp], -1) / math.sqrt(2)
            x = layer(x)
            if i < len(self.layers) - 1:
                x = self.act(x)
        return x[:, 0], torch.sigmoid(10 * x[:, 1:])

    def sdf_and_normal(self, q: torch.Tensor, create_graph: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sdf (N,), gradient (N, 3) in normalised units, albedo (N, 3)) at ``q``; the gradient
        is differentiable itself when ``create_graph`` (the Eikonal term, shading's normals)."""
        with torch.enable_grad():
            q = q if q.requires_grad else q.detach().requires_grad_(True)
            sdf, albedo = self(q)
            # retain: albedo shares the forward, and a loss may still backpropagate through it
            grad, = torch.autograd.grad(sdf.sum(), q, create_graph=create_graph, retain_graph=True)
        return sdf, grad, albedo


class Deformer(nn.Module):
    """MLP_d (Eq. 4-5) on normalised points q (N, 3): a body to a hidden code h (N, width), and
    linear heads from h to the canonical offset O (N, 3, metres), the expression blendshapes E
    (N, n_expr, 3) and pose correctives P (N, n_pose, 3) (metres per unit coefficient), and through
    one more layer the skinning weights W (N, n_bones), summing to one (softmax of 20x the
    logits, as the authors' code). The heads start at zero: no offset, no blendshapes, equal
    weights -- the head-model regulariser pulls them to the nearest vertex's.

    E and P are linear in h, so a frame's blendshape offset ``sum_k psi_k E_k`` is h times the
    heads' weights contracted with psi first (:meth:`blend_matrices`): the per-point (N, n_expr, 3)
    tensors are only formed for the regulariser, never per frame."""

    BLEND_SCALE = 1e-3  # blendshape outputs in mm per unit coefficient: O(1) for the network
    OFFSET_SCALE = 1e-2  # canonical offsets in cm

    def __init__(self, width: int, layers: int, n_expr: int, n_pose: int, n_bones: int, norm: bool = True,
                 offset: bool = True):
        super().__init__()
        self.n_expr, self.n_pose, self.use_offset = n_expr, n_pose, offset
        dims = [3] + [width] * layers
        self.body = nn.ModuleList(_linear(dims[i], dims[i + 1], norm) for i in range(layers))
        self.expr = nn.Linear(width, 3 * n_expr)  # row k * 3 + c: coordinate c of blendshape k
        self.pose = nn.Linear(width, 3 * n_pose)
        self.offset = nn.Linear(width, 3)
        self.skin_hidden = _linear(width, width, norm)
        self.skin = nn.Linear(width, n_bones)
        for lin in (self.expr, self.pose, self.offset, self.skin):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)
        self.act = nn.Softplus(beta=100)

    def forward(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(h (N, width), W (N, n_bones), O (N, 3) metres)."""
        h = q
        for layer in self.body:
            h = self.act(layer(h))
        W = torch.softmax(20 * self.skin(self.act(self.skin_hidden(h))), -1)
        O = self.offset(h) * self.OFFSET_SCALE if self.use_offset else torch.zeros_like(q)
        return h, W, O

    def blendshapes(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """E (N, n_expr, 3) and P (N, n_pose, 3), metres per unit coefficient."""
        N = h.shape[0]
        return (self.expr(h) * self.BLEND_SCALE).reshape(N, self.n_expr, 3), \
            (self.pose(h) * self.BLEND_SCALE).reshape(N, self.n_pose, 3)

    def blend_matrices(self, expr: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For coefficients expr (B, n_expr) and pose features pose (B, n_pose): G (B, 3, width)
        and g (B, 3) with ``sum_k expr_k E_k + sum_l pose_l P_l = h @ G^T + g`` per point."""
        width = self.expr.weight.shape[1]
        G = (expr @ self.expr.weight.reshape(self.n_expr, 3 * width)
             + pose @ self.pose.weight.reshape(self.n_pose, 3 * width)).reshape(-1, 3, width)
        g = expr @ self.expr.bias.reshape(self.n_expr, 3) + pose @ self.pose.bias.reshape(self.n_pose, 3)
        return G * self.BLEND_SCALE, g * self.BLEND_SCALE


class AlbedoNet(nn.Module):
    """A separate albedo MLP (headforge's deviation, docs/pointavatar.md): q (N, 3) -> albedo (N, 3)
    in (0, 1), sigmoid(10 x) as the canonical network's albedo output. Its own positional encoding
    can go finer than the SDF's (``frequencies`` octaves: the finest period 2 pi / 2^(frequencies - 1)
    normalised units, 7 mm at 8) without making the SDF's normals noisy, and it needs no gradient
    with respect to q, so it costs a plain forward and backward (no double backward)."""

    def __init__(self, width: int, layers: int, frequencies: int, norm: bool = True):
        super().__init__()
        self.frequencies = frequencies
        dims = [3 + 6 * frequencies] + [width] * layers + [3]
        self.layers = nn.ModuleList(_linear(dims[i], dims[i + 1], norm) for i in range(len(dims) - 1))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        x = positional_encoding(q, self.frequencies)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = torch.relu(x)
        return torch.sigmoid(10 * x)


class MouthAlbedoNet(nn.Module):
    """Beyond the paper (headforge's deviation 19, docs/pointavatar.md): a frame-dependent change
    of the albedo near the mouth. (q (N, 3), cond (B, n_cond)) -> delta (B, N, 3) in (-1, 1),
    added to the albedo before shading: a point in the canonical mouth's opening is lip when the
    mouth closes over it and tongue, teeth or a dark cavity when it opens, which one static
    albedo per point cannot be. ``cond`` is the frame's expression relative to the canonical one
    and its jaw rotation. The last layer starts at zero: no change until the images ask for one."""

    def __init__(self, width: int, layers: int, frequencies: int, n_cond: int, norm: bool = True):
        super().__init__()
        self.frequencies = frequencies
        dims = [3 + 6 * frequencies + n_cond] + [width] * layers + [3]
        self.layers = nn.ModuleList(_linear(dims[i], dims[i + 1], norm and i < layers) for i in range(len(dims) - 1))
        nn.init.zeros_(self.layers[-1].weight)
        nn.init.zeros_(self.layers[-1].bias)

    def forward(self, q: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        pe = positional_encoding(q, self.frequencies)
        x = torch.cat([pe.expand(cond.shape[0], -1, -1), cond[:, None].expand(-1, q.shape[0], -1)], -1)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = torch.relu(x)
        return torch.tanh(x)


class ShadingNet(nn.Module):
    """MLP_s (Eq. 8): a unit normal n (..., 3) in the deformed (posed head) frame -> shading
    (..., 3) in (0, 1); the colour is albedo x shading x 2 (the authors' scale, so a mid shading
    leaves the albedo as is). With ``in_dim`` 6 (normal, albedo features) it is the entangled
    colour network of the paper's ablation (Fig. 6, column 1)."""

    def __init__(self, width: int, layers: int, norm: bool = True, in_dim: int = 3):
        super().__init__()
        dims = [in_dim] + [width] * layers + [3]
        self.layers = nn.ModuleList(_linear(dims[i], dims[i + 1], norm) for i in range(len(dims) - 1))

    def forward(self, n: torch.Tensor) -> torch.Tensor:
        x = n
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = torch.relu(x)
        return torch.sigmoid(x)
