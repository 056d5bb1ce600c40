"""Model edges that show no image edge although only one face owns them: T-junction joints.

:func:`flat_t_junctions` is used once per model by
:meth:`mst.pipeline.tracking.visibility.ModelGeometry.from_model`. Frames and units: model frame,
the model's units (metres for city models); angles in degrees.
"""

from __future__ import annotations

import numpy as np

from mst.pipeline.tracking.exact import dot3


def flat_t_junctions(V: np.ndarray, E: np.ndarray, ef: np.ndarray, N: np.ndarray, crease_deg: float) -> np.ndarray:
    """(E,) bool: one-face edges lying (>= 90 % of their length) on collinear edges of other faces
    that are coplanar with theirs (normals within ``crease_deg``) and face the same way: T-junction joints inside one flat surface
    (adjacent buildings' facades in a city model, split unevenly), which show no image edge.

    Edges are grouped by their supporting line (direction and foot point quantised to 1e-5 of the
    model size); only groups of two or more are compared. Runs once per model."""
    flat = np.zeros(len(E), bool)
    single = (ef[:, 0] >= 0) & (ef[:, 1] < 0)
    if not single.any() or len(E) < 2:
        return flat
    A, B = V[E[:, 0]], V[E[:, 1]]
    d = B - A
    L = np.linalg.norm(d, axis=1)
    ok = (L > 0) & (ef[:, 0] >= 0)
    u = d / np.maximum(L, 1e-300)[:, None]
    # canonical direction sign: first non-zero component positive
    k = np.argmax(np.abs(u) > 1e-9, axis=1)
    sgn = np.sign(u[np.arange(len(u)), k])
    u = u * sgn[:, None]
    foot = A - np.einsum("ij,ij->i", A, u)[:, None] * u
    tol = 1e-5 * (float(np.ptp(V, axis=0).max()) or 1.0)
    key = np.column_stack([np.round(u / 1e-5), np.round(foot / tol)]).astype(np.int64)
    idx = np.flatnonzero(ok)
    _, inv, counts = np.unique(key[idx], axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    if not (counts > 1).any():
        return flat
    order = np.argsort(inv, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(counts)])
    c = np.cos(np.radians(crease_deg))
    for gi in np.flatnonzero(counts > 1):  # few groups: collinear edges of different faces
        g = idx[order[bounds[gi]:bounds[gi + 1]]]
        if not single[g].any():
            continue
        t0 = np.einsum("ij,ij->i", A[g], u[g[0]][None, :])
        t1 = np.einsum("ij,ij->i", B[g], u[g[0]][None, :])
        lo, hi = np.minimum(t0, t1), np.maximum(t0, t1)
        for a in np.flatnonzero(single[g]):
            fa = ef[g[a], 0]
            cov = []
            for b in range(len(g)):
                if b == a:
                    continue
                fb = [f for f in ef[g[b]] if f >= 0 and f != fa and dot3(N[f], N[fa]) > c]
                if fb:
                    s0, s1 = max(lo[a], lo[b]), min(hi[a], hi[b])
                    if s1 > s0:
                        cov.append((s0, s1))
            if cov:  # union length of the covered parts
                cov.sort()
                tot, cur0, cur1 = 0.0, *cov[0]
                for s0, s1 in cov[1:]:
                    if s0 > cur1:
                        tot += cur1 - cur0
                        cur0, cur1 = s0, s1
                    else:
                        cur1 = max(cur1, s1)
                tot += cur1 - cur0
                flat[g[a]] = tot >= 0.9 * (hi[a] - lo[a])
    return flat
