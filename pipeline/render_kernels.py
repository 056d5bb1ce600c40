"""Numba per-ray kernels of :class:`~mst.pipeline.render.ShadedRenderer` (compiled once, cached on disk).

One pass per ray does what used to be a dozen numpy passes with temporaries: the model-frame ray
direction from camera-frame ``(x, y, 1)``, sky colour on a miss, flat colour or procedural texture
(mip-mapped bilinear lookups in an atlas, optional low-frequency modulation) times the triangle's
Lambertian shade on a hit, and the mean over each pixel's sub-pixel samples (edge anti-aliasing).
Everything is float32 and single-threaded (the renderer's one-core budget); no fastmath, so the
output is reproducible bit for bit.

Units: ray directions have camera z = 1, so the ray parameter ``t`` is the camera z-depth (metres);
texture coordinates are level-0 texels; colours are linear RGB in [0, 1].
"""

from __future__ import annotations

import numpy as np
from numba import njit

F32 = np.float32


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear(atlas, ti, x, y):
    """Bilinear sample (r, g, b), 0..255, of atlas ``ti`` at atlas pixel coordinates (x, y)."""
    H = atlas.shape[1]
    W = atlas.shape[2]
    xf = np.floor(x)
    yf = np.floor(y)
    fx = x - xf
    fy = y - yf
    x0 = min(max(int(xf), 0), W - 1)
    y0 = min(max(int(yf), 0), H - 1)
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    gx = F32(1.0) - fx
    gy = F32(1.0) - fy
    a = atlas[ti]
    r0 = gx * F32(a[y0, x0, 0]) + fx * F32(a[y0, x1, 0])
    g0 = gx * F32(a[y0, x0, 1]) + fx * F32(a[y0, x1, 1])
    b0 = gx * F32(a[y0, x0, 2]) + fx * F32(a[y0, x1, 2])
    r1 = gx * F32(a[y1, x0, 0]) + fx * F32(a[y1, x1, 0])
    g1 = gx * F32(a[y1, x0, 1]) + fx * F32(a[y1, x1, 1])
    b1 = gx * F32(a[y1, x0, 2]) + fx * F32(a[y1, x1, 2])
    return gy * r0 + fy * r1, gy * g0 + fy * g1, gy * b0 + fy * b1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _wrap(a, size):
    """``a`` modulo ``size`` (float32, in [0, size])."""
    return a - np.floor(a * (F32(1.0) / size)) * size


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def texture_sample(atlas, ti, size, nlev, level_xy, u, v, foot, mip):
    """Colour (r, g, b), 0..255, of texture ``ti`` at level-0 texel coordinates (u, v).

    ``mip``: trilinear-ish ("brilinear") mip-mapping from the footprint ``foot`` (level-0 texels):
    level ``floor(lod)``, blended with the next one over the middle half of each level step.
    Without ``mip``: plain bilinear in level 0. Texel centres are at integer (u, v).
    """
    sz = F32(size)
    uw = _wrap(u, sz) + F32(0.5)
    vw = _wrap(v, sz) + F32(0.5)
    lvl = 0
    w = F32(0.0)
    scale = F32(1.0)
    if mip:
        # lod = log2(footprint) = lvl + log2(m), m in [1, 2); log2(m) ~ x (1.3465 - 0.3465 x), x = m - 1
        m = foot
        while m >= F32(2.0) and lvl < nlev - 1:
            m *= F32(0.5)
            scale *= F32(0.5)
            lvl += 1
        if lvl < nlev - 1:
            xm = max(m, F32(1.0)) - F32(1.0)
            frac = xm * (F32(1.3465) - F32(0.3465) * xm)
            w = min(max((frac - F32(0.25)) * F32(2.0), F32(0.0)), F32(1.0))
            if w >= F32(1.0):
                lvl += 1
                scale *= F32(0.5)
                w = F32(0.0)
    x = uw * scale + (level_xy[ti, lvl, 0] - F32(0.5))
    y = vw * scale + (level_xy[ti, lvl, 1] - F32(0.5))
    r, g, b = _bilinear(atlas, ti, x, y)
    if w > F32(0.0):
        scale2 = scale * F32(0.5)
        x2 = uw * scale2 + (level_xy[ti, lvl + 1, 0] - F32(0.5))
        y2 = vw * scale2 + (level_xy[ti, lvl + 1, 1] - F32(0.5))
        r2, g2, b2 = _bilinear(atlas, ti, x2, y2)
        r += (r2 - r) * w
        g += (g2 - g) * w
        b += (b2 - b) * w
    return r, g, b


