"""Numba kernels of the edge tracker's hot loops (issue #14; compiled once, cached on disk).

* :func:`me_convolve` and :func:`me_select`: the moving-edge search of a frame in two passes over all
  its samples: the oriented-mask convolutions at the pixels read along each normal (summed in float64,
  rounded once to float32: no BLAS, the same on every CPU), then ViSP's contrast and likelihood tests,
  the polarity vote of each model edge, local maxima, the best candidates and their parabolic
  sub-pixel refinement (float32 where the numpy formulation
  :func:`mst.pipeline.tracking.moving_edges.search_edges_numpy` is float32, thresholds rounded to
  float32 as numpy's weak Python scalars are, float64 elsewhere).
* :func:`vvs_solve`: the whole robust VVS of a frame (issue #14: the ~6 iterations of ~20 numpy
  calls each were most of the solve's time) on :func:`vvs_residuals` (one iteration's residuals at a
  pose: each sample's candidates against its projected model line) and :func:`vvs_linearise` (the
  candidate choice, Tukey weights on the MAD scale, the edge-spread re-weighting, the point-to-line
  Jacobian), with the normal equations, the KLT points, the damped step with undo and the stopping
  test; every sum in a fixed order (no BLAS, no FMA), so the pose is the numpy formulation's within
  rounding and the same on every CPU.
* :func:`sobel_at`: the Sobel gradient at sample positions; :func:`pose_health` and
  :func:`pose_gradients`: the health tests and the evidence gradients of a solved pose.
* :func:`edge_samples`, :func:`candidate_edges`, :func:`face_angles`, :func:`face_visibility_kernel`,
  :func:`zbuffer_planes`, :func:`zbuffer_faces`, :func:`samples_unhidden`, :func:`unhidden_samples`:
  the visibility pass (the candidate edges, their clipping and sampling, the face angle test with its
  hysteresis, the depth buffer's plane and per-vertex set-up, the hidden-line test at the samples and
  the kept samples' model points), the numpy formulations' values to the bit (face angles: to an ulp).
* :func:`canonical_normals_kernel`, :func:`vvs_inputs`, :func:`project_uv`, :func:`strongest`,
  :func:`candidates_uv_kernel`: the per-call set-up of the moving-edge search (normal flips, mask
  indices, the reference contrast's projection and strongest response) and of the VVS (samples with a
  candidate, the candidates' pixels), numpy's bits (issue #14: each replaced numpy calls whose fixed
  cost, a few microseconds each, was most of their time on a few hundred samples).

No fastmath (reproducible bit for bit on every CPU), single-threaded (the tracker's one-core budget).
Units: pixels, metres; ``R``, ``t`` the rotation and translation of ``T_cam_model``.

Longer than 500 lines: one module for every per-frame kernel of the tracker (moving edges, VVS,
health, visibility), which share private jitted helpers (``_rigid``, ``_sobel1``, ``_median``) and
one warm-up and cache-statistics list (:mod:`mst.eval.c2m.warmup`); it may be split along those
lines (search / pose / visibility) when the warm-up lists modules instead.
"""

from __future__ import annotations

import numpy as np
from numba import njit

F32 = np.float32


