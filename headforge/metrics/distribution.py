"""Point-cloud distribution metrics with PointFlow's definitions (Yang et al. 2019), used by
HeadCraft: MMD-CD, COV-CD, 1-NNA-CD and JSD of voxel occupancy.

Sets are lists/arrays of clouds (S, N, 3), normalised the same way by the caller.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from headforge.errors import HeadforgeError


def pairwise_chamfer(set_a, set_b) -> np.ndarray:
    """(len(a), len(b)) Chamfer distances (mean squared NN distance, both directions)."""
    trees_b = [cKDTree(b) for b in set_b]
    trees_a = [cKDTree(a) for a in set_a]
    out = np.zeros((len(set_a), len(set_b)))
    for i, a in enumerate(set_a):
        for j, b in enumerate(set_b):
            out[i, j] = (trees_b[j].query(a)[0] ** 2).mean() + (trees_a[i].query(b)[0] ** 2).mean()
    return out


def mmd_cov_1nna(generated, reference) -> dict:
    """MMD-CD (mean over reference clouds of the closest generated cloud's Chamfer distance),
    COV-CD (fraction of reference clouds that are the nearest reference of some generated
    cloud) and 1-NNA-CD (leave-one-out 1-NN accuracy telling the two sets apart; 0.5 is ideal)."""
    if len(generated) < 1 or len(reference) < 1:
        raise HeadforgeError("both point-cloud sets must be non-empty")
    gr = pairwise_chamfer(generated, reference)  # (G, R)
    mmd = float(gr.min(axis=0).mean())
    cov = float(len(np.unique(gr.argmin(axis=1))) / len(reference))
    gg = pairwise_chamfer(generated, generated)
    rr = pairwise_chamfer(reference, reference)
    np.fill_diagonal(gg, np.inf)
    np.fill_diagonal(rr, np.inf)
    # for each sample, is its nearest neighbour (excluding itself) from the same set?
    g_correct = gg.min(axis=1) < gr.min(axis=1)
    r_correct = rr.min(axis=1) < gr.min(axis=0)
    nna = float((g_correct.sum() + r_correct.sum()) / (len(generated) + len(reference)))
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
