"""A small planner on the occupancy map: cheapest voxel path weighted by the risk of collision,
then the free-path probability of its straight segments from the field (``free_path``).

Edge cost from voxel a to its 6-neighbour b (voxel size h):

    c(a, b) = h * (1 + risk_weight * (-log(1 - P_b)))

so the path trades length for ``-sum log(1 - P)`` (the log-probability that every voxel it enters
is free, treating voxels as independent). Voxels outside the region (unknown) cannot be entered.
Shortest paths by Dijkstra (``scipy.sparse.csgraph``), then the voxel chain is shortened into
straight segments whose every voxel has P below ``simplify_max_probability``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .occupancy_map import OccupancyMap

#: Probabilities are clipped below 1 by this much before taking log(1 - P).
PLAN_PROBABILITY_CLIP: float = 1e-6
#: Default weight of the risk term against path length.
PLAN_RISK_WEIGHT: float = 10.0


def plan_voxel_path(occ: OccupancyMap, start: np.ndarray, goal: np.ndarray, *,
                    risk_weight: float = PLAN_RISK_WEIGHT) -> tuple[np.ndarray, float]:
    """(voxel indices [M, 3] from start to goal, the path's sum of -log(1 - P)).

    ``start``/``goal``: world points [3] inside known voxels. ValueError when either is outside the
    grid or region, or when no path exists."""
    X, Y, Z = occ.shape
    p = np.clip(occ.dense(unknown=np.nan).astype(np.float64), 0.0, 1.0 - PLAN_PROBABILITY_CLIP)
    known = occ.inside_region
    risk = -np.log1p(-np.nan_to_num(p, nan=0.0))  # [X, Y, Z]
    idx = np.arange(X * Y * Z).reshape(occ.shape)
    rows, cols, w = [], [], []
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        ok = known[tuple(a)] & known[tuple(b)]
        ia, ib = idx[tuple(a)][ok], idx[tuple(b)][ok]
        ra, rb = risk[tuple(a)][ok], risk[tuple(b)][ok]
        rows += [ia, ib]
        cols += [ib, ia]
        w += [occ.voxel_size * (1 + risk_weight * rb), occ.voxel_size * (1 + risk_weight * ra)]
    graph = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(X * Y * Z,) * 2).tocsr()
    ends = []
    for name, pt in (("start", start), ("goal", goal)):
        ijk = occ.index_of(np.asarray(pt, np.float64)[None])[0]
        if np.any(ijk < 0) or np.any(ijk >= occ.shape) or not known[tuple(ijk)]:
            raise ValueError(f"plan: {name} {list(map(float, pt))} is outside the known region of the occupancy map")
        ends.append(int(idx[tuple(ijk)]))
    dist, pred = dijkstra(graph, directed=True, indices=ends[0], return_predecessors=True)
    if not math.isfinite(dist[ends[1]]):
        raise ValueError("plan: no path between start and goal through known voxels")
    chain = [ends[1]]
    while chain[-1] != ends[0]:
        chain.append(int(pred[chain[-1]]))
    chain = np.asarray(chain[::-1])
    vox = np.stack(np.unravel_index(chain, occ.shape), axis=-1)
    return vox, float(risk[tuple(vox.T)].sum())


def simplify_voxel_path(occ: OccupancyMap, voxels: np.ndarray, *, max_probability: float = 0.01) -> np.ndarray:
    """World waypoints [W, 3]: greedy shortcuts along the voxel chain [M, 3]. A shortcut from chain
    voxel i to j is kept when every voxel its straight line passes (sampled at a quarter voxel) has
    P <= max(``max_probability``, the largest P of chain voxels i..j): it takes no more risk per
    voxel than the chain it replaces."""
    dense = occ.dense(unknown=1.0)
    centres = occ.origin + (voxels + 0.5) * occ.voxel_size
    out = [centres[0]]
    i = 0
    while i < len(voxels) - 1:
        j = len(voxels) - 1
        while j > i + 1:
            a, b = centres[i], centres[j]
            n = int(np.ceil(np.linalg.norm(b - a) / (0.25 * occ.voxel_size))) + 1
            pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
            ijk = np.clip(occ.index_of(pts), 0, np.asarray(occ.shape) - 1)
            allowed = max(max_probability, float(np.max(dense[tuple(voxels[i:j + 1].T)])))
            if np.all(dense[tuple(ijk.T)] <= allowed):
                break
            j -= 1
        out.append(centres[j])
        i = j
    return np.asarray(out)