@njit(cache=True, nogil=True, error_model="numpy")
def me_convolve(img, uv, normal, ks, moff, masks, mask_idx, conv, k_eff, skip_zero):
    """The oriented-mask convolutions ``conv[i, m]`` (float32) at ``uv[i] + ks[m] * normal[i]`` (nearest
    pixel, clipped so that the mask ``masks[mask_idx[i]]`` (offsets ``moff``) stays inside the image),
    and ``k_eff[i, m]`` the signed distance (px) along the normal of the pixel actually read (see
    :func:`~mst.pipeline.tracking.moving_edges.convolve_along`). Each convolution is summed in
    float64 (every product of an 8-bit or float32 gray level and a float32 weight is exact there;
    four partial sums, the mask's pixel ``s`` going to sum ``s % 4`` in the mask's pixel order, added
    as ``(l0 + l1) + (l2 + l3)``) and rounded once to float32: within one float32 rounding of the exact
    value, and the same on every CPU (numpy's float32 matrix product of the gathered pixels went
    through BLAS, whose summation order depends on the CPU).

    Work skipped, to the same bits: ``skip_zero`` (8-bit images: every pixel finite) leaves out
    the mask's zero weights (the disc's corners, the pixels on the edge line; a partial sum that
    starts at +0.0 is unchanged by adding +-0.0), and a position whose rounded pixel is the previous
    position's (a slanted normal reads pixels twice) shares that convolution (issue #14: 0.21 ->
    0.13 ms per call on the L-building orbit's ~430 samples).

    Loop order (issue #14): per sample, each tap of the mask is applied to all its distinct
    positions before the next tap (the tap's offset and weight stay in registers, the positions'
    sums are independent); each position's partial sums still add the same products in the same
    order, so the bits are those of one convolution after the other (27 -> 20 ns per position on
    a 17-position search)."""
    H, W = img.shape
    S = moff.shape[0]
    M = ks.shape[0]
    r = 0
    for s in range(S):
        r = max(r, abs(moff[s, 0]), abs(moff[s, 1]))
    hi_x, hi_y = W - 1 - r, H - 1 - r
    fo = np.empty(S, np.int64)  # flat pixel offsets of the mask
    for s in range(S):
        fo[s] = moff[s, 1] * W + moff[s, 0]
    flat = img.ravel()
    # the current mask's taps in summation order: lane 0's (pixels 0, 4, 8, ...), then lane 1's, ...
    tf = np.empty(S, np.int64)
    tw = np.empty(S)
    lane_end = np.zeros(4, np.int64)
    pos = np.empty(M, np.int64)  # the sample's distinct flat pixels, in position order
    which = np.empty(M, np.int64)  # each position's entry in pos
    acc = np.empty((4, M))  # the partial sums of each distinct pixel
    last_mk = -1
    for i in range(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        nx, ny = normal[i, 0], normal[i, 1]
        mk = mask_idx[i]
        if mk != last_mk:  # the samples of one edge share their mask
            last_mk = mk
            n = 0
            for lane in range(4):
                for s in range(lane, S, 4):
                    wv = np.float64(masks[mk, s])
                    if skip_zero and wv == 0.0:
                        continue
                    tf[n] = fo[s]
                    tw[n] = wv
                    n += 1
                lane_end[lane] = n
        U = 0
        for m in range(M):
            k = ks[m]
            ix = min(max(np.rint(u + k * nx), r), hi_x)
            iy = min(max(np.rint(v + k * ny), r), hi_y)
            b = int(iy) * W + int(ix)
            k_eff[i, m] = (ix - u) * nx + (iy - v) * ny
            if U == 0 or b != pos[U - 1]:  # the same pixel as the previous position: the same convolution
                pos[U] = b
                U += 1
            which[m] = U - 1
        j0 = 0
        for lane in range(4):
            for q in range(U):
                acc[lane, q] = 0.0
            for j in range(j0, lane_end[lane]):
                o = tf[j]
                wj = tw[j]
                for q in range(U):
                    acc[lane, q] += np.float64(flat[pos[q] + o]) * wj
            j0 = lane_end[lane]
        for m in range(M):
            q = which[m]
            conv[i, m] = F32((acc[0, q] + acc[1, q]) + (acc[2, q] + acc[3, q]))


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
                cv = conv[i, m]
                if strong:
                    ratio = cv / rf
                    lc = abs(cv + rf)
                    like[i, m] = lc
                    ok[i, m] = (ratio > lo) and (ratio < hi) and (lc > thr2)
                else:
                    ln = two * abs(cv)
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
                    cm = conv[i, m]  # not ``c`` (nor above): numba.pycc types a reused name once (``c`` is an index below)
                    sg = 1.0 if cm > 0 else (-1.0 if cm < 0 else 0.0)
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


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
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
def _quickselect(s, h):
    """Rearrange ``s`` in place so that ``s[h]`` is its ``h``-th smallest value, ``s[:h]`` no larger
    and ``s[h + 1:]`` no smaller (Hoare's quickselect, middle pivot); returns ``s[h]``. No NaN in ``s``."""
    lo, hi = 0, s.shape[0] - 1
    while lo < hi:
        piv = s[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while s[i] < piv:
                i += 1
            while s[j] > piv:
                j -= 1
            if i <= j:
                tmp = s[i]
                s[i] = s[j]
                s[j] = tmp
                i += 1
                j -= 1
        if h <= j:
            hi = j
        elif h >= i:
            lo = i
        else:
            break
    return s[h]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _median(a):
    """The median of ``a`` (the middle value, or the mean of the two middle values): a selection, so
    exactly :func:`mst.pipeline.tracking.vvs._median`'s value. Quickselect on a copy (issue #14: a
    full sort twice per VVS iteration was a fifth of the solve), the sort when ``a`` holds a NaN (its
    order statistics put NaN last)."""
    n = a.shape[0]
    h = n // 2
    s = a.copy()
    for i in range(n):
        if s[i] != s[i]:
            s = np.sort(a)
            if n % 2 == 0 and n > 1:
                return 0.5 * (s[h - 1] + s[h])
            return s[h]
    m = _quickselect(s, h)
    if n % 2 == 0 and n > 1:
        lo = s[0]  # the (h - 1)-th smallest: the largest of s[:h]
        for i in range(1, h):
            if s[i] > lo:
                lo = s[i]
        return 0.5 * (lo + m)
    return m


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
def vvs_linearise(r_all, ch, r, w, w_tukey, min_scale, tukey_c, e, nE, spread, spread_k, nx, ny, x, y, iz, fx, fy,
                  J, wJ):
    """One VVS linearisation at the residuals ``r_all`` of :func:`vvs_residuals` (all outputs in
    place): per sample the candidate nearest its model line (``ch``, ``r``; first on ties), Tukey
    weights on the MAD scale floored at ``min_scale`` (``w_tukey``), the edge-spread re-weighting
    (``w``, when ``spread``: an edge whose inlier residuals scatter counts less), the point-to-line
    Jacobian ``J (N, 6)`` and ``wJ = w J``. Returns the robust scale sigma (px). The products
    ``J^T wJ`` and ``wJ^T r`` are left to numpy's BLAS (the numpy formulation's values to the bit)."""
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


# ---------------------------------------------------------------------------- the whole VVS solve
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _xform(P, i, T):
    """Point ``P[i]`` (model frame) in the frame of ``T`` (4x4): ``R @ p + t`` as three floats, summed
    in a fixed order (no BLAS, no FMA: the same on every CPU)."""
    p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
    return (((p0 * T[0, 0] + p1 * T[0, 1]) + p2 * T[0, 2]) + T[0, 3],
            ((p0 * T[1, 0] + p1 * T[1, 1]) + p2 * T[1, 2]) + T[1, 3],
            ((p0 * T[2, 0] + p1 * T[2, 1]) + p2 * T[2, 2]) + T[2, 3])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rigid(P, T, out):
    """``out = P @ R.T + t`` for (N, 3) points, in a fixed order (:func:`_xform`)."""
    for i in range(P.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _xform(P, i, T)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
def _solve6(A, b, x):
    """``x = A^-1 b`` for a 6x6 system by Gaussian elimination with partial pivoting (a fixed order
    of operations, as ``dgesv``'s LU). Returns False when a pivot is exactly zero (singular)."""
    M = np.empty((6, 7))
    for i in range(6):
        for j in range(6):
            M[i, j] = A[i, j]
        M[i, 6] = b[i]
    for k in range(6):
        p = k
        for i in range(k + 1, 6):
            if abs(M[i, k]) > abs(M[p, k]):
                p = i
        if M[p, k] == 0.0:
            return False
        if p != k:
            for j in range(7):
                tmp = M[k, j]
                M[k, j] = M[p, j]
                M[p, j] = tmp
        for i in range(k + 1, 6):
            f = M[i, k] / M[k, k]
            for j in range(k, 7):
                M[i, j] -= f * M[k, j]
    for i in range(5, -1, -1):
        s = M[i, 6]
        for j in range(i + 1, 6):
            s -= M[i, j] * x[j]
        x[i] = s / M[i, i]
    return True


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
def _se3_exp_left(xi, T, out):
    """``out = exp(xi) @ T`` (the exact SE(3) exponential of :func:`mst.pipeline.tracking.vvs.se3_exp`)."""
    v0, v1, v2, w0, w1, w2 = xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-16:  # small angle: the series of mst.core.poses.se3_exp
        a, b, cc = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = np.sqrt(th2)
        s, c = np.sin(th), np.cos(th)
        a = s / th
        b = (1.0 - c) / th2
        cc = (th - s) / (th2 * th)
    x00, x11, x22 = w0 * w0 - th2, w1 * w1 - th2, w2 * w2 - th2
    x01, x02, x12 = w0 * w1, w0 * w2, w1 * w2
    E = np.empty((3, 4))
    E[0, 0], E[0, 1], E[0, 2] = 1.0 + b * x00, b * x01 - a * w2, b * x02 + a * w1
    E[1, 0], E[1, 1], E[1, 2] = b * x01 + a * w2, 1.0 + b * x11, b * x12 - a * w0
    E[2, 0], E[2, 1], E[2, 2] = b * x02 - a * w1, b * x12 + a * w0, 1.0 + b * x22
    V00, V11, V22 = 1.0 + cc * x00, 1.0 + cc * x11, 1.0 + cc * x22
    E[0, 3] = V00 * v0 + (cc * x01 - b * w2) * v1 + (cc * x02 + b * w1) * v2
    E[1, 3] = (cc * x01 + b * w2) * v0 + V11 * v1 + (cc * x12 - b * w0) * v2
    E[2, 3] = (cc * x02 - b * w1) * v0 + (cc * x12 + b * w0) * v1 + V22 * v2
    for i in range(3):
        for j in range(4):
            out[i, j] = (E[i, 0] * T[0, j] + E[i, 1] * T[1, j]) + E[i, 2] * T[2, j] + (E[i, 3] if j == 3 else 0.0)
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
def _tukey_into(r, min_scale, tukey_c, w):
    """Tukey weights of ``r`` on its MAD scale floored at ``min_scale`` into ``w``; returns sigma."""
    n = r.shape[0]
    sigma = min_scale
    if n:
        med = _median(r)
        sigma = max(1.4826 * _median(np.abs(r - med)), min_scale)
    cs = tukey_c * sigma
    for i in range(n):
        u = r[i] / cs
        w[i] = (1.0 - u * u) ** 2 if abs(u) < 1.0 else 0.0
    return sigma


@njit(cache=True, nogil=True, error_model="numpy", inline="always")  # called from vvs_solve only
def _normal_equations(J, wJ, w, r, H, g):
    """``H = J^T wJ`` (6, 6), ``g = wJ^T r`` (6,) in place; returns ``cost = sum w r^2``. One pass over
    the samples with the 36 + 6 + 1 sums as independent accumulators, each summed in sample order
    (the values of one loop per entry to the bit, without its latency-bound chains: issue #14)."""
    n = r.shape[0]
    acc = np.zeros(43)
    for i in range(n):
        for p in range(6):
            jp = J[i, p]
            for q in range(6):
                acc[6 * p + q] += jp * wJ[i, q]
            acc[36 + p] += wJ[i, p] * r[i]
        acc[42] += w[i] * r[i] * r[i]
    for p in range(6):
        for q in range(6):
            H[p, q] = acc[6 * p + q]
        g[p] = acc[36 + p]
    return acc[42]


@njit(cache=True, nogil=True, error_model="numpy")
def vvs_solve(X, e, AB, nE, cu, cv, Xk, uk, T0, fx, fy, cx, cy, iters, lm_mu, min_mad, tukey_c, klt_weight, stop_px,
              stop_mu, spread, spread_k, T_out, H_out, He_out, w_out, r_out, wt_out, wk_out, klt_info_cap=0.0):
    """The whole robust VVS of :func:`mst.pipeline.tracking.vvs.solve_pose` in one call (the loop of
    :func:`~mst.pipeline.tracking.vvs.solve_pose_numpy`: residuals, candidate choice, Tukey and
    edge-spread weights, the Levenberg-Marquardt step with undo, the stopping test), every sum and
    product in a fixed order (no BLAS): the same pose as the numpy formulation within rounding
    (~1e-15 relative), and the same on every CPU. ``X (n, 3)`` samples with a candidate, ``e`` their
    edge, ``AB (2 nE, 3)`` the edge end points, ``cu, cv (n, C)`` candidates (1e9: none), ``Xk (nk,
    3)`` / ``uk (nk, 2)`` KLT points (nk may be 0). Outputs in place: ``T_out`` the pose, ``H_out``
    the last information matrix, ``He_out`` its edge samples' part (``H_out`` without the KLT block: the
    evidence of the pose, :attr:`~mst.pipeline.tracking.vvs.VVSResult.W_edges`), ``w_out``, ``r_out``,
    ``wt_out`` the last edge weights, residuals,
    Tukey weights, ``wk_out (2 nk)`` the KLT weights (Tukey x ``klt_weight``, before the cap).
    ``klt_info_cap`` > 0: the KLT block's information is scaled down to at most this x the edge
    samples' (``tr(H_e^-1 H_k) / 6``, :func:`~mst.pipeline.tracking.vvs.klt_info_scale`). The step test
    (``stop_px``) applies once the damping has relaxed to ``stop_mu`` (:data:`~mst.pipeline.tracking.vvs.STOP_MU`). Returns
    ``(iterations, sigma, status)`` with status 0 = a pose, 1 = diverged (a damped retry could not be
    solved: no pose)."""
    n = X.shape[0]
    nk = Xk.shape[0]
    C = cu.shape[1]
    Xc = np.empty((n, 3))
    P = np.empty((2 * nE, 3))
    Xck = np.empty((nk, 3))
    r_all = np.empty((n, C))
    nx, ny, x, y, iz = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    ch = np.zeros(n, np.int64)
    w = np.zeros(n)
    r = np.zeros(n)
    wt = np.zeros(n)
    J = np.empty((n, 6))
    wJ = np.empty((n, 6))
    rk = np.zeros(2 * nk)
    Jk = np.empty((2 * nk, 6))
    wk = np.zeros(2 * nk)
    Hk = np.zeros((6, 6))
    gk = np.zeros(6)
    col = np.empty(6)
    xc = np.empty(6)
    # the accepted linearisation: its pose, cost, choice, weights, H and g
    pT = np.empty((4, 4))
    pch = np.zeros(n, np.int64)
    pw = np.zeros(n)
    pwk = np.zeros(2 * nk)
    pH = np.zeros((6, 6))
    pg = np.zeros(6)
    pcost = 0.0
    have_prev = False
    H = np.zeros((6, 6))
    He = np.zeros((6, 6))
    g = np.zeros(6)
    A = np.empty((6, 6))
    xi = np.empty(6)
    T = T0.copy()
    Tn = np.empty((4, 4))
    fmax = max(fx, fy)
    _rigid(X, T, Xc)
    iz_max, xy_max = 1.0, 1.0
    if n:
        zmin = Xc[0, 2]
        xy_max = 0.0
        for i in range(n):
            zmin = min(zmin, Xc[i, 2])
            zz = max(Xc[i, 2], 1e-9)
            xy_max = max(xy_max, abs(Xc[i, 0] / zz), abs(Xc[i, 1] / zz))
        iz_max = 1.0 / max(zmin, 1e-9)
    mu = lm_mu
    raised = False  # a step was undone: the damping rose at a minimum, small steps are convergence
    sigma = min_mad
    it = 0
    completed = True
    for it in range(1, iters + 1):
        # residuals of every candidate at T (vvs_residuals), and the KLT points' residuals and Jacobian
        _rigid(X, T, Xc)
        _rigid(AB, T, P)
        vvs_residuals(Xc, P, nE, e, cu, cv, fx, fy, cx, cy, r_all, nx, ny, x, y, iz)
        if nk:
            _rigid(Xk, T, Xck)
            for i in range(nk):
                izk = 1.0 / Xck[i, 2]  # not ``q``, an index below: numba.pycc typed the reused name once
                xk, yk = Xck[i, 0] * izk, Xck[i, 1] * izk
                rk[i] = fx * xk + cx - uk[i, 0]
                rk[nk + i] = fy * yk + cy - uk[i, 1]
                Jk[i, 0], Jk[i, 1], Jk[i, 2] = fx * izk, 0.0, -fx * xk * izk
                Jk[i, 3], Jk[i, 4], Jk[i, 5] = -fx * xk * yk, fx * (1.0 + xk * xk), -fx * yk
                Jk[nk + i, 0], Jk[nk + i, 1], Jk[nk + i, 2] = 0.0, fy * izk, -fy * yk * izk
                Jk[nk + i, 3], Jk[nk + i, 4], Jk[nk + i, 5] = -fy * (1.0 + yk * yk), fy * xk * yk, fy * xk
        if have_prev:
            cost_new = 0.0
            for i in range(n):
                ro = r_all[i, pch[i]]
                cost_new += pw[i] * ro * ro
            for i in range(2 * nk):
                cost_new += pwk[i] * rk[i] * rk[i]
            if cost_new > pcost * (1 + 1e-9) and mu < 1e8:
                # undo: retry from the previous linearisation with more damping
                mu *= 10.0
                raised = True
                for i in range(6):
                    for j in range(6):
                        A[i, j] = pH[i, j]
                    A[i, i] = pH[i, i] + mu * (pH[i, i] + 1e-9)
                if not _solve6(A, pg, xi):
                    return it, sigma, 1
                for i in range(6):
                    xi[i] = -xi[i]
                _se3_exp_left(xi, pT, Tn)
                T[:, :] = Tn
                continue
            mu = max(mu / 10.0, 1e-7)
        # linearise (vvs_linearise), then the KLT points' Tukey weights
        sigma = vvs_linearise(r_all, ch, r, w, wt, min_mad, tukey_c, e, nE, spread, spread_k, nx, ny, x, y, iz, fx,
                              fy, J, wJ)
        cost = _normal_equations(J, wJ, w, r, H, g)  # H = J^T wJ, g = wJ^T r, cost = sum w r^2
        He[:, :] = H
        sc = 1.0  # the KLT block's information cap
        if nk:
            _tukey_into(rk, min_mad, tukey_c, wk)
            for i in range(2 * nk):
                wk[i] *= klt_weight
            for p in range(6):
                for q in range(6):
                    s = 0.0
                    for i in range(2 * nk):
                        s += Jk[i, p] * (wk[i] * Jk[i, q])
                    Hk[p, q] = s
                s = 0.0
                for i in range(2 * nk):
                    s += Jk[i, p] * (wk[i] * rk[i])
                gk[p] = s
            if klt_info_cap > 0.0:
                # rho = tr(H_e^-1 H_k) / 6: the KLT block's information in units of the edges'
                rho = 0.0
                solved = True
                for j in range(6):
                    for i in range(6):
                        col[i] = Hk[i, j]
                    if not _solve6(H, col, xc):
                        solved = False
                        break
                    rho += xc[j]
                rho /= 6.0
                if solved and rho > klt_info_cap:
                    sc = klt_info_cap / rho
            for p in range(6):
                for q in range(6):
                    H[p, q] += sc * Hk[p, q]
                g[p] += sc * gk[p]
            for i in range(2 * nk):
                cost += sc * wk[i] * rk[i] * rk[i]
        for i in range(6):
            for j in range(6):
                A[i, j] = H[i, j]
            A[i, i] = H[i, i] + mu * (H[i, i] + 1e-9)
        if not _solve6(A, g, xi):
            completed = False
            break
        for i in range(6):
            xi[i] = -xi[i]
        pT[:, :] = T
        pcost = cost
        pch[:] = ch
        pw[:] = w
        for i in range(2 * nk):
            pwk[i] = sc * wk[i]
        pH[:, :] = H
        pg[:] = g
        have_prev = True
        a0 = max(abs(xi[0]), abs(xi[1]), abs(xi[2]))
        a1 = max(abs(xi[3]), abs(xi[4]), abs(xi[5]))
        step_px = fmax * (a0 * iz_max + a1 * (1.0 + xy_max))
        _se3_exp_left(xi, T, Tn)
        T[:, :] = Tn
        if step_px < stop_px and (mu <= stop_mu or raised):
            completed = False
            break
    if completed and have_prev:
        # iteration budget spent: keep the last accepted pose unless it is better
        _rigid(X, T, Xc)
        _rigid(AB, T, P)
        vvs_residuals(Xc, P, nE, e, cu, cv, fx, fy, cx, cy, r_all, nx, ny, x, y, iz)
        c2 = 0.0
        for i in range(n):
            ro = r_all[i, pch[i]]
            c2 += pw[i] * ro * ro
        if c2 > pcost * (1 + 1e-9):
            T[:, :] = pT
    T_out[:, :] = T
    H_out[:, :] = H
    He_out[:, :] = He
    w_out[:] = w
    r_out[:] = r
    wt_out[:] = wt
    wk_out[:] = wk
    return it, sigma, 0


# ---------------------------------------------------------------------------- edge sampling
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _nan_max(a, b):
    """``np.maximum(a, b)`` (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _nan_min(a, b):
    """``np.minimum(a, b)`` (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a <= b else b


@njit(cache=True, nogil=True, error_model="numpy")
def edge_samples(Xv, E, small_face, near, far, K, R, t, x0, y0, x1, y1, step, use_lod, lod_min_line_px):
    """The clipping and sampling steps of :func:`mst.pipeline.tracking.visibility.visible_samples`
    for the candidate edges ``E (nE, 2)`` (vertex ids into the camera-frame vertices ``Xv``), in one
    pass with the numpy formulation's operations in its order (so its values to the bit): near/far
    clipping in 3D, projection with ``K``, the level-of-detail rule (``use_lod``: edges on small faces
    (``small_face``) or shorter than ``lod_min_line_px``), the Liang-Barsky clip to the rectangle
    ``x0..x1, y0..y1`` px, samples every ``step`` px with their inverse depth.

    Returns ``(counts (5,) int64: behind, beyond_far, lod, outside, short; z_min (m, NaN: no edge in
    front); keep (nE,) the index of each kept edge's row in E; pa, pb (k, 2) px the clipped end points;
    A_model, B_model (k, 3) m the clipped end points in the model frame (R, t: T_cam_model); uv
    (N, 2) px, nrm (N, 2), iz (N,) 1/m, Xc (N, 3) camera frame m, edge_id (N,) index into the kept
    edges)``."""
    nE = E.shape[0]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    counts = np.zeros(5, np.int64)
    z_min = np.nan
    keep = np.empty(nE, np.int64)
    pa = np.empty((nE, 2))
    pb = np.empty((nE, 2))
    iza = np.empty(nE)
    izb = np.empty(nE)
    Lk = np.empty(nE)
    nsk = np.empty(nE, np.int64)
    k = 0
    for e in range(nE):
        A0, A1, A2 = Xv[E[e, 0], 0], Xv[E[e, 0], 1], Xv[E[e, 0], 2]
        B0, B1, B2 = Xv[E[e, 1], 0], Xv[E[e, 1], 1], Xv[E[e, 1], 2]
        zA, zB = A2, B2
        behind = (zA < near) and (zB < near)
        if behind:
            counts[0] += 1
            continue
        zm = _nan_min(zA, zB)
        z_min = zm if z_min != z_min else min(z_min, zm)
        # near/far clipping (_clip_near_far)
        kp = not ((zA > far) and (zB > far))
        dz = zB - zA
        t_near = (near - zA) / dz
        t_far = (far - zA) / dz
        t0, t1 = 0.0, 1.0
        if zA < near:
            t0 = t_near
        if zB < near:
            t1 = t_near
        if zA > far:
            t0 = _nan_max(t0, t_far)
        if zB > far:
            t1 = _nan_min(t1, t_far)
        kp = kp and (t1 > t0)
        if not kp:
            counts[1] += 1
            continue
        D0, D1, D2 = B0 - A0, B1 - A1, B2 - A2
        a0, a1, a2 = A0 + t0 * D0, A1 + t0 * D1, A2 + t0 * D2
        b0, b1, b2 = A0 + t1 * D0, A1 + t1 * D1, A2 + t1 * D2
        # projection (_mat3(A, K), then the division)
        ux = a0 * K[0, 0] + a1 * K[0, 1] + a2 * K[0, 2]
        uy = a0 * K[1, 0] + a1 * K[1, 1] + a2 * K[1, 2]
        uz = a0 * K[2, 0] + a1 * K[2, 1] + a2 * K[2, 2]
        vx = b0 * K[0, 0] + b1 * K[0, 1] + b2 * K[0, 2]
        vy = b0 * K[1, 0] + b1 * K[1, 1] + b2 * K[1, 2]
        vz = b0 * K[2, 0] + b1 * K[2, 1] + b2 * K[2, 2]
        uax, uay = ux / uz, uy / uz
        ubx, uby = vx / vz, vy / vz
        if use_lod:
            ddx, ddy = ubx - uax, uby - uay
            big = (not small_face[e]) and (np.sqrt(ddx * ddx + ddy * ddy) >= lod_min_line_px)
            if not big:
                counts[2] += 1
                continue
        # Liang-Barsky (_clip_rect)
        dx, dy = ubx - uax, uby - uay
        s0, s1 = 0.0, 1.0
        inside = True
        for side in range(4):
            if side == 0:
                p, q = -dx, uax - x0
            elif side == 1:
                p, q = dx, x1 - uax
            elif side == 2:
                p, q = -dy, uay - y0
            else:
                p, q = dy, y1 - uay
            par = abs(p) < 1e-12
            if par and q < 0:
                inside = False
            rr = q / p
            if (not par) and p < 0:
                s0 = _nan_max(s0, rr)
            if (not par) and p > 0:
                s1 = _nan_min(s1, rr)
        inside = inside and (s1 > s0)
        if not inside:
            counts[3] += 1
            continue
        izA, izB = 1.0 / a2, 1.0 / b2
        pax, pay = uax + s0 * dx, uay + s0 * dy
        pbx, pby = uax + s1 * dx, uay + s1 * dy
        ia = izA + s0 * (izB - izA)
        ib = izA + s1 * (izB - izA)
        lx, ly = pbx - pax, pby - pay
        L = np.sqrt(lx * lx + ly * ly)
        ns = np.int64(np.floor(L / step))
        if not ns >= 1:
            counts[4] += 1
            continue
        keep[k] = e
        pa[k, 0], pa[k, 1], pb[k, 0], pb[k, 1] = pax, pay, pbx, pby
        iza[k], izb[k], Lk[k], nsk[k] = ia, ib, L, ns
        k += 1
    A_model = np.empty((k, 3))
    B_model = np.empty((k, 3))
    n = 0
    for j in range(k):
        n += nsk[j]
        for end in range(2):
            px, py, izv = (pa[j, 0], pa[j, 1], iza[j]) if end == 0 else (pb[j, 0], pb[j, 1], izb[j])
            c0 = ((px - cx) / fx) / izv - t[0]
            c1 = ((py - cy) / fy) / izv - t[1]
            c2 = 1.0 / izv - t[2]
            out = A_model if end == 0 else B_model
            out[j, 0] = c0 * R[0, 0] + c1 * R[1, 0] + c2 * R[2, 0]
            out[j, 1] = c0 * R[0, 1] + c1 * R[1, 1] + c2 * R[2, 1]
            out[j, 2] = c0 * R[0, 2] + c1 * R[1, 2] + c2 * R[2, 2]
    uv = np.empty((n, 2))
    nrm = np.empty((n, 2))
    iz = np.empty(n)
    Xc = np.empty((n, 3))
    edge_id = np.empty(n, np.int64)
    i = 0
    for j in range(k):
        ns = nsk[j]
        dx, dy = pb[j, 0] - pa[j, 0], pb[j, 1] - pa[j, 1]
        Lm = max(Lk[j], 1e-9)
        tx, ty = dx / Lm, dy / Lm
        diz = izb[j] - iza[j]
        for q in range(ns):
            s = (q + 0.5) / ns
            u = pa[j, 0] + s * dx
            v = pa[j, 1] + s * dy
            zi = iza[j] + s * diz
            uv[i, 0], uv[i, 1] = u, v
            nrm[i, 0], nrm[i, 1] = -ty, tx
            iz[i] = zi
            Xc[i, 0] = ((u - cx) / fx) / zi
            Xc[i, 1] = ((v - cy) / fy) / zi
            Xc[i, 2] = 1.0 / zi
            edge_id[i] = j
            i += 1
    return counts, z_min, keep[:k].copy(), pa[:k].copy(), pb[:k].copy(), A_model, B_model, uv, nrm, iz, Xc, edge_id


# ---------------------------------------------------------------------------- depth buffer set-up
@njit(cache=True, nogil=True, error_model="numpy")
def zbuffer_faces(V, R, t, Ks, near, sel, d, loop_vid, loop_start, loop_end, ring_vid, face_vstart, uu, vv):
    """The per-vertex set-up of :func:`mst.pipeline.tracking.depth_buffer.inverse_depth_buffer` for
    the faces ``sel`` (K,) (their planes' ``d`` (K,) given): each face's depth range over its outer
    loop (vertices ``V`` moved to the camera frame by ``R``, ``t`` as ``_mat3`` does, in its order),
    the faces kept (``|d| >= 1e-12`` and not wholly behind ``near``) split into those wholly in front
    (``inside``) and those crossing the near plane, and the buffer-pixel projection ``uu, vv`` (with
    ``Ks``) of every ring vertex of the inside faces, written in place (the other entries are not
    touched: the rasteriser reads no others). Returns ``(inside, crossing)`` face ids."""
    k = sel.shape[0]
    inside = np.empty(k, np.int64)
    crossing = np.empty(k, np.int64)
    ni, nc = 0, 0
    for j in range(k):
        f = sel[j]
        zmin, zmax = np.inf, -np.inf
        for q in range(loop_start[f], loop_end[f]):
            vi = loop_vid[q]
            z = ((V[vi, 0] * R[2, 0] + V[vi, 1] * R[2, 1]) + V[vi, 2] * R[2, 2]) + t[2]
            zmin = min(zmin, z)
            zmax = max(zmax, z)
        if not (abs(d[j]) >= 1e-12 and zmax >= near):
            continue
        if zmin >= near:
            inside[ni] = f
            ni += 1
            for q in range(face_vstart[f], face_vstart[f + 1]):
                vi = ring_vid[q]
                x0 = ((V[vi, 0] * R[0, 0] + V[vi, 1] * R[0, 1]) + V[vi, 2] * R[0, 2]) + t[0]
                x1 = ((V[vi, 0] * R[1, 0] + V[vi, 1] * R[1, 1]) + V[vi, 2] * R[1, 2]) + t[1]
                x2 = ((V[vi, 0] * R[2, 0] + V[vi, 1] * R[2, 1]) + V[vi, 2] * R[2, 2]) + t[2]
                z = x2 if x2 > 1e-12 else 1e-12
                uu[vi] = (Ks[0, 0] * x0 + Ks[0, 1] * x1) / z + Ks[0, 2]
                vv[vi] = Ks[1, 1] * x1 / z + Ks[1, 2]
        else:
            crossing[nc] = f
            nc += 1
    return inside[:ni].copy(), crossing[:nc].copy()


# ---------------------------------------------------------------------------- health tests
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sobel1(img, u, v):
    """The Sobel gradient (gx, gy) float32 at the nearest pixel of (u, v) (as :func:`sobel_at`)."""
    H, W = img.shape
    ix = min(max(int(np.rint(u)), 1), W - 2) if np.isfinite(u) else 1
    iy = min(max(int(np.rint(v)), 1), H - 2) if np.isfinite(v) else 1
    two = F32(2.0)
    p0 = F32(img[iy - 1, ix - 1])
    p1 = F32(img[iy - 1, ix])
    p2 = F32(img[iy - 1, ix + 1])
    p3 = F32(img[iy, ix - 1])
    p5 = F32(img[iy, ix + 1])
    p6 = F32(img[iy + 1, ix - 1])
    p7 = F32(img[iy + 1, ix])
    p8 = F32(img[iy + 1, ix + 1])
    return (p2 + two * p5 + p8) - (p0 + two * p3 + p6), (p6 + two * p7 + p8) - (p0 + two * p1 + p2)


@njit(cache=True, nogil=True, error_model="numpy")
def pose_health(img, X, A, B, edge, T, fx, fy, cx, cy, z_min, strong_min):
    """The numeric part of ``EdgeTracker._absolute_health`` at the pose ``T``: the samples ``X (N, 3)``
    (model frame) projected (``uv (N, 2)`` px; a sample at depth <= ``z_min`` is projected at z = 1
    and reported in ``all_in_front``), the unit normal of each sample's projected model edge (``A``,
    ``B`` (E, 3) its end points), the Sobel gradient there; a gradient of norm >= ``strong_min`` is
    strong. Returns ``(uv, all_in_front, n_strong, sum of the strong samples' angles between gradient
    and normal, deg)``. Transforms and sums in a fixed order (no BLAS)."""
    N = X.shape[0]
    nE = A.shape[0]
    nx = np.empty(nE)
    ny = np.empty(nE)
    for k in range(nE):
        a0, a1, a2 = _xform(A, k, T)
        b0, b1, b2 = _xform(B, k, T)
        dx = (b0 / b2 * fx + cx) - (a0 / a2 * fx + cx)
        dy = (b1 / b2 * fy + cy) - (a1 / a2 * fy + cy)
        ln = max(np.sqrt(dx * dx + dy * dy), 1e-12)
        nx[k] = -(dy / ln)
        ny[k] = dx / ln
    uv = np.empty((N, 2))
    in_front = True
    n_strong = 0
    ang_sum = 0.0
    for i in range(N):
        x0, x1, x2 = _xform(X, i, T)
        ok = x2 > z_min
        in_front = in_front and ok
        z = x2 if ok else 1.0
        u = fx * x0 / z + cx
        v = fy * x1 / z + cy
        uv[i, 0], uv[i, 1] = u, v
        gx, gy = _sobel1(img, u, v)
        gn = np.sqrt(gx * gx + gy * gy)  # float32, as numpy's norm of the float32 gradient
        if gn >= strong_min:
            e = edge[i]
            c = abs(np.float64(gx) * nx[e] + np.float64(gy) * ny[e]) / max(np.float64(gn), 1e-9)
            c = min(max(c, 0.0), 1.0)
            ang_sum += np.degrees(np.arccos(c))
            n_strong += 1
    return uv, in_front, n_strong, ang_sum


@njit(cache=True, nogil=True, error_model="numpy")
def pose_gradients(img, X, A, B, edge, T, fx, fy, cx, cy, strong_min, cos_tol):
    """The gradient part of ``EdgeTracker.evidence`` at the pose ``T``: the samples projected (``uv``
    (N, 2) px, depth floored at 1e-9 m), each sample's projected model-edge normal ``n (N, 2)`` (fixed
    by the edge direction A -> B), the Sobel gradient at -1, 0, +1 px along it (the one with the
    largest |projection| on n kept, first on ties): ``sign`` (N,) int8 its polarity where it is at
    least ``strong_min``, else 0, and ``good`` (N,) strong and within ``acos(cos_tol)`` of n.
    Transforms in a fixed order (no BLAS)."""
    N = X.shape[0]
    nE = A.shape[0]
    ex = np.empty(nE)
    ey = np.empty(nE)
    for k in range(nE):
        a0, a1, a2 = _xform(A, k, T)
        b0, b1, b2 = _xform(B, k, T)
        dx = (b0 / b2 - a0 / a2) * fx
        dy = (b1 / b2 - a1 / a2) * fy
        ln = max(np.sqrt(dx * dx + dy * dy), 1e-12)
        ex[k] = -(dy / ln)
        ey[k] = dx / ln
    uv = np.empty((N, 2))
    n = np.empty((N, 2))
    sign = np.zeros(N, np.int8)
    good = np.zeros(N, np.bool_)
    for i in range(N):
        x0, x1, x2 = _xform(X, i, T)
        z = max(x2, 1e-9)
        u = fx * x0 / z + cx
        v = fy * x1 / z + cy
        uv[i, 0], uv[i, 1] = u, v
        e = edge[i]
        a, b = ex[e], ey[e]
        n[i, 0], n[i, 1] = a, b
        best, bgx, bgy = -1.0, F32(0.0), F32(0.0)
        pbest = 0.0
        for kk in range(3):
            s = np.float64(kk - 1)
            gx, gy = _sobel1(img, u + s * a, v + s * b)
            p = np.float64(gx) * a + np.float64(gy) * b
            if abs(p) > best:
                best, pbest, bgx, bgy = abs(p), p, gx, gy
        if best >= strong_min:
            sign[i] = 1 if pbest > 0 else (-1 if pbest < 0 else 0)
            gn = np.sqrt(bgx * bgx + bgy * bgy)
            good[i] = best >= cos_tol * np.float64(gn)
    return uv, n, sign, good


# ---------------------------------------------------------------------------- face visibility
@njit(cache=True, nogil=True, error_model="numpy")
def face_angles(V, N, loop_vid, loop_start, loop_end, sel, c_model):
    """The smallest angle (deg) between each face's outward normal ``N[f]`` and the rays from its
    outer-loop vertices to the camera centre ``c_model`` (model frame), for the faces ``sel`` (K,):
    the test of :func:`mst.pipeline.tracking.visibility.face_visibility` (rays normalised, cosines
    summed in a fixed order; numpy's einsum and arccos differ from it by an ulp, which moves a face
    across an appear/disappear angle only when it lies within ~1e-13 deg of it)."""
    k = sel.shape[0]
    ang = np.empty(k)
    for j in range(k):
        f = sel[j]
        n0, n1, n2 = N[f, 0], N[f, 1], N[f, 2]
        best = -np.inf
        for q in range(loop_start[f], loop_end[f]):
            vi = loop_vid[q]
            r0, r1, r2 = c_model[0] - V[vi, 0], c_model[1] - V[vi, 1], c_model[2] - V[vi, 2]
            ln = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
            cs = (r0 / ln) * n0 + (r1 / ln) * n1 + (r2 / ln) * n2
            if cs > best or cs != cs:
                best = cs
        ang[j] = np.degrees(np.arccos(min(max(best, -1.0), 1.0)))
    return ang


@njit(cache=True, nogil=True, error_model="numpy")
def face_visibility_kernel(V, N, loop_vid, loop_start, loop_end, sel, c_model, prev, has_prev, appear_deg,
                           disappear_deg, F):
    """(F,) bool :func:`mst.pipeline.tracking.visibility.face_visibility`: of the faces ``sel`` (K,), those
    at a :func:`face_angles` angle below ``appear_deg``, or below ``disappear_deg`` when visible in
    ``prev`` (F,) bool (``has_prev``); the others False."""
    ang = face_angles(V, N, loop_vid, loop_start, loop_end, sel, c_model)
    vis = np.zeros(F, np.bool_)
    for j in range(sel.shape[0]):
        a = ang[j]
        vis[sel[j]] = (a < appear_deg) or (has_prev and prev[sel[j]] and a < disappear_deg)
    return vis


@njit(cache=True, nogil=True, error_model="numpy")
def surface_values(img, X, face, face_visible, T, fx, fy, cx, cy, near, buf, sc, use_buf):
    """The surface part of ``EdgeTracker.evidence`` (``_surface_values``) at the pose ``T``: of the
    surface points ``X (M, 3)`` (model frame) on faces ``face (M,)``, those on a visible face, in
    front of ``near`` m, whose rounded pixel lies at least 1 px inside the image and (``use_buf``)
    that are not behind the inverse-depth buffer ``buf`` (scale ``sc``: ``1/z >= 0.99 x`` the
    buffer's, the product in float32 as numpy's), and their 3x3 mean gray level (float32 sum and
    division, as numpy's). Returns ``(idx (K,) int64, val (K,) float64)``; the transform in the fixed
    order of ``transform_points(elementwise=True)``."""
    H, W = img.shape
    M = X.shape[0]
    idx = np.empty(M, np.int64)
    val = np.empty(M)
    k = 0
    f99 = F32(1.0 - 1e-2)
    bh, bw = buf.shape
    for j in range(M):
        if not face_visible[face[j]]:
            continue
        x0, x1, x2 = _xform(X, j, T)
        if not x2 > near:
            continue
        ix = np.int64(np.rint(x0 / x2 * fx + cx))
        iy = np.int64(np.rint(x1 / x2 * fy + cy))
        if not (ix >= 1 and iy >= 1 and ix < W - 1 and iy < H - 1):
            continue
        if use_buf:
            bx = min(max(np.int64(np.rint((ix + 0.5) * sc - 0.5)), 0), bw - 1)
            by = min(max(np.int64(np.rint((iy + 0.5) * sc - 0.5)), 0), bh - 1)
            if not 1.0 / x2 >= np.float64(F32(buf[by, bx]) * f99):
                continue
        s = F32(0.0)
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                s += F32(img[iy + dy, ix + dx])
        idx[k] = j
        val[k] = np.float64(s / F32(9.0))
        k += 1
    return idx[:k], val[:k]


@njit(cache=True, nogil=True, error_model="numpy")
def samples_unhidden(buf, uv, iz, sc):
    """The hidden-line test of :func:`~mst.pipeline.tracking.visibility.visible_samples` at the samples
    ``uv (N, 2)`` px (inverse depths ``iz (N,)`` 1/m): (N,) bool, True where the sample is not behind the
    farthest surface of its buffer pixel's 3x3 neighbourhood (``buf (h, w)`` float32 inverse depths at
    ``sc`` x the image's pixels; the neighbours inside the buffer, as ``cv2.erode``'s default border).
    The erosion read at the N samples instead of computed over the whole buffer (issue #14: a
    320x240 ``cv2.erode`` was ~0.2 ms a frame); float32 margin arithmetic as numpy's ``far_nb * (1.0 -
    2e-3) - 1e-9`` on the float32 erosion: the same bits."""
    bh, bw = buf.shape
    f = F32(1.0 - 2e-3)
    eps = F32(1e-9)
    out = np.empty(uv.shape[0], np.bool_)
    for i in range(uv.shape[0]):
        ix = min(max(np.int64(np.rint((uv[i, 0] + 0.5) * sc - 0.5)), 0), bw - 1)
        iy = min(max(np.int64(np.rint((uv[i, 1] + 0.5) * sc - 0.5)), 0), bh - 1)
        m = buf[iy, ix]
        for y in range(max(iy - 1, 0), min(iy + 2, bh)):
            for x in range(max(ix - 1, 0), min(ix + 2, bw)):
                m = min(m, buf[y, x])
        out[i] = iz[i] >= np.float64(m * f - eps)
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _edge_of(edge_faces, e, faces):
    """Edge ``e`` has an adjacent face in ``faces`` (F,) bool, or none at all (a free line)."""
    f0, f1 = edge_faces[e, 0], edge_faces[e, 1]
    return (f0 >= 0 and faces[f0]) or (f1 >= 0 and faces[f1]) or (f0 < 0 and f1 < 0)


@njit(cache=True, nogil=True, error_model="numpy")
def candidate_edges(edges, edge_faces, e_sel, fv, fv_big):
    """The candidate edges of :func:`~mst.pipeline.tracking.visibility.visible_samples` among ``e_sel``
    (K,) edge ids, in their order: those with an adjacent face in ``fv`` (F,) bool, and the free lines
    (no adjacent face). Returns ``(eid (E',), E (E', 2) vertex ids, small_face (E',) bool: no adjacent
    face in fv_big)`` (issue #14: the numpy formulation's ten calls, ~25 us a frame)."""
    n = 0
    keep = np.zeros(e_sel.shape[0], np.bool_)
    for k in range(e_sel.shape[0]):
        keep[k] = _edge_of(edge_faces, e_sel[k], fv)
        if keep[k]:
            n += 1
    eid = np.empty(n, np.int64)
    E = np.empty((n, 2), np.int64)
    small = np.empty(n, np.bool_)
    j = 0
    for k in range(e_sel.shape[0]):
        if not keep[k]:
            continue
        e = e_sel[k]
        eid[j] = e
        E[j, 0], E[j, 1] = edges[e, 0], edges[e, 1]
        small[j] = not _edge_of(edge_faces, e, fv_big)
        j += 1
    return eid, E, small


@njit(cache=True, nogil=True, error_model="numpy")
def project_uv(X, T, fx, fy, cx, cy):
    """(N, 2) pixels of the model points ``X (N, 3)`` at the pose ``T`` (4x4): the camera-frame point as
    :func:`_xform` sums it (``mat3_kernel``'s order), its depth floored at 1e-9 m (``np.maximum``: NaN stays
    NaN), ``u = fx x / z + cx``, ``v = fy y / z + cy`` (numpy's order of operations: the same bits as the numpy
    steps of :meth:`mst.pipeline.tracking.edge_tracker.EdgeTracker._edge_pass`, one call instead of six)."""
    out = np.empty((X.shape[0], 2))
    for i in range(X.shape[0]):
        c0, c1, z = _xform(X, i, T)
        if z < 1e-9:
            z = 1e-9
        out[i, 0] = fx * c0 / z + cx
        out[i, 1] = fy * c1 / z + cy
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def strongest(conv):
    """``conv[i, argmax_m |conv[i, m]|]`` (N,) of a float32 ``conv (N, M)``: ``np.argmax``'s choice
    (the first of equal maxima, the first NaN when there is one)."""
    n, m = conv.shape
    out = np.empty(n, conv.dtype)
    for i in range(n):
        j = 0
        best = abs(conv[i, 0])
        if best == best:
            for k in range(1, m):
                a = abs(conv[i, k])
                if a != a:
                    j = k
                    break
                if a > best:
                    best = a
                    j = k
        out[i] = conv[i, j]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def candidates_uv_kernel(uv, offset, normal):
    """(N, C, 2) ``uv[i] + offset[i, c] * normal[i]`` (numpy's broadcast: the same bits)."""
    n, C = offset.shape
    out = np.empty((n, C, 2))
    for i in range(n):
        for c in range(C):
            o = offset[i, c]
            out[i, c, 0] = uv[i, 0] + o * normal[i, 0]
            out[i, c, 1] = uv[i, 1] + o * normal[i, 1]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def unhidden_samples(buf, uv, iz, sc, nrm, Xc, edge_id, R, t):
    """The samples that pass :func:`samples_unhidden` (in order) and their model-frame points, in one
    pass (issue #14: four boolean gathers and the model transform were ~30 us of numpy calls a frame):
    ``(n_hidden, uv (K, 2), nrm (K, 2), Xc (K, 3), edge_id (K,), X_model (K, 3))`` with ``X_model =
    (Xc - t) @ R`` summed as :func:`mst.pipeline.tracking.depth_buffer._mat3` sums ``_mat3(Xc - t,
    R.T)`` (``(d0 R0j + d1 R1j) + d2 R2j``): the same bits as the numpy steps."""
    vis = samples_unhidden(buf, uv, iz, sc)
    n = 0
    for i in range(vis.shape[0]):
        if vis[i]:
            n += 1
    uv_o = np.empty((n, 2))
    nrm_o = np.empty((n, 2))
    xc_o = np.empty((n, 3))
    id_o = np.empty(n, edge_id.dtype)
    xm_o = np.empty((n, 3))
    k = 0
    for i in range(vis.shape[0]):
        if not vis[i]:
            continue
        uv_o[k, 0], uv_o[k, 1] = uv[i, 0], uv[i, 1]
        nrm_o[k, 0], nrm_o[k, 1] = nrm[i, 0], nrm[i, 1]
        d0, d1, d2 = Xc[i, 0] - t[0], Xc[i, 1] - t[1], Xc[i, 2] - t[2]
        xc_o[k, 0], xc_o[k, 1], xc_o[k, 2] = Xc[i, 0], Xc[i, 1], Xc[i, 2]
        id_o[k] = edge_id[i]
        for j in range(3):
            xm_o[k, j] = (d0 * R[0, j] + d1 * R[1, j]) + d2 * R[2, j]
        k += 1
    return vis.shape[0] - n, uv_o, nrm_o, xc_o, id_o, xm_o


@njit(cache=True, nogil=True, error_model="numpy")
def canonical_normals_kernel(normal, ang, n_masks, n_out, idx):
    """The flips and mask indices of :func:`~mst.pipeline.tracking.moving_edges.canonical_normals` from
    ``ang (N,)`` (degrees of each normal, numpy's ``degrees(arctan2)``: the transcendental stays numpy's)
    into ``n_out (N, 2)`` and ``idx (N,)``, numpy's elementwise operations in its order (issue #14: ~10
    numpy calls, ~60 us a call). Returns False (outputs incomplete) at a non-finite angle, whose integer
    cast numpy defines by the CPU: the caller takes numpy's formulation then."""
    step = 180.0 / n_masks
    for i in range(normal.shape[0]):
        a = ang[i]
        if not np.isfinite(a):
            return False
        if a < 0 or a >= 180:
            n_out[i, 0] = -normal[i, 0]
            n_out[i, 1] = -normal[i, 1]
            a = a + 180.0
        else:
            n_out[i, 0] = normal[i, 0]
            n_out[i, 1] = normal[i, 1]
        a = a % 180.0
        idx[i] = np.int64(np.rint(a / step)) % n_masks
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def vvs_inputs(X_model, edge, cand_uv):
    """The inputs of :func:`vvs_solve` from a solve's samples (issue #14: six numpy calls, ~50 us a
    solve): ``has (N,)`` the samples with a candidate (a finite u), and of those the model points
    ``X (n, 3)``, edge ids ``e (n,)`` and candidates ``cu, cv (n, C)`` px with each non-finite
    coordinate replaced by 1e9 (never the nearest candidate)."""
    N, C = cand_uv.shape[0], cand_uv.shape[1]
    has = np.zeros(N, np.bool_)
    n = 0
    for i in range(N):
        for c in range(C):
            if np.isfinite(cand_uv[i, c, 0]):
                has[i] = True
                n += 1
                break
    X = np.empty((n, 3))
    e = np.empty(n, np.int64)
    cu = np.empty((n, C))
    cv = np.empty((n, C))
    k = 0
    for i in range(N):
        if not has[i]:
            continue
        for j in range(3):
            X[k, j] = X_model[i, j]
        e[k] = edge[i]
        for c in range(C):
            u, v = cand_uv[i, c, 0], cand_uv[i, c, 1]
            cu[k, c] = u if np.isfinite(u) else 1e9
            cv[k, c] = v if np.isfinite(v) else 1e9
        k += 1
    return has, X, e, cu, cv


@njit(cache=True, nogil=True, error_model="numpy")
def zbuffer_planes(face_normals, face_point, sel, R, t, Kinv, coef):
    """The plane set-up of :func:`mst.pipeline.tracking.depth_buffer.inverse_depth_buffer` for the
    faces ``sel`` (K,): each face's normal and point in the camera frame (``_mat3``'s products and
    sums in its order), ``d = n_c . p_c`` (the 3 products summed as ``numpy.einsum`` sums them on x86-64,
    ``(p0 + p2) + p1``, fixed here on every CPU) and ``coef[f] = (n_c Kinv) / d`` (``1/z`` affine in the
    buffer's pixels) written into the rows ``sel`` of ``coef (F, 3)``; returns ``d (K,)`` (issue #14:
    five numpy calls of each render)."""
    k = sel.shape[0]
    d = np.empty(k)
    for j in range(k):
        f = sel[j]
        n0, n1, n2 = face_normals[f, 0], face_normals[f, 1], face_normals[f, 2]
        q0, q1, q2 = face_point[f, 0], face_point[f, 1], face_point[f, 2]
        c0 = (n0 * R[0, 0] + n1 * R[0, 1]) + n2 * R[0, 2]
        c1 = (n0 * R[1, 0] + n1 * R[1, 1]) + n2 * R[1, 2]
        c2 = (n0 * R[2, 0] + n1 * R[2, 1]) + n2 * R[2, 2]
        p0 = ((q0 * R[0, 0] + q1 * R[0, 1]) + q2 * R[0, 2]) + t[0]
        p1 = ((q0 * R[1, 0] + q1 * R[1, 1]) + q2 * R[1, 2]) + t[1]
        p2 = ((q0 * R[2, 0] + q1 * R[2, 1]) + q2 * R[2, 2]) + t[2]
        dj = (c0 * p0 + c2 * p2) + c1 * p1  # numpy's einsum order for 3 terms (its 2-wide pairs 0+2, then 1)
        d[j] = dj
        for m in range(3):
            coef[f, m] = ((c0 * Kinv[0, m] + c1 * Kinv[1, m]) + c2 * Kinv[2, m]) / dj
    return d


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pairwise_block(a, lo, n):
    """numpy's ``pairwise_sum`` of ``a[lo:lo + n]`` for ``n <= 128``: sequential from -0.0 below 8
    terms, else 8 interleaved partial sums combined as a tree, then the rest sequentially."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True, error_model="numpy")
def _pairwise_sum(a, lo, n):
    """numpy's pairwise summation of ``a[lo:lo + n]`` (the ``pairwise_sum`` of its add loop), to the
    bit: :func:`_pairwise_block` up to 128 terms, beyond it the sum of the two halves (the first a
    multiple of 8 terms long), evaluated here with an explicit stack (numba's on-disk cache of a
    recursive function crashed the next process that loaded it)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    s_lo = np.empty(64, np.int64)  # the pending halvings (depth <= log2(n / 128) + 1)
    s_n = np.empty(64, np.int64)
    s_st = np.empty(64, np.int64)  # 0: left half not summed, 1: right half not summed, 2: both summed
    vals = np.empty(64)
    top, nv = 0, 0
    s_lo[0], s_n[0], s_st[0] = lo, n, 0
    while top >= 0:
        lo_, n_ = s_lo[top], s_n[top]
        if n_ <= 128:
            vals[nv] = _pairwise_block(a, lo_, n_)
            nv += 1
            top -= 1
            continue
        n2 = n_ // 2
        n2 -= n2 % 8
        st = s_st[top]
        if st == 2:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            top -= 1
            continue
        s_st[top] = st + 1
        top += 1
        if st == 0:
            s_lo[top], s_n[top] = lo_, n2
        else:
            s_lo[top], s_n[top] = lo_ + n2, n_ - n2
        s_st[top] = 0
    return vals[0]


@njit(cache=True, nogil=True, error_model="numpy")
def face_areas_px2(Xc, loop_vid, loop_start, loop_end, sel, fx, fy, near, area):
    """The projected area (px^2) of each face ``sel[j]``'s outer loop into ``area[sel[j]]``: the
    shoelace formula on ``u = fx X / z``, ``v = fy Y / z`` of the camera-frame vertices ``Xc`` (V, 3)
    (``z`` replaced by 1 at or in front of ``near``), ``inf`` for a face with a vertex at or in front
    of ``near`` (metres; its projection is unbounded). The numpy formulation of
    :func:`mst.pipeline.tracking.visibility.projected_face_area_px2` to the bit: the same products,
    and each loop's cross products summed as ``np.add.reduceat`` does (the first term, then numpy's
    pairwise sum of the rest)."""
    n_max = 0
    for j in range(sel.shape[0]):
        n_max = max(n_max, loop_end[sel[j]] - loop_start[sel[j]])
    u = np.empty(n_max)
    v = np.empty(n_max)
    cr = np.empty(n_max)
    for j in range(sel.shape[0]):
        f = sel[j]
        a0, n = loop_start[f], loop_end[f] - loop_start[f]
        z_min = np.inf
        for q in range(n):
            vi = loop_vid[a0 + q]
            z = Xc[vi, 2]
            z_min = min(z_min, z)
            zs = z if z > near else 1.0
            u[q] = fx * Xc[vi, 0] / zs
            v[q] = fy * Xc[vi, 1] / zs
        for q in range(n):
            q1 = q + 1 if q + 1 < n else 0  # the last vertex closes the loop
            cr[q] = u[q] * v[q1] - u[q1] * v[q]
        s = cr[0] + _pairwise_sum(cr, 1, n - 1) if n > 1 else cr[0]
        area[f] = np.inf if z_min <= near else 0.5 * abs(s)


@njit(cache=True, nogil=True, error_model="numpy")
def mat3_kernel(X, M, t, add_t, out):
    """``out = X @ M.T (+ t)`` for (N, 3) points, as :func:`mst.pipeline.tracking.depth_buffer._mat3`'s
    numpy formulation sums it (``(x0 m0 + x1 m1) + x2 m2``, then ``+ t``): the same bits, no temporaries."""
    for i in range(X.shape[0]):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        for j in range(3):
            s = (x0 * M[j, 0] + x1 * M[j, 1]) + x2 * M[j, 2]
            out[i, j] = s + t[j] if add_t else s


@njit(cache=True, nogil=True, error_model="numpy")
def frustum_cull(center, radius, sel, R, t, planes, near, far, out):
    """``out[sel[j]] = True`` for each face ``sel[j]`` whose bounding sphere (``center`` (F, 3) model
    frame, ``radius`` (F,) m) reaches into the view frustum: ``near - r <= z <= far + r`` and on the
    inner side of the 4 side ``planes`` (4, 3) within ``r`` (the test of
    :func:`mst.pipeline.tracking.visibility.frustum_faces`; the centre moved to the camera frame as
    ``_mat3`` does, each plane's dot product in a fixed order, so a face's answer can differ from
    numpy's BLAS product only where its sphere touches a plane within rounding)."""
    for j in range(sel.shape[0]):
        f = sel[j]
        x0, x1, x2 = center[f, 0], center[f, 1], center[f, 2]
        c0 = (x0 * R[0, 0] + x1 * R[0, 1]) + x2 * R[0, 2] + t[0]
        c1 = (x0 * R[1, 0] + x1 * R[1, 1]) + x2 * R[1, 2] + t[1]
        c2 = (x0 * R[2, 0] + x1 * R[2, 1]) + x2 * R[2, 2] + t[2]
        r = radius[f]
        ok = c2 >= near - r and c2 <= far + r
        for p in range(4):
            if ok and (c0 * planes[p, 0] + c1 * planes[p, 1]) + c2 * planes[p, 2] < -r:
                ok = False
        out[f] = ok


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _running_sum(a, n):
    """``a[0] + a[1] + ... + a[n - 1]`` left to right (numpy's add.reduce over a strided axis)."""
    s = a[0]
    for k in range(1, n):
        s += a[k]
    return s


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear_at(img, u, v):
    """``edgelets._bilinear`` at one point: ``img`` (H, W) read in float64, ``u, v`` clipped to the image."""
    H, W = img.shape
    u = min(max(u, 0.0), W - 1.001)
    v = min(max(v, 0.0), H - 1.001)
    i0 = int(np.floor(v))
    j0 = int(np.floor(u))
    a = v - i0
    b = u - j0
    return ((((1 - a) * (1 - b)) * np.float64(img[i0, j0]) + ((1 - a) * b) * np.float64(img[i0, j0 + 1]))
            + (a * (1 - b)) * np.float64(img[i0 + 1, j0])) + (a * b) * np.float64(img[i0 + 1, j0 + 1])


@njit(cache=True, nogil=True, error_model="numpy")
def contour_crossings(img, uv, n_out, offset, normal, sgn, t, ramp_idx, tc_ramp, den, tm, bg_idx, win_idx, step,
                      side_tol_min, out):
    """The sub-pixel contour crossings of :func:`mst.pipeline.tracking.render_edges.crossing_offsets` (its
    docstring), its numpy formulation's operations in their order (the bilinear profile of ``edgelets._bilinear``
    on the float32 image; its sums over the profile run one term after the other, as numpy reduces the strided
    last axis of a fancy-indexed array): ``out`` (N, C) the moved offsets, NaN where none.

    ``img`` (H, W) uint8 or float32; ``uv``, ``n_out``, ``normal`` (N, 2); ``offset`` (N, C) (NaN: no candidate); ``sgn``
    (N,) the sign of ``n_out . normal``; ``t`` (T,) the profile's abscissae (px along ``n_out``), ``ramp_idx``,
    ``bg_idx``, ``win_idx`` the indices of its ramp, background and crossing window; ``tc_ramp`` the ramp's
    ``t - tm`` (``tm`` their mean) and ``den`` the sum of their squares."""
    N, C = offset.shape
    T = t.shape[0]
    prof = np.empty(T)
    buf = np.empty(T)
    nr, nb, nw = ramp_idx.shape[0], bg_idx.shape[0], win_idx.shape[0]
    d = np.empty(nw)
    for i in range(N):
        for c in range(C):
            off = offset[i, c]
            if not np.isfinite(off):
                out[i, c] = np.nan
                continue
            cu = uv[i, 0] + off * normal[i, 0]
            cv = uv[i, 1] + off * normal[i, 1]
            for k in range(T):
                prof[k] = _bilinear_at(img, cu + t[k] * n_out[i, 0], cv + t[k] * n_out[i, 1])
            for k in range(nr):
                buf[k] = prof[ramp_idx[k]]
            mp = _running_sum(buf, nr) / nr
            for k in range(nr):
                buf[k] = (buf[k] - mp) * tc_ramp[k]
            bb = _running_sum(buf, nr) / den
            aa = mp - bb * tm
            for k in range(nb):
                buf[k] = prof[bg_idx[k]]
            g = _running_sum(buf, nb) / nb
            for k in range(nw):
                d[k] = prof[win_idx[k]] - 0.5 * ((aa + bb * t[win_idx[k]]) + g)
            changes = 0
            j = -1
            for k in range(nw - 1):
                if np.sign(d[k + 1]) != np.sign(d[k]):
                    changes += 1
                    if j < 0:
                        j = k
            if changes == 1 and abs(aa - g) > side_tol_min:
                p0, p1 = d[j], d[j + 1]
                out[i, c] = off + sgn[i] * (t[win_idx[j]] + step * p0 / (p0 - p1))
            else:
                out[i, c] = np.nan
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def contour_sides(img, ref_img, uv, uv_ref, n_out, offset, normal, side_px, side_tol, side_tol_min, ok):
    """The object-side test of :func:`mst.pipeline.tracking.render_edges.contour_side_test` (its docstring), its
    numpy formulation's operations in their order: ``ok`` (N, C) bool. ``uv_ref`` (N, 2) the samples projected at
    the reference pose, ``side_px`` the two read-in distances (px), ``offset`` (N, C) (read through
    ``numpy.nan_to_num``)."""
    N, C = offset.shape
    d0, d1 = side_px[0], side_px[1]
    for i in range(N):
        nx, ny = n_out[i, 0], n_out[i, 1]
        ru, rv = uv_ref[i, 0], uv_ref[i, 1]
        ref_in = (_bilinear_at(ref_img, ru - d0 * nx, rv - d0 * ny) + _bilinear_at(ref_img, ru - d1 * nx, rv - d1 * ny)) / 2
        ref_out = (_bilinear_at(ref_img, ru + d0 * nx, rv + d0 * ny) + _bilinear_at(ref_img, ru + d1 * nx, rv + d1 * ny)) / 2
        tol = max(side_tol * abs(ref_in - ref_out), side_tol_min)
        for c in range(C):
            off = offset[i, c]
            if np.isnan(off):  # numpy.nan_to_num's
                off = 0.0
            elif np.isinf(off):
                off = 1.7976931348623157e308 if off > 0 else -1.7976931348623157e308
            cu = uv[i, 0] + off * normal[i, 0]
            cv = uv[i, 1] + off * normal[i, 1]
            g_in = (_bilinear_at(img, cu - d0 * nx, cv - d0 * ny) + _bilinear_at(img, cu - d1 * nx, cv - d1 * ny)) / 2
            ok[i, c] = abs(g_in - ref_in) <= tol
    return ok


@njit(cache=True, nogil=True, error_model="numpy")
def blur_sobel_f32(img, k, gx, gy):
    """Separable blur of ``img`` (H, W) float32 by the kernel ``k`` (2r+1,) float32, rows then columns, then the
    3x3 Sobel derivatives of the blurred image into ``gx``, ``gy`` (H, W) float32 (x: ``[-1 0 1]`` across,
    ``[1 2 1]`` down; y transposed); borders reflected without the edge pixel (OpenCV's default
    ``BORDER_REFLECT_101``). Each output a float32 sum in a fixed order (the taps in ``k``'s order; Sobel
    ``(d[-1] + 2 d[0]) + d[1]``): the same bits on every CPU, where ``cv2.GaussianBlur`` and ``cv2.Sobel`` on
    float32 pick SIMD code (and its summation order) by CPU. Needs H, W > r."""
    H, W = img.shape
    r = k.shape[0] // 2
    pad = np.empty(W + 2 * r, np.float32)
    tmp = np.empty((H + 2 * r, W), np.float32)
    for i in range(H):  # rows: the padded row, then the taps in order, vectorised across the row
        for j in range(W):
            pad[j + r] = img[i, j]
        for m in range(r):
            pad[r - 1 - m] = img[i, m + 1]
            pad[W + r + m] = img[i, W - 2 - m]
        o = tmp[i + r]
        for j in range(W):
            o[j] = k[0] * pad[j]
        for m in range(1, 2 * r + 1):
            km = k[m]
            for j in range(W):
                o[j] = o[j] + km * pad[j + m]
    for m in range(r):  # the rows reflected above and below
        tmp[r - 1 - m] = tmp[r + m + 1]
        tmp[H + r + m] = tmp[H + r - 2 - m]
    b = np.empty((H + 2, W + 2), np.float32)  # the blurred image with a reflected 1-px border (Sobel's)
    for i in range(H):
        o = b[i + 1]
        for j in range(W):
            o[j + 1] = k[0] * tmp[i, j]
        for m in range(1, 2 * r + 1):
            km = k[m]
            src = tmp[i + m]
            for j in range(W):
                o[j + 1] = o[j + 1] + km * src[j]
        o[0] = o[2]
        o[W + 1] = o[W - 1]
    b[0] = b[2]
    b[H + 1] = b[H - 1]
    two = np.float32(2.0)
    for i in range(H):
        for j in range(W):
            gx[i, j] = ((b[i, j + 2] - b[i, j]) + two * (b[i + 1, j + 2] - b[i + 1, j])) + (b[i + 2, j + 2] - b[i + 2, j])
            gy[i, j] = ((b[i + 2, j] - b[i, j]) + two * (b[i + 2, j + 1] - b[i, j + 1])) + (b[i + 2, j + 2] - b[i, j + 2])
