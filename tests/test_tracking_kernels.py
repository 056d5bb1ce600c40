"""The edge tracker's numba kernels (:mod:`mst.pipeline.tracking.kernels`, issue #14) against the numpy
formulations they replaced (``search_edges_numpy``, ``reference_contrast_numpy``, ``solve_pose_numpy``).

Budget: the moving-edge convolutions are summed in float64 and rounded once to float32 (numpy's
BLAS product rounds in float32), the decisions after them are elementwise IEEE arithmetic in the
numpy formulation's order: the same matches except at rounding ties (see the test's budget). The
whole VVS solve is one kernel whose sums run in a fixed order instead of BLAS's: the same
iterations, inliers and status, the pose within rounding (see the test's budget).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mst.core.poses import inv_T, look_at, se3_exp, se3_log
from mst.pipeline.tracking import moving_edges as me
from mst.pipeline.tracking.vvs import solve_pose, solve_pose_numpy


def _scene(seed: int = 3):
    """A textured 640x480 image with a bright box, samples near its border and random ones."""
    rng = np.random.default_rng(seed)
    img = (rng.random((480, 640)) * 60).astype(np.uint8)
    cv2.rectangle(img, (200, 150), (420, 330), 190, -1)
    img = cv2.GaussianBlur(img, (5, 5), 1.0)
    n = 600
    t = rng.uniform(0, 1, n)
    uv = np.c_[200 + 220 * t, 150 + rng.normal(0, 2.5, n)]
    uv[300:] = rng.uniform([2, 2], [637, 477], (300, 2))  # some at the image border (clipped reads)
    ang = rng.uniform(0, 2 * np.pi, n)
    nrm = np.c_[np.cos(ang), np.sin(ang)]
    nrm[:150] = [0.0, 1.0]
    normal, midx = me.canonical_normals(nrm, 180)
    return img, uv, normal, midx, rng.integers(0, 12, n)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_moving_edge_search_matches_numpy(dtype):
    # The kernel sums each convolution in float64 and rounds once to float32; numpy's BLAS product
    # rounds in float32 as it goes. Budget: the convolutions within a few float32 ulps (relative
    # 1e-6 of max(|conv|, 1 gray level)); a decision differs only where two likelihoods or a
    # likelihood and a threshold are within that rounding (ties): at most 1 % of the candidate
    # slots, and a best candidate that both keep is at the same offset within 1e-4 px.
    img, uv, normal, midx, edge = _scene()
    img = img.astype(dtype)
    ref = me.reference_contrast(img, uv + 0.6, normal, midx, 5, 180)
    ref_np = me.reference_contrast_numpy(img, uv + 0.6, normal, midx, 5, 180)
    assert ref.dtype == ref_np.dtype == np.float32
    np.testing.assert_allclose(ref, ref_np, rtol=0, atol=1e-6 * max(1.0, float(np.abs(ref_np).max())))
    for r in (None, ref):
        for e in (None, edge):
            for R, C in ((8, 2), (3, 3), (0, 1)):
                kw = dict(search_range=R, threshold=12.0, mu1=0.5, mu2=0.5, size=5, n_masks=180, n_candidates=C,
                          mask_idx=midx, edge=e)
                a = me.search_edges(img, uv, normal, r, **kw)
                b = me.search_edges_numpy(img, uv, normal, r, **kw)
                assert a.likelihood.dtype == b.likelihood.dtype and a.conv.dtype == b.conv.dtype
                assert np.isfinite(b.offset).sum() > 100
                assert (np.isnan(a.offset) != np.isnan(b.offset)).mean() <= 0.01
                both = np.isfinite(a.offset[:, 0]) & np.isfinite(b.offset[:, 0])
                assert both.mean() >= 0.99 * np.isfinite(b.offset[:, 0]).mean()
                assert np.mean(np.abs(a.offset[both, 0] - b.offset[both, 0]) <= 1e-4) >= 0.99
                same = both & (np.abs(a.offset[:, 0] - b.offset[:, 0]) <= 1e-4)
                np.testing.assert_allclose(a.conv[same], b.conv[same], rtol=0,
                                           atol=1e-6 * max(1.0, float(np.abs(b.conv).max())))


def test_moving_edge_convolution_shortcuts_are_bit_exact():
    # me_convolve skips the masks' zero weights on 8-bit images and copies the convolution of a
    # position that reads the previous position's pixel: the same bits as the plain sum (four
    # float64 partial sums, pixel s of the mask into sum s % 4, rounded once to float32), written
    # out here per convolution; the float32 image (no skipping) gives the same bits too
    img, uv, normal, midx, _ = _scene()
    masks, moff = me.make_masks(5, 180)
    ks = np.arange(-8, 9, dtype=np.float64)
    conv8, keff8 = me._convolve(img, uv, normal, ks, midx, masks, moff)
    conv32, keff32 = me._convolve(img.astype(np.float32), uv, normal, ks, midx, masks, moff)
    assert conv8.tobytes() == conv32.tobytes() and keff8.tobytes() == keff32.tobytes()
    H, W = img.shape
    dup = 0
    for i in range(0, len(uv), 7):
        last = None
        for m, k in enumerate(ks):
            ix = min(max(np.rint(uv[i, 0] + k * normal[i, 0]), 2), W - 3)
            iy = min(max(np.rint(uv[i, 1] + k * normal[i, 1]), 2), H - 3)
            dup += last == (ix, iy)
            last = (ix, iy)
            a = [0.0, 0.0, 0.0, 0.0]
            for s, (dx, dy) in enumerate(moff):
                a[s % 4] += float(img[int(iy) + dy, int(ix) + dx]) * float(masks[midx[i], s])
            assert np.float32((a[0] + a[1]) + (a[2] + a[3])) == conv8[i, m]
            assert (ix - uv[i, 0]) * normal[i, 0] + (iy - uv[i, 1]) * normal[i, 1] == keff8[i, m]
    assert dup >= 20  # the copied positions were exercised


def test_edge_chunks_kernel_is_the_numpy_clustering():
    from mst.pipeline.tracking.covariance import edge_chunks, edge_chunks_numpy

    rng = np.random.default_rng(5)
    for n, n_edges, chunk in ((0, 1, 8), (1, 1, 8), (500, 40, 8), (300, 3, 1), (200, 90, 5), (64, 2, 100)):
        e = rng.integers(0, n_edges, n)
        e[: n // 2].sort()  # runs of one edge, and interleaved ids
        cl, nc = edge_chunks(e, chunk)
        cl_np, nc_np = edge_chunks_numpy(e, chunk)
        assert nc == nc_np and cl.dtype == cl_np.dtype and np.array_equal(cl, cl_np)
    e = np.array([3, -1, 3, -1])  # negative ids: the numpy formulation
    assert np.array_equal(edge_chunks(e, 1)[0], edge_chunks_numpy(e, 1)[0])


def test_canonical_normals_kernel_is_the_numpy_formulation():
    rng = np.random.default_rng(2)
    ang = np.concatenate([rng.uniform(-np.pi, np.pi, 2000), np.arange(-4, 5) * np.pi / 4])
    nrm = np.c_[np.cos(ang), np.sin(ang)]
    nrm = np.concatenate([nrm, [[-1.0, 0.0], [-1.0, -0.0], [0.0, -1.0], [1.0, -0.0], [0.0, 0.0]]])
    for n_masks in (180, 7, 1):
        a, ia = me.canonical_normals(nrm, n_masks)
        b, ib = me.canonical_normals_numpy(nrm, n_masks)
        assert a.tobytes() == b.tobytes() and ia.tobytes() == ib.tobytes()
    bad = np.array([[np.nan, 1.0], [1.0, 0.0]])  # a non-finite angle: numpy's formulation
    with np.errstate(invalid="ignore"):  # numpy's cast of the NaN angle
        assert me.canonical_normals(bad, 180)[1][1] == me.canonical_normals_numpy(bad, 180)[1][1]


def test_moving_edge_search_of_no_samples():
    img = np.zeros((50, 60), np.uint8)
    z = np.zeros((0, 2))
    m = me.search_edges(img, z, z, None, search_range=4, threshold=10.0, mu1=0.5, mu2=0.5, size=5, n_masks=180,
                        n_candidates=2, mask_idx=np.zeros(0, np.int64), edge=np.zeros(0, np.int64))
    assert m.offset.shape == (0, 2) and m.conv.shape == (0,)


K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def _box_problem(seed: int):
    """Samples on a 20 cm cube's 12 edges 1 m away; 2 candidates each: the true projection plus
    0.5 px normal noise, and a clutter edge 2-6 px off; 10 % gross outliers; KLT points on faces."""
    rng = np.random.default_rng(seed)
    c = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1)])
    E = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(np.abs(c[i] - c[j]) > 0) == 1]
    A, B = c[[e[0] for e in E]], c[[e[1] for e in E]]
    t = np.linspace(0.05, 0.95, 12)
    X = np.concatenate([A[k] + t[:, None] * (B[k] - A[k]) for k in range(len(E))])
    edge = np.repeat(np.arange(len(E)), len(t))
    T = se3_exp(np.array([0.02, -0.01, 1.0, 0.3, 0.5, 0.1]))

    def proj(P):
        Pc = P @ T[:3, :3].T + T[:3, 3]
        return Pc[:, :2] / Pc[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]

    d = proj(B) - proj(A)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.stack([-d[:, 1], d[:, 0]], 1)[edge]
    uv = proj(X)
    c0 = uv + rng.normal(0, 0.5, len(uv))[:, None] * nrm
    c1 = uv + rng.choice([-1, 1], len(uv))[:, None] * rng.uniform(2, 6, len(uv))[:, None] * nrm
    out = rng.random(len(uv)) < 0.1
    c0[out] += rng.normal(0, 8, (out.sum(), 2))
    cand = np.stack([c0, c1], 1)
    cand[rng.random(len(uv)) < 0.05, 1] = np.nan  # some samples with one candidate only
    Xk = c[rng.integers(0, 8, 30)] * rng.uniform(0.3, 1.0, (30, 1))
    uk = proj(Xk) + rng.normal(0, 0.3, (30, 2))
    T0 = se3_exp(np.array([0.004, -0.003, 0.01, 0.01, -0.008, 0.006])) @ T
    return T0, X, edge, A, B, cand, Xk, uk


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("klt", [False, True, "cap"])
def test_vvs_kernels_solve_the_numpy_pose(seed, klt):
    T0, X, edge, A, B, cand, Xk, uk = _box_problem(seed)
    kw = {"klt_X_model": Xk, "klt_uv": uk} if klt else {}
    if klt == "cap":  # the KLT information capped (0.05 x the edges': binding on this problem)
        kw["klt_info_cap"] = 0.05
        free = solve_pose(T0, K, X, edge, A, B, cand, klt_X_model=Xk, klt_uv=uk)
        capped = solve_pose(T0, K, X, edge, A, B, cand, **kw)
        assert not np.allclose(free.T_cam_model, capped.T_cam_model, rtol=0, atol=1e-9)
    for mad, spread in ((0.3, True), (1.0, False)):
        a = solve_pose(T0, K, X, edge, A, B, cand, min_mad_px=mad, edge_spread_weight=spread, **kw)
        b = solve_pose_numpy(T0, K, X, edge, A, B, cand, min_mad_px=mad, edge_spread_weight=spread, **kw)
        assert a.status is b.status and a.iters == b.iters
        # the fused solve sums in a fixed order (no BLAS): a rounding difference only. Budget:
        # ~1e-16 relative per operation, a few hundred operations per step, <= 30 steps: 1e-12
        np.testing.assert_allclose(a.T_cam_model, b.T_cam_model, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.weights, b.weights, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(a.inlier, b.inlier)
        np.testing.assert_allclose(a.W, b.W, rtol=1e-9, atol=0)
        # the edge samples' part (VVSResult.W_edges: W itself without KLT points) and the covariance from it
        np.testing.assert_allclose(a.W_edges, b.W_edges, rtol=1e-9, atol=0)
        np.testing.assert_allclose(a.cov_classical, b.cov_classical, rtol=1e-6, atol=0)
        if klt:
            assert not np.array_equal(a.W_edges, a.W)
        else:
            assert np.array_equal(a.W_edges, a.W) and np.array_equal(b.W_edges, b.W)
        assert abs(a.rms_px - b.rms_px) <= 1e-9 * b.rms_px and abs(a.sigma_px - b.sigma_px) <= 1e-9 * b.sigma_px
        # and it is a real solve: the start was ~5 mm / 0.8 deg off the cube's true pose
        assert np.abs(se3_log(a.T_cam_model @ inv_T(T0))).max() > 1e-3
        if klt:
            assert np.array_equal(a.klt_inlier, b.klt_inlier)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_sobel_kernel_is_identical_to_numpy(dtype):
    from mst.pipeline.tracking.health import sobel_at, sobel_at_numpy

    img, uv, *_ = _scene(5)
    img = img.astype(dtype) * (np.float32(1.37) if dtype == np.float32 else 1)
    uv = np.concatenate([uv, [[-5.0, 3.0], [700.0, 500.0], [0.5, 478.5], [np.nan, 10.0]]])  # outside: clipped
    a = sobel_at(img, uv)
    with np.errstate(invalid="ignore"):  # numpy's cast of the NaN position
        b = sobel_at_numpy(img, uv)
    assert a.dtype == b.dtype == np.float32
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("model_name", ["l_shape", "city"])
def test_edge_sampling_kernel_is_identical_to_numpy(model_name):
    # exact: the kernel does the numpy formulation's elementwise IEEE operations in its order
    # (clipping, projection, level of detail, rectangle clip, sampling), so every output and count
    # must be identical, with and without the level-of-detail rule, near and far planes that cut
    # edges, and a city with a face index (the edges of the faces in view only)
    from mst.meshtools.generate import city_block_model, l_shape_model
    from mst.pipeline.tracking.visibility import ModelGeometry, visible_samples

    m = l_shape_model() if model_name == "l_shape" else city_block_model(buildings=200)
    g = ModelGeometry.from_model(m)
    V = np.asarray(m.vertices)
    rad = float(np.ptp(V, 0).max())
    rng = np.random.default_rng(1)
    fields = ("uv", "normal", "X_model", "edge", "A_model", "B_model", "edge_uv", "face_visible", "model_edge")
    n_s = 0
    for k in range(6):
        ang = 2 * np.pi * k / 6
        eye = V.mean(0) + rad * np.array([1.2 * np.cos(ang), 1.2 * np.sin(ang), 0.5])
        T = inv_T(look_at(eye, V.mean(0))) if k % 2 else se3_exp(rng.normal(0, 0.05, 6)) @ inv_T(look_at(eye, V.mean(0)))
        for near, far, lod in ((0.01 * rad, None, (0.0, 0.0)), (0.9 * rad, 1.4 * rad, (12.0, 64.0))):
            kw = dict(hidden_lines=True, zbuffer_scale=0.5, max_samples=600, lod_min_line_px=lod[0],
                      lod_min_face_px2=lod[1])
            a = visible_samples(g, T, K, 640, 480, 4.0, near, far, 80, 85, None, **kw)
            b = visible_samples(g, T, K, 640, 480, 4.0, near, far, 80, 85, None, _numpy_reference=True, **kw)
            for f in fields:
                np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
            assert a.stats == b.stats
            n_s += len(a)
    assert n_s > 500


def test_depth_buffer_setup_kernel_is_identical_to_numpy():
    # exact: the kernel moves and projects the vertices with the numpy formulation's operations in
    # its order; poses around a city from afar and from inside it (faces crossing the near plane)
    from mst.meshtools.generate import city_block_model
    from mst.pipeline.tracking.depth_buffer import inverse_depth_buffer
    from mst.pipeline.tracking.visibility import ModelGeometry, face_visibility

    m = city_block_model(buildings=120)
    g = ModelGeometry.from_model(m)
    V = np.asarray(m.vertices)
    c, rad = V.mean(0), float(np.ptp(V, 0).max())
    n_px = 0
    for k, (dist, h) in enumerate(((1.2, 0.5), (0.3, 0.02), (0.05, 0.01))):
        eye = c + rad * np.array([dist * np.cos(k), dist * np.sin(k), h])
        T = inv_T(look_at(eye, c + [0.0, 0.0, 0.01 * rad]))
        fv = face_visibility(g, T, None, 80.0, 85.0)
        for scale, near in ((0.5, 0.01 * rad), (1.0, 0.05 * rad)):
            a, sa = inverse_depth_buffer(g, T, K, 640, 480, fv, near, scale)
            b, sb = inverse_depth_buffer(g, T, K, 640, 480, fv, near, scale, _numpy_reference=True)
            assert sa == sb
            np.testing.assert_array_equal(a, b)
            n_px += int((a > 0).sum())
    assert n_px > 10_000


def test_depth_buffer_plane_kernel_is_identical_to_numpy():
    # the plane coefficients (float64, before the float32 buffer rounds them) of every face of a city
    # under random poses: d exactly in the kernel's fixed order ((0 + 2) + 1, einsum's on the x86-64
    # machines measured), and against _mat3 / einsum's within rounding
    from mst.meshtools.generate import city_block_model
    from mst.pipeline.tracking.depth_buffer import _mat3
    from mst.pipeline.tracking.kernels import zbuffer_planes
    from mst.pipeline.tracking.visibility import ModelGeometry

    g = ModelGeometry.from_model(city_block_model(buildings=120))
    rng = np.random.default_rng(8)
    sel = np.arange(len(g.faces))
    for _ in range(4):
        T = se3_exp(np.r_[rng.normal(0, 50, 3), rng.normal(0, 1, 3)])
        R, t = T[:3, :3], T[:3, 3]
        Kinv = np.linalg.inv(K * [[rng.uniform(0.4, 1.2)], [rng.uniform(0.4, 1.2)], [1.0]])
        n_c = _mat3(g.face_normals[sel], R)
        p_c = _mat3(g.face_point[sel], R, t)
        d = np.einsum("ij,ij->i", n_c, p_c)
        with np.errstate(divide="ignore", invalid="ignore"):
            coef_np = _mat3(n_c, Kinv.T) / d[:, None]
        coef = np.zeros((len(g.faces), 3))
        d_k = zbuffer_planes(g.face_normals, g.face_point, sel, R.copy(), t.copy(), Kinv, coef)
        q = n_c * p_c
        assert d_k.tobytes() == ((q[:, 0] + q[:, 2]) + q[:, 1]).tobytes()  # the kernel's fixed order, exact
        # numpy's einsum picks its summation by CPU (SIMD width): the same values within rounding
        # everywhere (bit-equal where it sums (0 + 2) + 1, as on the machines measured), so that this
        # test does not fail on another CPU while the kernel gives the same bits on all of them
        np.testing.assert_allclose(d_k, d, rtol=1e-13, atol=1e-12 * np.abs(d).max())
        fin = np.isfinite(coef_np[sel]).all(axis=1) & (np.abs(d) > 1e-9 * np.abs(d).max())
        np.testing.assert_allclose(coef[sel][fin], coef_np[sel][fin], rtol=1e-9)


def _health_numpy(img, X, A, B, edge, T, near, thr):
    """The numpy formulation of the health tests and of the evidence gradients that the kernels
    (``kernels.pose_health``, ``kernels.pose_gradients``) replaced (their reference)."""
    from mst.pipeline.tracking.health import ORIENT_TOL_DEG, sobel_at_numpy

    fx, fy = K[0, 0], K[1, 1]
    Xc = X @ T[:3, :3].T + T[:3, 3]
    ok_z = Xc[:, 2] > near * 0.5
    z = np.where(ok_z, Xc[:, 2], 1.0)
    uv = np.stack([fx * Xc[:, 0] / z + K[0, 2], fy * Xc[:, 1] / z + K[1, 2]], 1)
    Ae, Be = A @ T[:3, :3].T + T[:3, 3], B @ T[:3, :3].T + T[:3, 3]
    pa = Ae[:, :2] / Ae[:, 2:3] * [fx, fy] + K[:2, 2]
    pb = Be[:, :2] / Be[:, 2:3] * [fx, fy] + K[:2, 2]
    d = pb - pa
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    n = np.stack([-d[:, 1], d[:, 0]], 1)[edge]
    g = sobel_at_numpy(img, uv)
    gn = np.linalg.norm(g, axis=1)
    ang = np.degrees(np.arccos(np.clip(np.abs((g * n).sum(1)) / np.maximum(gn, 1e-9), 0, 1)))
    strong = gn >= 2.0 * thr
    health = (uv, bool(ok_z.all()), float(strong.mean()), float(ang[strong].mean()))
    # evidence: depth floored at 1e-9, normals from the normalised coordinates, best of -1, 0, +1 px
    z = np.maximum(Xc[:, 2], 1e-9)
    uv = np.stack([fx * Xc[:, 0] / z + K[0, 2], fy * Xc[:, 1] / z + K[1, 2]], 1)
    d = (Be[:, :2] / Be[:, 2:3] - Ae[:, :2] / Ae[:, 2:3]) * [fx, fy]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    n = np.stack([-d[:, 1], d[:, 0]], 1)[edge]
    g = np.stack([sobel_at_numpy(img, uv + k * n) for k in (-1.0, 0.0, 1.0)])
    proj = (g * n[None]).sum(2)
    j = np.argmax(np.abs(proj), axis=0)
    ii = np.arange(len(uv))
    pbest, gbest = proj[j, ii], g[j, ii]
    strong = np.abs(pbest) >= 2.0 * thr
    oriented = np.abs(pbest) >= np.cos(np.radians(ORIENT_TOL_DEG)) * np.linalg.norm(gbest, axis=1)
    sign = np.where(strong, np.sign(pbest), 0).astype(np.int8)
    return health, (uv, n, sign, oriented & strong)


@pytest.mark.parametrize("seed", [0, 1])
def test_health_kernels_match_numpy(seed):
    # The kernels transform the points in a fixed order instead of numpy's BLAS product: positions
    # within 1e-9 px (rounding ~1e-13 px); a nearest-pixel read changes only for a position within
    # that of a half-pixel boundary (never, at these counts), so the gradients, polarities,
    # orientation tests and the strong share are identical; the mean angle sums in another order
    # (1e-9 deg)
    from mst.pipeline.tracking.health import ORIENT_TOL_DEG
    from mst.pipeline.tracking.kernels import pose_gradients, pose_health

    img = _scene(seed)[0]
    T0, X, edge, A, B, *_ = _box_problem(seed)
    thr = 12.0
    (uv_h, front, support, perr), (uv_e, n_e, sign_e, good_e) = _health_numpy(img, X, A, B, edge, T0, 0.01, thr)
    args = (img, X, A, B, edge.astype(np.int64), T0, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    uv, in_front, n_strong, ang_sum = pose_health(*args, 0.005, float(np.float32(2.0 * thr)))
    np.testing.assert_allclose(uv, uv_h, rtol=0, atol=1e-9)
    assert in_front == front and n_strong / len(uv) == support and 20 <= n_strong < len(uv)
    assert abs(ang_sum / n_strong - perr) <= 1e-9
    uv2, n2, sign2, good2 = pose_gradients(*args, 2.0 * thr, float(np.cos(np.radians(ORIENT_TOL_DEG))))
    np.testing.assert_allclose(uv2, uv_e, rtol=0, atol=1e-9)
    np.testing.assert_allclose(n2, n_e, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sign2, sign_e)
    np.testing.assert_array_equal(good2, good_e)
    assert (sign2 != 0).sum() >= 20 and good2.sum() >= 10


def test_face_visibility_kernel_matches_numpy():
    # the kernel sums the ray cosines in a fixed order and uses libm's arccos; numpy's einsum and
    # arccos differ by an ulp, which could move a face across the appear/disappear angle only when it
    # lies within ~1e-13 deg of it: over these random poses the face sets must be identical
    from mst.meshtools.generate import city_block_model, l_shape_model
    from mst.pipeline.tracking.visibility import ModelGeometry, face_visibility, view_faces
    from mst.pipeline.tracking.visibility_numpy import face_visibility_numpy

    rng = np.random.default_rng(4)
    n_vis = 0
    for m in (l_shape_model(), city_block_model(buildings=150)):
        g = ModelGeometry.from_model(m)
        V = np.asarray(m.vertices)
        c, rad = V.mean(0), float(np.ptp(V, 0).max())
        prev = None
        for k in range(12):
            eye = c + rad * np.array([np.cos(k), np.sin(k), 0.3]) * rng.uniform(0.3, 1.5)
            T = se3_exp(rng.normal(0, 0.1, 6)) @ inv_T(look_at(eye, c))
            among = view_faces(g, T, K, 640, 480, 0.01 * rad, None) if g.index is not None else None
            a = face_visibility(g, T, prev, 70.0, 85.0, among=among)
            b = face_visibility_numpy(g, T, prev, 70.0, 85.0, among=among)
            np.testing.assert_array_equal(a, b)
            prev, n_vis = a, n_vis + int(a.sum())
    assert n_vis > 100


def test_vvs_median_selection_is_numpy_median():
    """The VVS kernel's median (quickselect, issue #14) is numpy's median value exactly: odd and even
    lengths, ties, signed zeros, one element; a NaN gives the sort's answer (NaN ordered last)."""
    from mst.pipeline.tracking.kernels import _median

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 7, 8, 64, 431, 600):
        for a in (rng.normal(0, 1, n), np.round(rng.normal(0, 2, n)), np.zeros(n), -np.abs(rng.normal(0, 1, n))):
            assert _median(a) == np.median(a), (n, a[:5])
    a = rng.normal(0, 1, 9)
    a[3] = np.nan
    assert _median(a) == np.sort(a)[4]


