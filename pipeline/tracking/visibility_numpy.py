"""The numpy formulations of the edge sampling kernels (:func:`mst.pipeline.tracking.kernels.edge_samples`,
:func:`~mst.pipeline.tracking.kernels.candidate_edges`, :func:`~mst.pipeline.tracking.kernels.unhidden_samples`,
:func:`~mst.pipeline.tracking.kernels.face_visibility_kernel`): the references of their tests
(``visible_samples(..., _numpy_reference=True)``, :func:`face_visibility_numpy`), kept apart from the
visibility module that runs the kernels. Frames and units as :mod:`mst.pipeline.tracking.visibility`.
"""

from __future__ import annotations

import numpy as np

from mst.pipeline.tracking.depth_buffer import _loops_of, _mat3
from mst.pipeline.tracking.visibility import _clip_near_far, _clip_rect


def _edge_samples_numpy(Xv, E, small_face, near, far, K, R, t, x0, y0, x1, y1, step, use_lod, lod_min_line_px):
    """The numpy formulation of :func:`mst.pipeline.tracking.kernels.edge_samples` (the reference of
    its test; the steps of :func:`visible_samples` from the candidate edges to the samples): the
    same outputs to the bit."""
    counts = np.zeros(5, np.int64)
    eid = np.arange(len(E))
    A = Xv[E[:, 0]]
    B = Xv[E[:, 1]]
    behind = (A[:, 2] < near) & (B[:, 2] < near)
    counts[0] = int(behind.sum())
    front = ~behind
    z_min = float(np.minimum(A[front, 2], B[front, 2]).min()) if front.any() else np.nan
    A, B, keep, _, _ = _clip_near_far(A, B, near, far)
    counts[1] = int((~keep & ~behind).sum())
    A, B, small_face, eid = A[keep], B[keep], small_face[keep], eid[keep]
    ua = _mat3(A, K)
    ua = ua[:, :2] / ua[:, 2:3]
    ub = _mat3(B, K)
    ub = ub[:, :2] / ub[:, 2:3]
    if use_lod:
        big = ~small_face & (np.linalg.norm(ub - ua, axis=1) >= lod_min_line_px)
        counts[2] = int((~big).sum())
        A, B, ua, ub, eid = A[big], B[big], ua[big], ub[big], eid[big]
    s0, s1, k2 = _clip_rect(ua, ub, x0, y0, x1, y1)
    counts[3] = int((~k2).sum())
    A, B, ua, ub, s0, s1, eid = A[k2], B[k2], ua[k2], ub[k2], s0[k2], s1[k2], eid[k2]
    izA, izB = 1.0 / A[:, 2], 1.0 / B[:, 2]
    # clipped 2D endpoints and their inverse depths (1/z is affine along the projected segment)
    d2 = ub - ua
    pa = ua + s0[:, None] * d2
    pb = ua + s1[:, None] * d2
    iza = izA + s0 * (izB - izA)
    izb = izA + s1 * (izB - izA)
    L = np.linalg.norm(pb - pa, axis=1)
    n_s = np.floor(L / step).astype(np.int64)
    good = n_s >= 1
    counts[4] = int((~good).sum())
    pa, pb, iza, izb, L, n_s, eid = pa[good], pb[good], iza[good], izb[good], L[good], n_s[good], eid[good]
    Ka = (pa - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Kb = (pb - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Ac = np.column_stack([Ka, np.ones(len(Ka))]) / iza[:, None]  # camera-frame clipped endpoints
    Bc = np.column_stack([Kb, np.ones(len(Kb))]) / izb[:, None]
    A_model = _mat3(Ac - t, R.T)
    B_model = _mat3(Bc - t, R.T)
    edge_id = np.repeat(np.arange(len(n_s)), n_s)
    start = np.concatenate([[0], np.cumsum(n_s)[:-1]]) if len(n_s) else np.zeros(0, np.int64)
    j = np.arange(len(edge_id)) - np.repeat(start, n_s)
    s = (j + 0.5) / np.repeat(n_s, n_s)
    d = (pb - pa)[edge_id]
    uv = pa[edge_id] + s[:, None] * d
    iz = iza[edge_id] + s * (izb - iza)[edge_id]
    tang = (pb - pa) / np.maximum(L, 1e-9)[:, None]
    nrm = np.column_stack([-tang[:, 1], tang[:, 0]])[edge_id]
    xn = (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    Xc = np.column_stack([xn, np.ones(len(xn))]) / iz[:, None]
    return counts, z_min, eid, pa, pb, A_model, B_model, uv, nrm, iz, Xc, edge_id


def _candidate_edges_numpy(edges, edge_faces, e_sel, fv, fv_big):
    """The numpy formulation of :func:`mst.pipeline.tracking.kernels.candidate_edges` (its test's
    reference): ``(eid, E, small_face)`` of the edges ``e_sel`` with an adjacent face in ``fv``, and
    the free lines."""
    ef = edge_faces[e_sel]
    ev = ((ef[:, 0] >= 0) & fv[np.maximum(ef[:, 0], 0)]) | ((ef[:, 1] >= 0) & fv[np.maximum(ef[:, 1], 0)])
    ev |= (ef[:, 0] < 0) & (ef[:, 1] < 0)  # free lines: always candidates
    ev_big = ((ef[:, 0] >= 0) & fv_big[np.maximum(ef[:, 0], 0)]) | ((ef[:, 1] >= 0) & fv_big[np.maximum(ef[:, 1], 0)])
    ev_big |= (ef[:, 0] < 0) & (ef[:, 1] < 0)
    eid = e_sel[ev]
    return eid, edges[eid], ~ev_big[ev]


def _unhidden_samples_numpy(far_nb, uv, iz, sc, nrm, Xc, edge_id, R, t):
    """The numpy formulation of :func:`mst.pipeline.tracking.kernels.unhidden_samples` on the eroded
    buffer ``far_nb`` (the farthest surface in each 3x3 neighbourhood): ``(n_hidden, uv, nrm, Xc,
    edge_id, X_model)`` of the samples not behind it."""
    ix = np.clip(np.round((uv[:, 0] + 0.5) * sc - 0.5).astype(np.int64), 0, far_nb.shape[1] - 1)
    iy = np.clip(np.round((uv[:, 1] + 0.5) * sc - 0.5).astype(np.int64), 0, far_nb.shape[0] - 1)
    vis = iz >= far_nb[iy, ix] * (1.0 - 2e-3) - 1e-9
    return int((~vis).sum()), uv[vis], nrm[vis], Xc[vis], edge_id[vis], _mat3(Xc[vis] - t, R.T)


def face_visibility_numpy(geom, T_cam_model: np.ndarray, prev: np.ndarray | None, appear_deg: float,
                          disappear_deg: float, among: np.ndarray | None = None) -> np.ndarray:
    """The numpy formulation of :func:`mst.pipeline.tracking.visibility.face_visibility` (the reference of its
    kernel's test): the smallest angle between each selected face's normal and the rays from its outer-loop
    vertices to the camera centre, below ``appear_deg`` (or ``disappear_deg`` for a face visible in ``prev``)."""
    R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
    c_model = -R.T @ t  # camera centre in the model frame
    F = len(geom.faces)
    sel = np.arange(F) if among is None else np.flatnonzero(among)
    vis = np.zeros(F, bool)
    if not len(sel):
        return vis
    vid, start = (geom.loop_vid, geom.loop_start) if among is None else _loops_of(geom, sel)
    ray = c_model[None, :] - geom.vertices[vid]
    ray /= np.maximum(np.sqrt(np.einsum("ij,ij->i", ray, ray)), 1e-12)[:, None]
    fid = np.repeat(sel, np.diff(np.append(start, len(vid))))
    cosv = np.einsum("ij,ij->i", ray, geom.face_normals[fid])
    ang = np.degrees(np.arccos(np.clip(np.maximum.reduceat(cosv, start), -1, 1)))
    v = ang < appear_deg
    if prev is not None and len(prev) == F:
        v |= prev[sel] & (ang < disappear_deg)
    vis[sel] = v
    return vis
