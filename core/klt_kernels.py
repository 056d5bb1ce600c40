"""Numba kernel of the KLT front end (issue #14): pyramidal Lucas-Kanade on pyramids built once per frame.

OpenCV's ``calcOpticalFlowPyrLK`` rebuilds both images' pyramids (and the first one's Scharr
derivatives on every level) on each call, and its Python binding takes images only, not the
pyramids its C++ API accepts: a forward-backward check built every pyramid twice, and the
previous frame's once more on the next frame. Here each frame's pyramid is built once
(:func:`mst.core.klt.build_pyramid`: ``cv2.pyrDown``, as OpenCV's ``buildOpticalFlowPyramid``)
and :func:`lk_track` reads the Scharr derivatives only in the windows of the tracked points.

The algorithm is OpenCV's (Bouguet's pyramidal LK): per level from the coarsest, the window of
the previous image around the point (bilinear, its Scharr gradient), the spatial gradient matrix
and its smallest eigenvalue test, then Newton steps on the next image until the step is below
``eps`` or ``max_iter`` steps were taken (a step that undoes the previous one is halved and ends
the level). Differences: float64 arithmetic instead of OpenCV's 14-bit fixed-point interpolation,
replicated instead of reflected borders, and a point whose tracked position lies outside the
image is refused (OpenCV keeps those within a window of the border, matched against its
reflected border). Tracked positions agree with OpenCV's within its stopping step
(tests/test_core_klt.py). No fastmath, sums in a fixed order: the same on every CPU.

A pyramid is the base image (flat), one flat uint8 buffer of the coarser levels (row-major) and
an ``(L + 1, 3)`` int64 table of each level's offset, height and width. Pixels: (u, v) of the base image; level ``l`` holds
``(u, v) / 2**l`` (OpenCV's convention).
"""

from __future__ import annotations

import numpy as np
from numba import njit

