"""The training set of HeadCraft's generative model (A.2): baked displacement maps of a
registered scan set, the face part of every expression map replaced by the same person's
neutral map, split by identity.

A map folder is the output of ``headforge craft register`` (``MAPS/<key>/map.png`` +
``params.json``) or a flat folder of ``<key>.png`` maps. Keys name identities as
``<identity>[_<anything>]``: ``id004`` is the neutral scan of ``id004``, ``id004_expr`` one of
its expression scans (the names ``headforge craft scans`` writes).

Maps are (H, W, 3) displacements in metres in canonical axes (x right, y up, z toward the face),
row 0 is v = 1 (see :mod:`headforge.craft.uvmap`). Models see them divided by
:data:`SCALE_M` (2 cm, the paper's "typically ±2 units" in metres), as (N, 3, H, W) float32.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from headforge.craft import uvmap
from headforge.errors import HeadforgeError

SCALE_M = 0.02  # model units: displacement / SCALE_M


@dataclass
class MapItem:
    key: str
    identity: str
    path: Path
    params: dict | None  # head model parameters of the registration (shape, expression, jaw_pose)
    head_model: str | None = None
    levels: int | None = None


@dataclass
class MapSet:
    """Maps (N, H, W, 3) metres, their items, and the layout's texel islands at that size."""

    maps: np.ndarray
    items: list[MapItem]
    head_model: str
    levels: int
    face_replaced: list[str] = field(default_factory=list)

    @property
    def size(self) -> int:
        return int(self.maps.shape[1])

    @property
    def keys(self) -> list[str]:
        return [it.key for it in self.items]


def identity_of(key: str) -> str:
    return key.split("_")[0]


def list_maps(folder: str | Path) -> list[MapItem]:
    """Every map of a folder (registered item folders or flat PNGs), sorted by key."""
    folder = Path(folder)
    if not folder.is_dir():
        raise HeadforgeError(f"no map folder at {folder}")
    items = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith((".", "_")) or p.name.endswith(".partial") or ".partial." in p.name:
            continue
        if p.is_dir() and (p / "map.png").is_file():
            params, head_model, levels = None, None, None
            if (p / "params.json").is_file():
                meta = json.loads((p / "params.json").read_text())
                params = meta.get("params")
                head_model, levels = meta.get("head_model"), meta.get("levels")
            items.append(MapItem(p.name, identity_of(p.name), p / "map.png", params, head_model, levels))
        elif p.is_file() and p.suffix.lower() == ".png" and not p.stem.endswith("_mask"):
            items.append(MapItem(p.stem, identity_of(p.stem), p, None))
    if not items:
        raise HeadforgeError(f"{folder} holds no displacement maps (MAPS/<key>/map.png from headforge craft register, "
                             "or <key>.png)")
    return items