@pytest.mark.parametrize("convex", [False, True])
def test_surface_values_kernel_is_identical_to_numpy(convex):
    """The evidence's surface values in one kernel (issue #14) against their numpy formulation: the
    same points and the same 3x3 means to the bit (the transform in the same fixed order, the
    buffer test's product and the mean in float32 as numpy's), on the L building (hidden surface
    points: the depth buffer test) and a box, from poses around them, some points off the image."""
    from mst.core.camera import Camera
    from mst.meshtools.generate import box_model, l_shape_model
    from mst.pipeline.tracking import EdgeTracker
    from mst.pipeline.tracking.visibility import face_visibility

    m = box_model() if convex else l_shape_model()
    tr = EdgeTracker(m, Camera(600, 600, 319.5, 239.5, 640, 480))
    assert tr.geom.convex == convex
    img = _scene(2)[0]
    Vm = np.asarray(m.vertices, float)
    c, rad = Vm.mean(0), float(np.ptp(Vm, 0).max())
    rng = np.random.default_rng(1)
    n = 0
    for k in range(8):
        T = inv_T(look_at(c + rad * rng.uniform(0.9, 2.5) * np.array([np.cos(k), np.sin(k), 0.4]), c))
        T = se3_exp(np.r_[rng.normal(0, 0.05 * rad, 3), rng.normal(0, 0.15, 3)]) @ T
        fv = face_visibility(tr.geom, T, None, 80.0, 85.0)
        a_i, a_v = tr._surface_values(img, T, fv)
        b_i, b_v = tr._surface_values_numpy(img, T, fv)
        np.testing.assert_array_equal(a_i, b_i)
        assert a_v.dtype == b_v.dtype and np.array_equal(a_v, b_v)
        n += len(a_i)
    assert n > 200