W_BITS = 14  # fixed-point bits of the bilinear weights (OpenCV's)
#: unsigned indices in the window loops: numba checks a signed index for wrap-around (negative
#: values count from the end), which kept LLVM from vectorising them (about 10x slower)
U = np.uint64


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _patch(buf, off, H, W, y0, x0, n, S, P):
    """``P[r * S + c]`` = pixel (x0 + c, y0 + r) of a level (int32), ``r, c < n``, coordinates
    clamped to the image (replicated border)."""
    if x0 >= 0 and y0 >= 0 and x0 + n <= W and y0 + n <= H:
        for r in range(n):
            row = U(off + (y0 + r) * W + x0)
            pr = U(r * S)
            for c in range(U(n)):
                P[pr + c] = np.int32(buf[row + c])
        return
    for r in range(n):
        y = min(max(y0 + r, 0), H - 1)
        row_s = off + y * W
        # not ``c``, ``row`` (uint64 above): numba.pycc types a name once per function
        for cs in range(n):
            x = min(max(x0 + cs, 0), W - 1)
            P[r * S + cs] = np.int32(buf[row_s + x])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _weights(a, b):
    """Bilinear weights of the fractional offsets (a, b), fixed point (W_BITS), summing to 2^W_BITS."""
    one = 1 << W_BITS
    w00 = int(np.rint((1.0 - a) * (1.0 - b) * one))
    w01 = int(np.rint(a * (1.0 - b) * one))
    w10 = int(np.rint((1.0 - a) * b * one))
    return np.int32(w00), np.int32(w01), np.int32(w10), np.int32(one - w00 - w01 - w10)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lk_body(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, win, max_level, max_iter, eps, min_eig,
             out, status):
    """Track ``pts`` (N, 2) float64 px from the pyramid ``(pbase, pbuf, ptab)`` to ``(nbase, nbuf, ntab)``
    (the base level flat, the coarser levels, the table of :class:`mst.core.klt.Pyramid`).

    ``guess`` (N, 2): start positions in the next image when ``use_guess`` (else the points
    themselves). ``win``: the square window's side (px, every level); ``max_level``: the coarsest
    level used (at most the pyramids' ``len(tab) - 1``); ``eps``: the step (px) below which a level
    stops; ``min_eig``: the smallest eigenvalue of the window's mean gradient matrix below which a
    point is refused (gray levels^2 / px^2). Writes ``out`` (N, 2) and ``status`` (N,) uint8
    (1: tracked, 0: refused at the base level or left the image).

    Integer arithmetic as OpenCV's: gray levels x 32 (bilinear, W_BITS - 5 bits dropped with
    rounding), the unnormalised Scharr gradient (32 x gray levels / px); the window sums are exact
    (int64), so their order does not matter and the compiler may vectorise them."""
    half = (win - 1) * 0.5
    n_w = win * win
    ws = win + 1  # the window's pixels and their right / lower neighbours (bilinear)
    # flat patches, one row stride S for all (the loops run over whole patches, long enough to
    # vectorise; the columns beyond a patch's width are computed and masked out)
    S = win + 3
    P = np.zeros(S * S + 2 * S + 4, np.int32)  # previous level around the window (+1 px for Scharr)
    Q = np.zeros(ws * S + S + 2, np.int32)  # next level under the window
    gx = np.zeros(ws * S + S + 2, np.int32)
    gy = np.zeros(ws * S + S + 2, np.int32)
    Ip = np.zeros(win * S, np.int32)
    Gx = np.zeros(win * S, np.int32)
    Gy = np.zeros(win * S, np.int32)
    mask = np.zeros(win * S, np.int32)
    for km in range(win * S):  # not ``k``: the loops below count in uint64, and numba.pycc types a name once
        mask[km] = 1 if km % S < win else 0
    eps2 = eps * eps
    r5 = np.int32(1 << (W_BITS - 6))
    rw = np.int32(1 << (W_BITS - 1))
    sc = 1.0 / (32.0 * 32.0)  # window sums -> gray levels and px
    u1, u2, uS, uS2 = U(1), U(2), U(S), U(2 * S)
    for i in range(pts.shape[0]):
        st = 1
        nx, ny = 0.0, 0.0
        for level in range(max_level, -1, -1):
            scale = 1.0 / (1 << level)
            off, H, W = ptab[level, 0], ptab[level, 1], ptab[level, 2]
            noff, nH, nW = ntab[level, 0], ntab[level, 1], ntab[level, 2]
            px, py = pts[i, 0] * scale - half, pts[i, 1] * scale - half  # window corner in the previous level
            if level == max_level:
                if use_guess:
                    nx, ny = guess[i, 0] * scale - half, guess[i, 1] * scale - half
                else:
                    nx, ny = px, py
            else:
                nx, ny = (nx + half) * 2.0 - half, (ny + half) * 2.0 - half
            ix, iy = int(np.floor(px)), int(np.floor(py))
            if ix < -win or ix >= W or iy < -win or iy >= H:
                if level == 0:
                    st = 0
                continue
            w00, w01, w10, w11 = _weights(px - ix, py - iy)
            _patch(pbase if level == 0 else pbuf, off, H, W, iy - 1, ix - 1, win + 3, S, P)
            for k in range(U(ws * S)):  # Scharr 3-10-3 at the window's pixels and neighbours
                gx[k] = 3 * (P[k + u2] - P[k] + P[k + uS2 + u2] - P[k + uS2]) + 10 * (P[k + uS + u2] - P[k + uS])
                gy[k] = 3 * (P[k + uS2] - P[k] + P[k + uS2 + u2] - P[k + u2]) + 10 * (P[k + uS2 + u1] - P[k + u1])
            for k in range(U(win * S)):
                Ip[k] = (w00 * P[k + uS + u1] + w01 * P[k + uS + u2] + w10 * P[k + uS2 + u1] + w11 * P[k + uS2 + u2]
                         + r5) >> (W_BITS - 5)
                Gx[k] = mask[k] * ((w00 * gx[k] + w01 * gx[k + u1] + w10 * gx[k + uS] + w11 * gx[k + uS + u1] + rw) >> W_BITS)
                Gy[k] = mask[k] * ((w00 * gy[k] + w01 * gy[k + u1] + w10 * gy[k + uS] + w11 * gy[k + uS + u1] + rw) >> W_BITS)
            A11, A12, A22 = 0, 0, 0
            for k in range(U(win * S)):
                A11 += np.int64(Gx[k]) * Gx[k]
                A12 += np.int64(Gx[k]) * Gy[k]
                A22 += np.int64(Gy[k]) * Gy[k]
            a11, a12, a22 = A11 * sc, A12 * sc, A22 * sc  # (gray levels / px)^2
            D = a11 * a22 - a12 * a12
            lam = (a22 + a11 - np.sqrt((a11 - a22) * (a11 - a22) + 4.0 * a12 * a12)) / (2.0 * n_w)
            if lam < min_eig or D < 1e-12:
                if level == 0:
                    st = 0
                continue
            iD = 1.0 / D
            pdx, pdy = 0.0, 0.0
            for j in range(max_iter):
                jx, jy = int(np.floor(nx)), int(np.floor(ny))
                if jx < -win or jx >= nW or jy < -win or jy >= nH:
                    if level == 0:
                        st = 0
                    break
                v00, v01, v10, v11 = _weights(nx - jx, ny - jy)
                _patch(nbase if level == 0 else nbuf, noff, nH, nW, jy, jx, ws, S, Q)
                b1, b2 = 0, 0
                for k in range(U(win * S)):
                    d = (((v00 * Q[k] + v01 * Q[k + u1] + v10 * Q[k + uS] + v11 * Q[k + uS + u1] + r5) >> (W_BITS - 5))
                         - Ip[k])
                    b1 += np.int64(d) * Gx[k]
                    b2 += np.int64(d) * Gy[k]
                e1, e2 = b1 * sc, b2 * sc
                dx = (a12 * e2 - a22 * e1) * iD
                dy = (a12 * e1 - a11 * e2) * iD
                nx += dx
                ny += dy
                if dx * dx + dy * dy <= eps2:
                    break
                if j > 0 and abs(dx + pdx) < 0.01 and abs(dy + pdy) < 0.01:
                    nx -= dx * 0.5
                    ny -= dy * 0.5
                    break
                pdx, pdy = dx, dy
        ux, uy = nx + half, ny + half
        out[i, 0], out[i, 1] = ux, uy
        # a point tracked beyond the image was matched against the replicated border, not the image
        status[i] = st if 0.0 <= ux <= ntab[0, 2] - 1 and 0.0 <= uy <= ntab[0, 1] - 1 else 0


@njit(cache=True, nogil=True, error_model="numpy")
def lk_track(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, win, max_level, max_iter, eps, min_eig,
             out, status):
    """:func:`_lk_body` for any window (see there)."""
    _lk_body(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, win, max_level, max_iter, eps, min_eig, out,
             status)


# the two windows in use compiled with the size as a constant (the loops' trip counts known: 17 %
# less time at 5 px, the same results)
@njit(cache=True, nogil=True, error_model="numpy")
def lk_track_5(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, max_level, max_iter, eps, min_eig, out, status):
    """:func:`_lk_body` with a 5 px window (ViSP's teabox.xml)."""
    _lk_body(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, 5, max_level, max_iter, eps, min_eig, out,
             status)


@njit(cache=True, nogil=True, error_model="numpy")
def lk_track_11(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, max_level, max_iter, eps, min_eig, out, status):
    """:func:`_lk_body` with an 11 px window (the default)."""
    _lk_body(pbase, pbuf, ptab, nbase, nbuf, ntab, pts, guess, use_guess, 11, max_level, max_iter, eps, min_eig, out,
             status)
