"""How linear is a registered map set? The room a non-linear generator has over PCA.

For the scalp texels (the part HeadCraft's generator models beyond the face), projects every
held-out map onto the top-k principal components of the training maps and reports the RMS
residual per texel (mm) against k, beside the held-out maps' RMS around the training mean and
their distance to the nearest training map. If a few dozen components leave only registration-
level residuals, PCA's span already holds the held-out heads and a generator can win only on how
it samples within it, not on what it can express.

    python benchmarks/craft_map_span.py --train MAPS_TRAIN --held MAPS_HELD [--size 64]

Prints a Markdown table, then one JSON line: ``train_maps``, ``heldout_maps``, ``size``,
``heldout_rms_mm`` (around the training mean), ``heldout_nn_mm`` (median RMS to the nearest
training map), ``residual_mm`` {k: median held-out RMS residual with k components},
``components_for_90pct`` / ``_95pct`` / ``_99pct`` (training variance explained).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from headforge.craft.generative.data import load_maps, texel_islands
from headforge.craft.generative.evaluate import scalp_distances
from headforge.errors import HeadforgeError


def load_with_scalp(folder: str, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Maps (N, size, size, 3) metres, faces replaced (A.2), and the scalp texels (island 0)."""
    ms = load_maps(folder, size)
    return ms.maps, texel_islands(ms.head_model, ms.levels, ms.size) == 0


def span(train_maps: np.ndarray, held_maps: np.ndarray, scalp: np.ndarray, ks: list[int]) -> dict:
    """Residuals (mm, RMS per scalp texel) of the held-out maps' scalp texels after projection on
    the top-k principal directions of the training maps' scalp texels."""
    train = train_maps[:, scalp].reshape(len(train_maps), -1)
    held = held_maps[:, scalp].reshape(len(held_maps), -1)
    texels = scalp.sum()
    mean = train.mean(0)
    _, s, vt = np.linalg.svd(train - mean, full_matrices=False)
    var = np.cumsum(s ** 2) / (s ** 2).sum()
    h = held - mean
    rms = lambda r: np.sqrt((r ** 2).sum(-1) / texels) * 1000  # noqa: E731  (mm per texel)
    residual = {}
    for k in ks:
        k = min(k, len(vt))
        coeff = h @ vt[:k].T
        residual[k] = float(np.median(rms(h - coeff @ vt[:k])))
    nn = scalp_distances(held_maps, train_maps, scalp)[1]
    return {"heldout_rms_mm": float(np.median(rms(h))), "heldout_nn_mm": float(np.median(nn)),
            "residual_mm": residual,
            **{f"components_for_{p}pct": int(np.searchsorted(var, p / 100) + 1) for p in (90, 95, 99)}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", required=True, help="registered training maps (craft register output)")
    ap.add_argument("--held", required=True, help="registered held-out maps of other identities")
    ap.add_argument("--size", type=int, default=64, help="map size the models train at (quick preset: 64)")
    args = ap.parse_args()
    try:
        (train, scalp), (held, _) = load_with_scalp(args.train, args.size), load_with_scalp(args.held, args.size)
    except HeadforgeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    ks = [k for k in (1, 2, 4, 8, 16, 32, 64, 128, 256) if k < len(train)] + [len(train) - 1]
    out = {"train_maps": len(train), "heldout_maps": len(held), "size": args.size, **span(train, held, scalp, ks)}
    print("| components k | held-out scalp RMS residual (mm) |\n| --- | --- |")
    for k, r in out["residual_mm"].items():
        print(f"| {k} | {r:.2f} |")
    print(f"held-out RMS around the training mean {out['heldout_rms_mm']:.2f} mm, to the nearest training map "
          f"{out['heldout_nn_mm']:.2f} mm")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