def test_face_area_kernel_is_identical_to_numpy():
    """The LOD rule's projected face areas (kernels.face_areas_px2) equal the numpy formulation to the
    bit: loops of 4-6 vertices (numpy's sequential sum), of 12 and 64 (its 8 partial sums) and of 300
    (its halving), faces crossing the near plane (inf), some faces only."""
    from mst.meshtools.generate import city_block_model, cylinder_model, l_shape_model
    from mst.pipeline.tracking.visibility import ModelGeometry, projected_face_area_px2

    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    rng = np.random.default_rng(5)
    models = (l_shape_model(), city_block_model(buildings=40), cylinder_model(sections=12),
              cylinder_model(sections=64), cylinder_model(sections=300))
    n_inf = 0
    for m in models:
        g = ModelGeometry.from_model(m)
        c = g.vertices.mean(0)
        for _ in range(6):
            eye = c + rng.normal(size=3) * g.scale_m * rng.uniform(0.3, 3.0)
            T = inv_T(look_at(eye, c + rng.normal(size=3) * 0.2 * g.scale_m))
            near = float(rng.uniform(0.01, 0.5) * g.scale_m)
            faces = rng.random(len(g.faces)) < 0.7
            for sel in (None, faces):
                a = projected_face_area_px2(g, T, K, near, faces=sel)
                b = projected_face_area_px2(g, T, K, near, faces=sel, _numpy_reference=True)
                assert np.array_equal(a, b)
                n_inf += int(np.isinf(a).sum())
    assert n_inf > 0  # the near-plane case was exercised