@njit(cache=True, nogil=True, error_model="numpy")
def sample_points(atlas, ti, size, nlev, level_xy, u, v, foot, mip, out):
    """:func:`texture_sample` over arrays: ``out`` (N, 3) float32 in [0, 1]."""
    for i in range(len(u)):
        r, g, b = texture_sample(atlas, ti, size, nlev, level_xy, F32(u[i]), F32(v[i]), F32(foot[i]), mip)
        out[i, 0] = r * F32(1.0 / 255.0)
        out[i, 1] = g * F32(1.0 / 255.0)
        out[i, 2] = b * F32(1.0 / 255.0)


@njit(cache=True, nogil=True, error_model="numpy")
def shade_rays(x, y, inv_norm, R, t, prim, group, flat, tex_of_tri, u0, v0, a_uv, nrm, shade_tri, sky,
               inv_focal, atlas, tex_size, tex_inv_texel, tex_nlev, level_xy, mod_idx, mod_R, out):
    """Colour of rays from one camera centre; ``out[i]`` is the mean over rays ``i*group .. i*group+group-1``.

    ``x, y``: (N,) camera-frame directions ``(x, y, 1)``; ``inv_norm``: their 1/|d| (N,), or an empty
    array to compute it here; ``R`` (3, 3) float32 R_model_cam;
    ``t``/``prim``: cast results (prim >= M = number of triangles, or the uint32 invalid id, = miss).
    Per triangle: ``flat`` (M+1, 3) shaded flat colour, ``tex_of_tri`` (M,) texture index or -1,
    ``u0, v0`` (M,) uv (metres, wrapped to the tile) of the camera centre, ``a_uv`` (M, 6) model-frame
    linear forms of u and v, ``nrm`` (M, 3) unit normals, ``shade_tri`` (M,) Lambertian factor.
    ``sky`` (3, 3): texture-frame up (model coordinates), horizon and zenith colours.
    Textures (index k): ``atlas[k]`` uint8, ``tex_size``, ``tex_inv_texel`` (1/m), ``tex_nlev``,
    ``level_xy``; ``mod_idx[k]`` the modulation texture (-1: none) looked up at ``mod_R[k] @ (u, v)``.
    """
    M = len(tex_of_tri)
    inv_g = F32(1.0) / F32(group)
    n_out = len(x) // group
    have_inv = len(inv_norm) == len(x)
    for g in range(n_out):
        ar = F32(0.0)
        ag = F32(0.0)
        ab = F32(0.0)
        for s in range(group):
            i = g * group + s
            xi = x[i]
            yi = y[i]
            dx = R[0, 0] * xi + R[0, 1] * yi + R[0, 2]
            dy = R[1, 0] * xi + R[1, 1] * yi + R[1, 2]
            dz = R[2, 0] * xi + R[2, 1] * yi + R[2, 2]
            p = np.int64(prim[i])
            if p >= M:
                inv_n = inv_norm[i] if have_inv else F32(1.0) / np.sqrt(F32(1.0) + xi * xi + yi * yi)
                el = (sky[0, 0] * dx + sky[0, 1] * dy + sky[0, 2] * dz) * inv_n
                el = min(max(el, F32(0.0)), F32(1.0))
                ar += sky[1, 0] + (sky[2, 0] - sky[1, 0]) * el
                ag += sky[1, 1] + (sky[2, 1] - sky[1, 1]) * el
                ab += sky[1, 2] + (sky[2, 2] - sky[1, 2]) * el
                continue
            k = tex_of_tri[p]
            if k < 0:
                ar += flat[p, 0]
                ag += flat[p, 1]
                ab += flat[p, 2]
                continue
            tt = t[i]
            um = u0[p] + tt * (a_uv[p, 0] * dx + a_uv[p, 1] * dy + a_uv[p, 2] * dz)
            vm = v0[p] + tt * (a_uv[p, 3] * dx + a_uv[p, 4] * dy + a_uv[p, 5] * dz)
            inv_n = inv_norm[i] if have_inv else F32(1.0) / np.sqrt(F32(1.0) + xi * xi + yi * yi)
            cosi = abs(nrm[p, 0] * dx + nrm[p, 1] * dy + nrm[p, 2] * dz) * inv_n
            foot_m = tt * inv_focal / np.sqrt(max(cosi, F32(0.05)))
            it = tex_inv_texel[k]
            cr, cg, cb = texture_sample(atlas, k, tex_size[k], tex_nlev[k], level_xy, um * it, vm * it, foot_m * it, True)
            sh = shade_tri[p] * F32(1.0 / 255.0)
            mk = mod_idx[k]
            if mk >= 0:
                mu = mod_R[k, 0, 0] * um + mod_R[k, 0, 1] * vm
                mv = mod_R[k, 1, 0] * um + mod_R[k, 1, 1] * vm
                mr, mg, mb = texture_sample(atlas, mk, tex_size[mk], tex_nlev[mk], level_xy, mu, mv, F32(1.0), False)
                sh2 = sh * F32(1.0 / 255.0)
                ar += cr * mr * sh2
                ag += cg * mg * sh2
                ab += cb * mb * sh2
            else:
                ar += cr * sh
                ag += cg * sh
                ab += cb * sh
        if group == 1:
            out[g, 0] = ar
            out[g, 1] = ag
            out[g, 2] = ab
        else:
            out[g, 0] = ar * inv_g
            out[g, 1] = ag * inv_g
            out[g, 2] = ab * inv_g


