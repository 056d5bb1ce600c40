"""Shared cases of the C2M tests: the box building with its analytic signed distance, noisy clouds on
it, the winding number of a closed mesh, brute-force distances (the references the engines must equal)."""

from __future__ import annotations

import numpy as np

from mst.eval import c2m
from mst.meshtools.formats import save_triangles
from mst.meshtools.generate import box

BOX = (4.0, 6.0, 2.0)  # box from (0,0,0) to (4,6,2), outward winding


def box_index(signed=True, engine="bvh", split=2, shift=(0.0, 0.0, 0.0)):
    V, F = box(BOX, split=split)
    return c2m.prepare_mesh(V + np.asarray(shift), F, signed=signed, engine=engine), V, F


def box_sdf(P):
    """Analytic signed distance to the axis-aligned box [0,4]x[0,6]x[0,2] (negative inside)."""
    lo, hi = np.zeros(3), np.array(BOX)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(P - c) - h
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(1), 0)
    return outside + inside


def dist(idx, P, signed=True, max_dist=None):
    d, s = c2m.point_distances(idx, np.asarray(P, float) - idx.shift, signed, max_dist)
    return d, s


def building_case(tmp_path, n=20000, sigma=0.1, seed=0, nonfinite=3):
    """Noisy points on a box building (distances known from the analytic SDF of the noise-free box)."""
    V, F = box(BOX, split=3)
    mesh = tmp_path / "building.obj"
    save_triangles(mesh, V, F)
    rng = np.random.default_rng(seed)
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    ar = np.linalg.norm(np.cross(B - A, C - A), axis=1)
    t = rng.choice(len(F), n, p=ar / ar.sum())
    u = rng.random((n, 2))
    m = u.sum(1) > 1
    u[m] = 1 - u[m]
    P = A[t] + u[:, :1] * (B - A)[t] + u[:, 1:] * (C - A)[t] + rng.normal(0, sigma, (n, 3))
    P[:nonfinite] = [np.nan, np.inf, -np.inf][:nonfinite] if nonfinite else P[:0]
    return mesh, P


def winding_number(P, V, F):
    """Generalised winding number of points w.r.t. a closed mesh (Van Oosterom-Strackee solid angles)."""
    A = V[F[:, 0]][None] - P[:, None]
    B = V[F[:, 1]][None] - P[:, None]
    C = V[F[:, 2]][None] - P[:, None]
    a, b, c = (np.linalg.norm(X, axis=2) for X in (A, B, C))
    num = np.einsum("ijk,ijk->ij", A, np.cross(B, C))
    den = a * b * c + np.einsum("ijk,ijk->ij", A, B) * c + np.einsum("ijk,ijk->ij", B, C) * a \
        + np.einsum("ijk,ijk->ij", C, A) * b
    return (2 * np.arctan2(num, den)).sum(1) / (4 * np.pi)


def brute_force_d2(idx, P):
    """Exact squared distances of shifted points to every triangle (numpy, blockwise): the reference."""
    m = idx.n_triangles
    out = np.empty(len(P))
    for i, p in enumerate(P):
        d2, _, _ = c2m.triangle_distances(idx, np.broadcast_to(p, (m, 3)), np.arange(m))
        out[i] = d2.min()
    return out