def test_mat3_kernel_is_identical_to_numpy():
    """_mat3's kernel (X @ M.T + t without temporaries) gives numpy's formulation's bits, for a
    transposed (non-contiguous) M, with and without t, and for no points."""
    from mst.pipeline.tracking.depth_buffer import _mat3, _mat3_numpy

    rng = np.random.default_rng(9)
    R = cv2.Rodrigues(rng.normal(size=3))[0]
    t = rng.normal(size=3) * 100
    for n in (0, 1, 7, 1000):
        X = rng.normal(size=(n, 3)) * 10 ** rng.uniform(-3, 5, size=(n, 1))
        for M, tt in ((R, t), (R.T, None), (R.T, t)):
            assert np.array_equal(_mat3(X, M, tt), _mat3_numpy(X, M, tt))


def test_frustum_cull_kernel_matches_numpy():
    """frustum_faces' kernel (no counts asked) keeps the faces its numpy formulation (counts asked)
    keeps, on a city block seen from random poses, with and without a far plane and a candidate list."""
    from mst.meshtools.generate import city_block_model
    from mst.pipeline.tracking.visibility import ModelGeometry, frustum_faces

    g = ModelGeometry.from_model(city_block_model(buildings=150))
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    rng = np.random.default_rng(4)
    c = g.vertices.mean(0)
    kept = 0
    for _ in range(20):
        T = inv_T(look_at(c + rng.normal(size=3) * g.scale_m, c + rng.normal(size=3) * 0.3 * g.scale_m))
        among = np.flatnonzero(rng.random(len(g.faces)) < 0.5)
        for far in (np.inf, 0.8 * g.scale_m):
            for sel in (None, among):
                a = frustum_faces(g, T, K, 640, 480, 0.5, far, among=sel)
                b = frustum_faces(g, T, K, 640, 480, 0.5, far, {}, among=sel)
                assert np.array_equal(a, b)
                kept += int(a.sum())
    assert 0 < kept < 20 * 4 * len(g.faces)