def _read_checked(items: list[MapItem]) -> np.ndarray:
    """Read every map; one line naming the first map whose size or dtype differs."""
    import cv2

    first = None
    out = []
    for it in items:
        img = cv2.imread(str(it.path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise HeadforgeError(f"cannot read map {it.path}")
        sig = (img.shape, str(img.dtype))
        if first is None:
            first = (it.key, sig)
        elif sig != first[1]:
            raise HeadforgeError(f"maps differ in size or dtype: {first[0]} is {first[1][0]} {first[1][1]}, "
                                 f"{it.key} is {sig[0]} {sig[1]} (register them with one --map-size)")
        out.append(uvmap.read_map(it.path))
    return np.stack(out)


def load_maps(folder: str | Path, size: int | None = None, head_model: str | None = None) -> MapSet:
    """Read, check and (``size`` given) resample every map of a folder; then apply A.2's face
    replacement. Item folders must agree on head model and subdivision level."""
    items = list_maps(folder)
    maps = _read_checked(items)
    models = {it.head_model for it in items if it.head_model}
    levels = {it.levels for it in items if it.levels is not None}
    if len(models) > 1 or len(levels) > 1:
        raise HeadforgeError(f"maps of {folder} come from different head models or subdivisions: {sorted(models)} {sorted(levels)}")
    hm = models.pop() if models else (head_model or "open-head")
    if head_model and hm != head_model:
        raise HeadforgeError(f"maps of {folder} were registered on {hm}, not {head_model}")
    lv = levels.pop() if levels else 1
    if size is not None and size != maps.shape[1]:
        maps = resample(maps, size)
    ms = MapSet(maps, items, hm, lv)
    replace_faces(ms)
    return ms


def resample(maps: np.ndarray, size: int) -> np.ndarray:
    """(N, H, W, 3) -> (N, size, size, 3): area averaging down, bilinear up."""
    t = torch.as_tensor(maps).permute(0, 3, 1, 2)
    if size < maps.shape[1]:
        t = torch.nn.functional.interpolate(t, size=(size, size), mode="area")
    else:
        t = torch.nn.functional.interpolate(t, size=(size, size), mode="bilinear", align_corners=False)
    return t.permute(0, 2, 3, 1).numpy()


def face_texels(head_model: str, levels: int, size: int) -> np.ndarray:
    """(size, size) bool: texels of the face island (island 1) of the layout."""
    return texel_islands(head_model, levels, size) == 1


def texel_islands(head_model: str, levels: int, size: int, flame_dir: str | None = None) -> np.ndarray:
    from headforge.craft.pipeline import template_for

    _, duv = template_for(head_model, levels, flame_dir)
    return uvmap.texel_islands(duv, size)


def replace_faces(ms: MapSet) -> None:
    """A.2: the face island of every non-neutral map takes the neutral map of the same identity
    (a key equal to its identity). Identities without a neutral map keep their own face."""
    neutral = {it.key: i for i, it in enumerate(ms.items) if it.key == it.identity}
    face = face_texels(ms.head_model, ms.levels, ms.size)
    # the seam texels of the face side too: dilate by one texel so the face border is replaced whole
    from scipy.ndimage import binary_dilation

    face = binary_dilation(face, iterations=1) & (texel_islands(ms.head_model, ms.levels, ms.size) != 0)
    for i, it in enumerate(ms.items):
        j = neutral.get(it.identity)
        if j is not None and j != i:
            ms.maps[i][face] = ms.maps[j][face]
            ms.face_replaced.append(it.key)


def split_by_identity(items: list[MapItem], holdout: float, seed: int) -> tuple[list[int], list[int]]:
    """(train, held-out) item indices; whole identities go to one side."""
    if not 0 <= holdout < 1:
        raise HeadforgeError(f"--holdout must be within [0, 1), got {holdout}")
    ids = sorted({it.identity for it in items})
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(ids))
    n_out = int(round(holdout * len(ids)))
    if n_out >= len(ids):
        n_out = len(ids) - 1
    held = {ids[k] for k in order[:n_out]}
    train = [i for i, it in enumerate(items) if it.identity not in held]
    out = [i for i, it in enumerate(items) if it.identity in held]
    return train, out


def to_model(maps: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) metres -> (N, 3, H, W) float32 model units."""
    return torch.as_tensor(np.asarray(maps) / SCALE_M, dtype=torch.float32).permute(0, 3, 1, 2).contiguous()


def from_model(x: torch.Tensor) -> np.ndarray:
    """(N, 3, H, W) model units -> (N, H, W, 3) float64 metres."""
    return (x.detach().double().cpu().permute(0, 2, 3, 1) * SCALE_M).numpy()


def shape_stats(items: list[MapItem]) -> dict:
    """Per-dimension mean and std of the registrations' head model parameters: identity over
    one scan per identity, expression and jaw over all scans (the paper samples FLAMEs from
    statistics of a dataset). Empty when no item has parameters."""
    with_params = [it for it in items if it.params]
    if not with_params:
        return {}
    per_id = {}
    for it in with_params:
        per_id.setdefault(it.identity, it)
    out = {}
    shapes = np.array([np.ravel(it.params["shape"]) for it in per_id.values()])
    out["shape"] = (shapes.mean(0).tolist(), shapes.std(0).tolist())
    for key in ("expression", "jaw_pose"):
        vals = np.array([np.ravel(it.params[key]) for it in with_params if key in it.params])
        if len(vals):
            out[key] = (vals.mean(0).tolist(), vals.std(0).tolist())
    return out