@njit(cache=True, nogil=True, error_model="numpy")
def build_rays(o, R, x, y, idx, rays):
    """Rows ``rays[j] = (o, R @ (x[idx[j]], y[idx[j]], 1))`` (float32 (n, 6), Open3D's ray layout);
    ``idx`` None-like (length 0) means all rays in order."""
    n = len(rays)
    use_idx = len(idx) > 0
    for j in range(n):
        i = idx[j] if use_idx else j
        xi = x[i]
        yi = y[i]
        rays[j, 0] = o[0]
        rays[j, 1] = o[1]
        rays[j, 2] = o[2]
        rays[j, 3] = R[0, 0] * xi + R[0, 1] * yi + R[0, 2]
        rays[j, 4] = R[1, 0] * xi + R[1, 1] * yi + R[1, 2]
        rays[j, 5] = R[2, 0] * xi + R[2, 1] * yi + R[2, 2]


@njit(cache=True, nogil=True, error_model="numpy")
def fill_planar_cells(H, W, ys, xs, pcst, plane_id, num_tri, nrm, R, x, y, t, prim, rest):
    """Primary hits from a coarse grid (see ``ShadedRenderer.primary_hits``).

    ``pcst`` (len(ys), len(xs)) uint32 triangle ids cast at rows ``ys`` and columns ``xs``. A pixel
    in a cell whose 4 corners see one plane gets that plane's exact ray-plane depth
    ``num_tri[p] / (n_p . d)`` and the top-left corner's triangle; a cell of 4 misses is sky.
    Other pixels' indices go to ``rest``; returns how many.
    """
    M = len(num_tri)
    ny = len(ys)
    nx = len(xs)
    n_rest = 0
    for i in range(H):
        ki = min(i // 2, ny - 2)
        for j in range(W):
            kj = min(j // 2, nx - 2)
            pa = np.int64(pcst[ki, kj])
            la = plane_id[min(pa, M)]
            lb = plane_id[min(np.int64(pcst[ki + 1, kj]), M)]
            lc = plane_id[min(np.int64(pcst[ki, kj + 1]), M)]
            ld = plane_id[min(np.int64(pcst[ki + 1, kj + 1]), M)]
            q = i * W + j
            if la == lb and la == lc and la == ld:
                if pa >= M:
                    t[q] = np.inf
                    prim[q] = pcst[ki, kj]
                else:
                    xi = x[q]
                    yi = y[q]
                    dx = R[0, 0] * xi + R[0, 1] * yi + R[0, 2]
                    dy = R[1, 0] * xi + R[1, 1] * yi + R[1, 2]
                    dz = R[2, 0] * xi + R[2, 1] * yi + R[2, 2]
                    t[q] = num_tri[pa] / (nrm[pa, 0] * dx + nrm[pa, 1] * dy + nrm[pa, 2] * dz)
                    prim[q] = pcst[ki, kj]
            else:
                rest[n_rest] = q
                n_rest += 1
    return n_rest


@njit(cache=True, nogil=True, error_model="numpy")
def edge_mask(pc, t, plane_id, nrm, mat, cos_tol, rel_jump, edge):
    """Silhouette/crease pixels (see ``ShadedRenderer.edge_mask``): ``pc`` (H, W) int64 triangle ids with
    M = miss, ``t`` (H, W) float32 depths; sets ``edge`` (H, W) bool; returns the count."""
    H, W = pc.shape
    M = len(nrm)
    for i in range(H):
        for j in range(W):
            pa = pc[i, j]
            la = plane_id[pa]
            for k in range(4):
                if k == 0:
                    i2, j2 = i, j + 1
                elif k == 1:
                    i2, j2 = i + 1, j
                elif k == 2:
                    i2, j2 = i + 1, j + 1
                else:
                    i2, j2 = i + 1, j - 1
                if i2 >= H or j2 < 0 or j2 >= W:
                    continue
                pb = pc[i2, j2]
                if plane_id[pb] == la:
                    continue
                sep = pa == M or pb == M
                if not sep:
                    sep = mat[pa] != mat[pb]
                if not sep:
                    cosn = nrm[pa, 0] * nrm[pb, 0] + nrm[pa, 1] * nrm[pb, 1] + nrm[pa, 2] * nrm[pb, 2]
                    sep = abs(cosn) < cos_tol
                if not sep:
                    ta = t[i, j]
                    tb = t[i2, j2]
                    sep = abs(ta - tb) > rel_jump * min(ta, tb)
                if sep:
                    edge[i, j] = True
                    edge[i2, j2] = True
    n = 0
    for i in range(H):
        for j in range(W):
            if edge[i, j]:
                n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def depth_ids(t, prim, M, depth, ids):
    """``depth`` = t where hit else 0 (float32), ``ids`` = triangle id where hit else -1 (int64)."""
    for i in range(len(t)):
        p = np.int64(prim[i])
        if p < M:
            depth[i] = t[i]
            ids[i] = p
        else:
            depth[i] = 0.0
            ids[i] = -1


@njit(cache=True, nogil=True, error_model="numpy")
def subpixel_dirs(e_idx, W, pat, fx, fy, cx, cy, sx, sy):
    """Camera-frame directions (x, y, 1) of the sub-pixel samples ``pat`` (S, 2) (pixels, float64) of the
    pixels ``e_idx`` (row-major, width ``W``) of an undistorted pinhole camera: ``sx, sy`` (len(e_idx) * S,) float32."""
    S = len(pat)
    for j in range(len(e_idx)):
        u = float(e_idx[j] % W)
        v = float(e_idx[j] // W)
        for s in range(S):
            sx[j * S + s] = np.float32((u + pat[s, 0] - cx) / fx)
            sy[j * S + s] = np.float32((v + pat[s, 1] - cy) / fy)


@njit(cache=True, nogil=True, error_model="numpy")
def encode_bgr8(rgb, noise_bits, sigma, out):
    """8-bit BGR image ``out`` (H, W, 3) uint8 from linear RGB ``rgb`` (H, W, 3) float32 in [0, 1]:
    ``clip(255 rgb + sigma n + 0.5, 0, 255)`` truncated, with sensor noise ``n`` ~ N(0, 1) made from
    ``noise_bits`` (H, W, 3) uint32 random draws (RGB order; an empty array for no noise): the
    standardised sum of their four bytes (Irwin-Hall, 4 uniforms: Gaussian up to tails cut at 3.45 sigma)."""
    H, W, _ = rgb.shape
    has_noise = noise_bits.size == rgb.size
    inv_sd = F32(1.0 / np.sqrt(4.0 * (256.0 * 256.0 - 1.0) / 12.0))
    for i in range(H):
        for j in range(W):
            for c in range(3):
                val = rgb[i, j, c] * F32(255.0)
                if has_noise:
                    b = noise_bits[i, j, c]
                    sb = (b & 255) + ((b >> 8) & 255) + ((b >> 16) & 255) + (b >> 24)
                    val += (F32(sb) - F32(510.0)) * inv_sd * sigma
                val = min(max(val + F32(0.5), F32(0.0)), F32(255.0))
                out[i, j, 2 - c] = np.uint8(val)


@njit(cache=True, nogil=True, error_model="numpy")
def depth_to_mm(depth, out):
    """16-bit depth PNG content: ``out`` (H, W) uint16 = round(1000 depth) (metres -> millimetres, half to
    even, in float64), 0 where that is <= 0 or > 65535."""
    H, W = depth.shape
    for i in range(H):
        for j in range(W):
            mm = np.rint(np.float64(depth[i, j]) * 1000.0)
            out[i, j] = np.uint16(mm) if (mm > 0.0 and mm <= 65535.0) else np.uint16(0)