def _contour_inputs(rng, dtype, N=300, C=2):
    """A textured image with a bright disc and random contour samples near it, candidates within 2 px (20 % none)."""
    H, W = 120, 160
    yy, xx = np.mgrid[:H, :W]
    img = 60.0 + 40.0 * rng.random((H, W)) + 120.0 * (((xx - 80.0) ** 2 + (yy - 60.0) ** 2) < 40.0 ** 2)
    img = np.clip(img, 0, 255).astype(dtype)
    ang = rng.uniform(0, 2 * np.pi, N)
    n_out = np.stack([np.cos(ang), np.sin(ang)], 1)
    uv = np.array([80.0, 60.0]) + (40.0 + rng.normal(0, 1.0, (N, 1))) * n_out
    uv[: N // 10] = rng.uniform(-3, 165, (N // 10, 2))  # some near and beyond the image border
    normal = n_out * rng.choice([-1.0, 1.0], (N, 1))
    offset = rng.uniform(-2, 2, (N, C))
    offset[rng.random((N, C)) < 0.2] = np.nan
    return img, uv, n_out, offset, normal


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64])
def test_contour_crossing_kernel_is_the_numpy_formulation(dtype):
    """render_edges.crossing_offsets (one kernel) gives crossing_offsets_numpy's offsets to the bit, on 8-bit and
    float images, with candidates missing and samples at the border; most candidates near the disc cross."""
    from mst.pipeline.tracking.render_edges import crossing_offsets, crossing_offsets_numpy

    rng = np.random.default_rng(11)
    for _ in range(5):
        args = _contour_inputs(rng, dtype)
        a, b = crossing_offsets(*args), crossing_offsets_numpy(*args)
        assert np.array_equal(a, b, equal_nan=True)
        assert np.isfinite(a).sum() > 0.3 * a.size


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_contour_side_kernel_is_the_numpy_formulation(dtype):
    """render_edges.contour_side_test (one kernel) is contour_side_test_numpy to the bit: a reference frame of the
    same disc 1 px away, and the candidates of both outcomes."""
    from mst.pipeline.tracking.render_edges import contour_side_test, contour_side_test_numpy

    rng = np.random.default_rng(12)
    K = np.array([[500.0, 0, 80.0], [0, 500.0, 60.0], [0, 0, 1]])
    for _ in range(5):
        img, uv, n_out, offset, normal = _contour_inputs(rng, dtype)
        ref = np.roll(img, 1, axis=1)
        T = np.eye(4)
        T[:3, 3] = [0.001, 0.0, 0.0]
        X = np.column_stack([(uv - K[:2, 2]) / 500.0, np.ones(len(uv))])  # the samples' rays at 1 m
        a = contour_side_test(img, K, uv, n_out, X, offset, normal, ref, T)
        b = contour_side_test_numpy(img, K, uv, n_out, X, offset, normal, ref, T)
        assert np.array_equal(a, b) and 0 < a.mean() < 1


