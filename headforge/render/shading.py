"""Shading from normals: Lambert and 2nd-order spherical-harmonics lighting."""

from __future__ import annotations

import math

import torch


def lambert(normals: torch.Tensor, albedo: torch.Tensor, light_dir, ambient: float = 0.3) -> torch.Tensor:
    """albedo * (ambient + (1 - ambient) * max(0, n . l)); ``light_dir`` points toward the light.

    normals: (..., 3) unit; albedo: (..., C) or broadcastable.
    """
    light = torch.nn.functional.normalize(torch.as_tensor(light_dir, dtype=normals.dtype, device=normals.device), dim=-1)
    diffuse = (normals * light).sum(-1, keepdim=True).clamp(min=0)
    return albedo * (ambient + (1 - ambient) * diffuse)


def sh_basis(normals: torch.Tensor) -> torch.Tensor:
    """Real SH basis up to order 2 (9 values) at unit normals (..., 3), with the
    Lambertian convolution folded in (Ramamoorthi & Hanrahan 2001), so that
    ``sh_basis(n) @ coeffs`` is the irradiance for lighting ``coeffs`` (9, C)."""
    x, y, z = normals.unbind(-1)
    a0, a1, a2 = math.pi, 2 * math.pi / 3, math.pi / 4
    c0, c1 = 0.282095, 0.488603
    c2, c3, c4 = 1.092548, 0.315392, 0.546274
    return torch.stack([
        a0 * c0 * torch.ones_like(x),
        a1 * c1 * y, a1 * c1 * z, a1 * c1 * x,
        a2 * c2 * x * y, a2 * c2 * y * z, a2 * c3 * (3 * z * z - 1), a2 * c2 * x * z, a2 * c4 * (x * x - y * y),
    ], -1)


def sh_shading(normals: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Irradiance (..., C) for SH lighting ``coeffs`` (9, C) or (B, 9, C) at normals (B, ..., 3)."""
    basis = sh_basis(normals)
    if coeffs.ndim == 2:
        return basis @ coeffs
    B = coeffs.shape[0]
    flat = basis.reshape(B, -1, 9)
    return (flat @ coeffs).reshape(*basis.shape[:-1], coeffs.shape[-1])


def constant_sh(intensity: float = 1.0, channels: int = 3) -> torch.Tensor:
    """(9, C) SH coefficients of a uniform environment giving irradiance ``intensity``."""
    coeffs = torch.zeros(9, channels)
    coeffs[0] = intensity / (math.pi * 0.282095)
    return coeffs


def parse_light(text: str) -> dict:
    """A light given on the command line: ``X,Y,Z`` (a direction toward the light: Lambert),
    ``rotate:DEGREES`` (the learned shading's normals turned about the vertical axis: a
    light-direction change), or the path of a text/JSON file with 9 x 3 SH coefficients. Axes are
    the head's: x to the subject's left, y up, z toward the camera."""
    import json
    from pathlib import Path

    from headforge.errors import HeadforgeError

    text = text.strip()
    if text.startswith("rotate:"):
        try:
            degrees = float(text.split(":", 1)[1])
        except ValueError:
            raise HeadforgeError(f"--light {text!r}: rotate:DEGREES needs a number") from None
        a = math.radians(degrees)
        R = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
        return {"rotate": R}
    path = Path(text)
    if path.is_file():
        try:
            raw = path.read_text()
            values = json.loads(raw) if raw.lstrip().startswith(("[", "{")) else [float(v) for v in raw.replace(",", " ").split()]
            coeffs = torch.tensor(values, dtype=torch.float32).reshape(9, 3)
        except (ValueError, RuntimeError, TypeError):
            raise HeadforgeError(f"--light {path}: expected 9 x 3 SH coefficients (27 numbers)") from None
        return {"sh": coeffs}
    try:
        direction = [float(v) for v in text.split(",")]
    except ValueError:
        direction = []
    if len(direction) != 3 or not any(direction):
        raise HeadforgeError(f"--light {text!r} is not a direction X,Y,Z (non-zero), rotate:DEGREES or an SH file")
    return {"direction": torch.tensor(direction)}
