"""Numba kernels of the edge tracker's hot loops (issue #14; compiled once, cached on disk).

* :func:`me_gather` and :func:`me_select`: the moving-edge search of a frame in two passes over all
  its samples: the pixels read along each normal (gathered for the float32 dot products with the
  oriented masks, :func:`mst.pipeline.tracking.exact.masked_conv`: the convolutions, and every decision on them, are those of
  :func:`mst.pipeline.tracking.moving_edges.search_edges_numpy` to the bit), then ViSP's contrast
  and likelihood tests, the polarity vote of each model edge, local maxima, the best candidates and
  their parabolic sub-pixel refinement (float32 where the numpy formulation is float32, thresholds
  rounded to float32 as numpy's weak Python scalars are, float64 elsewhere).
* :func:`vvs_residuals`, :func:`vvs_linearise`: one VVS iteration's residuals at a pose (each
  sample's candidates against its projected model line) and its linearisation (candidate choice,
  Tukey weights on the MAD scale, the edge-spread re-weighting, the point-to-line Jacobian and its
  weighted copy). The rigid transforms (elementwise), ``J^T W J``, ``J^T W r`` and the 6x6 solve
  (:mod:`mst.pipeline.tracking.exact`, no BLAS: the same bits on every CPU) and the costs (numpy's
  pairwise sums) are shared with the numpy formulation, so that the solved poses are its to the bit.
* :func:`sobel_at`: the Sobel gradient at sample positions (the health tests).

No fastmath (reproducible bit for bit), single-threaded (the tracker's one-core budget).
Units: pixels, metres; ``R``, ``t`` the rotation and translation of ``T_cam_model``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

F32 = np.float32


@njit(cache=True, nogil=True, error_model="numpy")
def me_gather(img, uv, normal, ks, moff, patches, k_eff):
    """The mask pixels around ``uv[i] + ks[m] * normal[i]`` (nearest pixel, clipped so that the mask
    stays inside the image) into ``patches[i, m, :]`` (float32, the gray levels), and the signed
    distance ``k_eff[i, m]`` (px) along the normal of the pixel actually read (see
    :func:`~mst.pipeline.tracking.moving_edges.convolve_along`)."""
    H, W = img.shape
    S = moff.shape[0]
    r = 0
    for s in range(S):
        r = max(r, abs(moff[s, 0]), abs(moff[s, 1]))
    hi_x, hi_y = W - 1 - r, H - 1 - r
    for i in range(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        nx, ny = normal[i, 0], normal[i, 1]
        for m in range(ks.shape[0]):
            k = ks[m]
            ix = min(max(np.rint(u + k * nx), r), hi_x)
            iy = min(max(np.rint(v + k * ny), r), hi_y)
            jx, jy = int(ix), int(iy)
            for s in range(S):
                patches[i, m, s] = F32(img[jy + moff[s, 1], jx + moff[s, 0]])
            k_eff[i, m] = (ix - u) * nx + (iy - v) * ny


@njit(cache=True, nogil=True, error_model="numpy")
def me_select(conv, k_eff, ks, R, ref, has_ref, threshold, mu1, mu2, edge, vote, C):
    """The moving-edge decisions on the convolutions ``conv (N, M)`` float32 at offsets ``ks`` (see
    :func:`~mst.pipeline.tracking.moving_edges.search_edges`): ViSP's contrast test against ``ref``
    (N,) float32 (when ``has_ref``) or the likelihood threshold, the polarity vote of each model
    edge (``vote``: ``edge`` (N,) the model edge of each sample), local maxima, the ``C`` best and
    their parabolic sub-pixel refinement at ``k_eff``. Returns ``(offset (N, C) px, NaN none;
    likelihood (N, C) float32; conv (N,) float32 of the best candidate)``.
    """
    N, M = conv.shape
    like = np.empty((N, M), np.float32)
    ok = np.empty((N, M), np.bool_)
    thr = F32(threshold)
    thr2 = F32(2.0 * threshold)
    lo = F32(1.0 - mu1)
    hi = F32(1.0 + mu2)
    two = F32(2.0)
    for i in range(N):
        if has_ref:
            rf = ref[i]
            strong = abs(rf) >= thr
            for m in range(M):
                c = conv[i, m]
                if strong:
                    ratio = c / rf
                    lc = abs(c + rf)
                    like[i, m] = lc
                    ok[i, m] = (ratio > lo) and (ratio < hi) and (lc > thr2)
                else:
                    ln = two * abs(c)
                    like[i, m] = ln
                    ok[i, m] = ln > thr2
        else:
            for m in range(M):
                ln = two * abs(conv[i, m])
                like[i, m] = ln
                ok[i, m] = ln > thr2
    if (not has_ref) and vote and N > 0:
        # polarity of each model edge: the samples' best responses near the prediction, weighted
        prox = np.empty(M)
        sc = max(1.0, 0.5 * R)
        for m in range(M):
            q = ks[m] / sc
            prox[m] = np.exp(-(q * q))
        n_e = 0
        for i in range(N):
            n_e = max(n_e, edge[i] + 1)
        acc = np.zeros(n_e)
        for i in range(N):
            j = 0
            bv = -np.inf
            for m in range(M):
                val = np.float64(like[i, m]) * prox[m] if ok[i, m] else -1.0
                if val > bv:
                    bv = val
                    j = m
            if ok[i, j]:
                cb = conv[i, j]
                sg = F32(1.0) if cb > 0 else (F32(-1.0) if cb < 0 else F32(0.0))
                acc[edge[i]] += np.float64(sg * like[i, j]) * prox[j]
        for i in range(N):
            a = acc[edge[i]]
            pol = 1.0 if a > 0 else (-1.0 if a < 0 else 0.0)
            if pol != 0.0:
                for m in range(M):
                    c = conv[i, m]
                    sg = 1.0 if c > 0 else (-1.0 if c < 0 else 0.0)
                    if sg != pol:
                        ok[i, m] = False
    off = np.empty((N, C))
    lk = np.empty((N, C), np.float32)
    cbest = np.empty(N, np.float32)
    score = np.empty(M, np.float32)
    ninf = F32(-np.inf)
    for i in range(N):
        for m in range(M):
            lm = like[i, m]
            left = like[i, m - 1] if m > 0 else ninf
            right = like[i, m + 1] if m < M - 1 else ninf
            score[m] = lm if (ok[i, m] and lm >= left and lm >= right) else ninf
        for c in range(C):
            t = 0
            for m in range(1, M):
                if score[m] > score[t]:
                    t = m
            ts = score[t]
            score[t] = ninf
            if c == 0:
                cbest[i] = conv[i, t] if np.isfinite(ts) else F32(0.0)
            if not np.isfinite(ts):
                off[i, c] = np.nan
                lk[i, c] = F32(0.0)
                continue
            jl = min(max(t - 1, 0), M - 1)
            if abs(k_eff[i, jl] - k_eff[i, t]) < 1e-6:
                jl = min(max(t - 2, 0), M - 1)
            jr = min(max(t + 1, 0), M - 1)
            if abs(k_eff[i, jr] - k_eff[i, t]) < 1e-6:
                jr = min(max(t + 2, 0), M - 1)
            x0, x1, x2 = k_eff[i, jl], k_eff[i, t], k_eff[i, jr]
            y0, y1, y2 = like[i, jl], like[i, t], like[i, jr]
            den = (x0 - x1) * (x0 - x2) * (x1 - x2)
            a = (x2 * np.float64(y1 - y0) + x1 * np.float64(y0 - y2) + x0 * np.float64(y2 - y1)) / den
            b = (x2 * x2 * np.float64(y0 - y1) + x1 * x1 * np.float64(y2 - y0) + x0 * x0 * np.float64(y1 - y2)) / den
            xv = -b / (2.0 * a)
            if np.isfinite(xv) and a < 0 and x0 < x1 and x1 < x2:
                o = min(max(xv, x1 - 0.5 * (x1 - x0)), x1 + 0.5 * (x2 - x1))
            else:
                o = x1
            off[i, c] = o
            lk[i, c] = ts
    return off, lk, cbest


@njit(cache=True, nogil=True, error_model="numpy")
def vvs_residuals(Xc, P, nE, e, cu, cv, fx, fy, cx, cy, r_all, nx, ny, x, y, iz):
    """Residuals ``r_all (N, C)`` px of every candidate against its sample's projected model line,
    from the samples ``Xc (N, 3)`` and the edge end points ``P (2 nE, 3)`` (A then B) in the camera
    frame (the rigid transform stays numpy's matrix product, so that every value is the numpy
    formulation's to the bit); also the line normals ``nx, ny`` (N,) and the normalised
    coordinates and inverse depth ``x, y, iz`` (N,) of the samples (all outputs filled in place)."""
    lnx = np.empty(nE)
    lny = np.empty(nE)
    for k in range(nE):
        pa_u = fx * P[k, 0] / P[k, 2]
        pa_v = fy * P[k, 1] / P[k, 2]
        pb_u = fx * P[nE + k, 0] / P[nE + k, 2]
        pb_v = fy * P[nE + k, 1] / P[nE + k, 2]
        du = pb_u - pa_u
        dv = pb_v - pa_v
        ln = np.sqrt(du * du + dv * dv) + 1e-12
        lnx[k] = -dv / ln
        lny[k] = du / ln
    C = cu.shape[1]
    for i in range(Xc.shape[0]):
        q = 1.0 / Xc[i, 2]
        xi, yi = Xc[i, 0] * q, Xc[i, 1] * q
        u, v = fx * xi + cx, fy * yi + cy
        a, b = lnx[e[i]], lny[e[i]]
        nx[i], ny[i], x[i], y[i], iz[i] = a, b, xi, yi, q
        for c in range(C):
            r_all[i, c] = (u - cu[i, c]) * a + (v - cv[i, c]) * b


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _median(a):
    """The median of ``a`` (the middle value, or the mean of the two middle values): a selection, so
    exactly :func:`mst.pipeline.tracking.vvs._median`'s value."""
    n = a.shape[0]
    s = np.sort(a)
    h = n // 2
    if n % 2 == 0 and n > 1:
        return 0.5 * (s[h - 1] + s[h])
    return s[h]


@njit(cache=True, nogil=True, error_model="numpy")
def vvs_linearise(r_all, ch, r, w, w_tukey, min_scale, tukey_c, e, nE, spread, spread_k, nx, ny, x, y, iz, fx, fy,
                  J, wJ):
    """One VVS linearisation at the residuals ``r_all`` of :func:`vvs_residuals` (all outputs in
    place): per sample the candidate nearest its model line (``ch``, ``r``; first on ties), Tukey
    weights on the MAD scale floored at ``min_scale`` (``w_tukey``), the edge-spread re-weighting
    (``w``, when ``spread``: an edge whose inlier residuals scatter counts less), the point-to-line
    Jacobian ``J (N, 6)`` and ``wJ = w J``. Returns the robust scale sigma (px). The products
    ``J^T wJ`` and ``wJ^T r`` are :func:`mst.pipeline.tracking.exact.normal_equations`'s."""
    n = r.shape[0]
    C = r_all.shape[1]
    for i in range(n):
        j = 0
        for c in range(1, C):
            if abs(r_all[i, c]) < abs(r_all[i, j]):
                j = c
        ch[i] = j
        r[i] = r_all[i, j]
    sigma = min_scale
    if n:
        med = _median(r)
        sigma = max(1.4826 * _median(np.abs(r - med)), min_scale)
    cs = tukey_c * sigma
    for i in range(n):
        u = r[i] / cs
        w[i] = (1.0 - u * u) ** 2 if abs(u) < 1.0 else 0.0
        w_tukey[i] = w[i]
    if spread and n > 0:
        sw = np.zeros(nE)
        sm = np.zeros(nE)
        for i in range(n):
            sw[e[i]] += w[i]
            sm[e[i]] += w[i] * r[i]
        for k in range(nE):
            sw[k] += 1e-9
            sm[k] /= sw[k]
        sv = np.zeros(nE)
        for i in range(n):
            d = r[i] - sm[e[i]]
            sv[e[i]] += w[i] * (d * d)
        s2 = sigma * sigma
        for k in range(nE):
            sv[k] /= sw[k]
        for i in range(n):
            w[i] = w[i] / (1.0 + spread_k * sv[e[i]] / s2)
    for i in range(n):
        a_ = nx[i] * fx
        b_ = ny[i] * fy
        xi, yi, q = x[i], y[i], iz[i]
        J[i, 0] = a_ * q
        J[i, 1] = b_ * q
        J[i, 2] = -(a_ * xi + b_ * yi) * q
        J[i, 3] = -a_ * xi * yi - b_ * (1.0 + yi * yi)
        J[i, 4] = a_ * (1.0 + xi * xi) + b_ * xi * yi
        J[i, 5] = b_ * xi - a_ * yi
        for p in range(6):
            wJ[i, p] = w[i] * J[i, p]
    return sigma


@njit(cache=True, nogil=True, error_model="numpy")
def sobel_at(img, uv):
    """(N, 2) float32 Sobel gradient (gx, gy) of the 8-bit or float32 ``img`` at the nearest pixels
    of ``uv`` (clipped to the 1-px inner border; a non-finite position reads the corner pixel
    (1, 1), as numpy's conversion does): :func:`mst.pipeline.tracking.health.sobel_at` to the bit."""
    H, W = img.shape
    n = uv.shape[0]
    out = np.empty((n, 2), np.float32)
    two = F32(2.0)
    for i in range(n):
        u, v = uv[i, 0], uv[i, 1]
        ix = min(max(int(np.rint(u)), 1), W - 2) if np.isfinite(u) else 1
        iy = min(max(int(np.rint(v)), 1), H - 2) if np.isfinite(v) else 1
        p0 = F32(img[iy - 1, ix - 1])
        p1 = F32(img[iy - 1, ix])
        p2 = F32(img[iy - 1, ix + 1])
        p3 = F32(img[iy, ix - 1])
        p5 = F32(img[iy, ix + 1])
        p6 = F32(img[iy + 1, ix - 1])
        p7 = F32(img[iy + 1, ix])
        p8 = F32(img[iy + 1, ix + 1])
        out[i, 0] = (p2 + two * p5 + p8) - (p0 + two * p3 + p6)
        out[i, 1] = (p6 + two * p7 + p8) - (p0 + two * p1 + p2)
    return out