def test_model_geometry_build_is_the_per_face_loop():
    """ModelGeometry.from_model's vectorised loops (face centres, directed loop edges with their face, free lines)
    give what the per-face loop it replaced gave, to the bit: a courtyard (faces with holes) with a free line,
    and a 12,288-triangle vase (issue #14: its build 268 -> 68 ms)."""
    from mst.meshtools.generate import courtyard_model, vase
    from mst.meshtools.model import PolygonModel
    from mst.pipeline.tracking.visibility import ModelGeometry

    c = courtyard_model()
    V, F = vase()
    for m in (PolygonModel(c.vertices, c.faces, c.holes, lines=[[0, 5]]), PolygonModel(V, list(F))):
        g = ModelGeometry.from_model(m)
        P = np.array([m.vertices[f].mean(axis=0) for f in m.faces])
        assert np.array_equal(g.face_point, P)
        segs, fid = [], []
        for i, f in enumerate(m.faces):
            for lp in [f, *m.holes[i]]:
                segs.append(np.stack([lp, np.roll(lp, -1)], 1))
                fid.append(np.full(len(lp), i))
        segs.append(m.lines)
        fid.append(np.full(len(m.lines), -1))
        S = np.sort(np.concatenate(segs), axis=1)
        fid = np.concatenate(fid)
        # every unique undirected edge kept by the build is a loop edge or line, with its first face as listed
        key = S[:, 0] * len(m.vertices) + S[:, 1]
        first = {}
        for k, f in zip(key.tolist(), fid.tolist()):
            first.setdefault(k, f)
        gk = g.edges[:, 0] * len(m.vertices) + g.edges[:, 1]
        assert all(first[k] == f for k, f in zip(gk.tolist(), g.edge_faces[:, 0].tolist()))
        assert len(g.edges) > 0 and (m.n_holes == 0 or (g.face_nring > 1).any())


