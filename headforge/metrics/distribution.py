"""Point-cloud distribution metrics with PointFlow's definitions (Yang et al. 2019), used by
HeadCraft: MMD-CD, COV-CD, 1-NNA-CD and JSD of voxel occupancy.

Sets are lists/arrays of clouds (S, N, 3), normalised the same way by the caller.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from headforge.errors import HeadforgeError


def pairwise_chamfer(set_a, set_b=None, workers: int = -1) -> np.ndarray:
    """(len(a), len(b)) Chamfer distances (mean squared NN distance, both directions).

    ``set_b`` None: the symmetric (len(a), len(a)) matrix of ``set_a`` against itself, each pair
    computed once (zero diagonal). ``workers``: threads per nearest-neighbour query (-1: all)."""
    trees_a = [cKDTree(a) for a in set_a]
    if set_b is None:
        n = len(set_a)
        out = np.zeros((n, n))
        for i in range(n):
            for j in range(i + 1, n):
                out[i, j] = out[j, i] = _chamfer(set_a[i], trees_a[i], set_a[j], trees_a[j], workers)
        return out
    trees_b = [cKDTree(b) for b in set_b]
    out = np.zeros((len(set_a), len(set_b)))
    for i, a in enumerate(set_a):
        for j, b in enumerate(set_b):
            out[i, j] = _chamfer(a, trees_a[i], b, trees_b[j], workers)
    return out


def _chamfer(a, tree_a, b, tree_b, workers: int) -> float:
    return float((tree_b.query(a, workers=workers)[0] ** 2).mean() + (tree_a.query(b, workers=workers)[0] ** 2).mean())


def mmd_cov_1nna(generated, reference) -> dict:
    """MMD-CD (mean over reference clouds of the closest generated cloud's Chamfer distance),
    COV-CD (fraction of reference clouds that are the nearest reference of some generated
    cloud) and 1-NNA-CD (leave-one-out 1-NN accuracy telling the two sets apart; 0.5 is ideal)."""
    if len(generated) < 1 or len(reference) < 1:
        raise HeadforgeError("both point-cloud sets must be non-empty")
    return mmd_cov_1nna_from(pairwise_chamfer(generated, reference), pairwise_chamfer(generated),
                             pairwise_chamfer(reference))


def mmd_cov_1nna_from(gr: np.ndarray, gg: np.ndarray, rr: np.ndarray, cov_columns=None) -> dict:
    """:func:`mmd_cov_1nna` from the Chamfer matrices generated x reference (G, R), generated x
    generated (G, G) and reference x reference (R, R), so that a caller scoring several generated
    sets against one reference computes ``rr`` once. ``cov_columns``: a boolean (R,) mask of the
    reference clouds that COV counts (each generated cloud matched to its nearest among them;
    HeadCraft: one neutral scan per identity); None: all."""
    gr, gg, rr = np.asarray(gr, float), np.array(gg, float), np.array(rr, float)
    if gr.shape != (len(gg), len(rr)) or gg.shape[0] != gg.shape[1] or rr.shape[0] != rr.shape[1]:
        raise HeadforgeError(f"Chamfer matrices of mismatched shapes: {gr.shape}, {gg.shape}, {rr.shape}")
    mmd = float(gr.min(axis=0).mean())
    cols = np.ones(gr.shape[1], bool) if cov_columns is None else np.asarray(cov_columns, bool)
    if not cols.any():
        raise HeadforgeError("COV needs at least one reference cloud")
    cov = float(len(np.unique(gr[:, cols].argmin(axis=1))) / cols.sum())
    np.fill_diagonal(gg, np.inf)
    np.fill_diagonal(rr, np.inf)
    # for each sample, is its nearest neighbour (excluding itself) from the same set?
    g_correct = gg.min(axis=1) < gr.min(axis=1)
    r_correct = rr.min(axis=1) < gr.min(axis=0)
    nna = float((g_correct.sum() + r_correct.sum()) / (len(gg) + len(rr)))
    return {"mmd_cd": mmd, "cov_cd": cov, "1nna_cd": nna}


def occupancy(clouds, resolution: int = 28, bound: float = 0.5) -> np.ndarray:
    """Counts of points per voxel of a resolution^3 grid over [-bound, bound]^3, summed over
    the clouds (PointFlow's grid for JSD)."""
    grid = np.zeros((resolution,) * 3)
    for cloud in clouds:
        idx = np.floor((np.asarray(cloud) + bound) / (2 * bound) * resolution).astype(int)
        idx = idx[((idx >= 0) & (idx < resolution)).all(1)]
        np.add.at(grid, tuple(idx.T), 1)
    return grid


def jsd(generated, reference, resolution: int = 28, bound: float = 0.5) -> float:
    """Jensen-Shannon divergence (natural log) between the voxel-occupancy distributions."""
    p, q = occupancy(generated, resolution, bound).ravel(), occupancy(reference, resolution, bound).ravel()
    if p.sum() == 0 or q.sum() == 0:
        raise HeadforgeError("no points fall inside the JSD grid: normalise the clouds to the unit cube")
    p, q = p / p.sum(), q / q.sum()
    m = 0.5 * (p + q)

    def kl(a, b):
        nz = a > 0
        return float((a[nz] * np.log(a[nz] / b[nz])).sum())

    return 0.5 * kl(p, m) + 0.5 * kl(q, m)