def test_sorted_unique_of_sample_edges_is_numpy_unique():
    """The frame result's edge list: np.unique's ids, from the runs of the samplers' non-decreasing ids (and by
    np.unique itself when they are not in order)."""
    from mst.pipeline.tracking.edge_tracker import _sorted_unique

    rng = np.random.default_rng(5)
    for e in (np.sort(rng.integers(0, 40, 300)), rng.integers(0, 40, 300), np.zeros(0, np.int64), np.array([7]),
              np.arange(12)):
        assert np.array_equal(_sorted_unique(e), np.unique(e))


def test_health_median_is_numpy_median():
    """The health score's window median (sorted Python floats) is np.median's value to the bit, odd and even
    lengths, and so is the MAD built on it."""
    from mst.pipeline.tracking.health import _median

    rng = np.random.default_rng(6)
    for n in range(1, 52):
        v = list(rng.normal(size=n) * rng.choice([1e-3, 1.0, 1e3]))
        r = _median(v)
        assert r == float(np.median(np.asarray(v)))
        assert _median([abs(x - r) for x in v]) == float(np.median(np.abs(np.asarray(v) - r)))


def test_edge_pass_helper_kernels_are_the_numpy_steps():
    """The edge pass's small kernels give the bits of the numpy steps they replaced: the reference
    projection (depth floored at 1e-9 m, NaN kept), the strongest response (np.argmax of |conv|: first of
    ties, first NaN) and the candidates' pixels (numpy's broadcast)."""
    from mst.pipeline.tracking.depth_buffer import _mat3
    from mst.pipeline.tracking.kernels import candidates_uv_kernel, project_uv, strongest

    rng = np.random.default_rng(7)
    T = se3_exp(rng.normal(0, 0.3, 6))
    T[2, 3] = 1.0
    X = rng.normal(0, 2, (300, 3))
    c = np.array([[0.1, 0.2, -1.0], [0.3, 0.1, 0.0], [0.2, 0.2, 1e-12], [0.0, 0.0, np.nan], [1.0, 1.0, 3.0]])
    X[:5] = (c - T[:3, 3]) @ T[:3, :3]  # camera depths behind, on and near the camera plane, NaN
    Xc = _mat3(X, T[:3, :3], T[:3, 3])
    z = np.maximum(Xc[:, 2], 1e-9)
    ref = np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]], 1)
    got = project_uv(X, T, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    np.testing.assert_array_equal(got, ref)
    assert np.isnan(got[3]).all() and (Xc[:5, 2] < 1e-9).sum() >= 3

    conv = rng.integers(-40, 40, (200, 5)).astype(np.float32)
    conv[0] = [3, -7, 7, 1, 0]  # a tie of magnitudes: the first
    conv[1] = [1, np.nan, 9, np.nan, 2]  # the first NaN
    conv[2] = [np.nan, 1, 2, 3, 4]
    np.testing.assert_array_equal(strongest(conv), conv[np.arange(len(conv)), np.argmax(np.abs(conv), axis=1)])

    uv, nrm = rng.normal(300, 100, (200, 2)), rng.normal(0, 1, (200, 2))
    off = rng.normal(0, 4, (200, 2))
    off[::7, 1] = np.nan
    np.testing.assert_array_equal(candidates_uv_kernel(uv, off, nrm), uv[:, None, :] + off[..., None] * nrm[:, None, :])
