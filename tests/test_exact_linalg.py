"""The BLAS- and LAPACK-free small linear algebra of the tracker (:mod:`mst.pipeline.tracking.exact`,
:func:`mst.core.poses.orthonormalise`, the render edges' smoothed gradient): the values of numpy's and
OpenCV's routines to rounding (their bits depend on the CPU; these do not: tests/test_reproducibility_cpu.py),
and the fixed summation order each documents, to the bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mst.core.poses import orthonormalise, so3_exp
from mst.pipeline.tracking.exact import centre, dot3, eigh, eigvalsh, mv, norm3, quad_form, rigid


def _symmetric(rng, n: int, kind: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    S = A @ A.T
    if kind == 1:  # nearly repeated eigenvalues (a body of revolution's moments)
        S = np.diag(np.arange(1.0, n + 1.0)) + 1e-9 * S
        S[0, 0] = S[1, 1]
    elif kind == 2:  # a covariance over 12 decades (metres and radians of a far pose)
        s = np.logspace(-6, 0, n)
        S = S * s[:, None] * s[None, :]
    return S


@pytest.mark.parametrize("n", [3, 4, 6])
def test_eigh_matches_lapack_to_rounding(n):
    """Eigenvalues within 1e-13 of the largest of LAPACK's, an orthonormal basis that rebuilds the
    matrix to the same, ascending order; 600 random, near-degenerate and badly scaled matrices."""
    rng = np.random.default_rng(n)
    for i in range(600):
        S = _symmetric(rng, n, i % 3)
        lam, V = eigh(S)
        lam_ref = np.linalg.eigvalsh(S)
        tol = 1e-13 * np.abs(lam_ref).max()
        assert np.abs(lam - lam_ref).max() <= tol
        assert (np.diff(lam) >= 0).all()
        assert np.abs(V.T @ V - np.eye(n)).max() <= 1e-13
        assert np.abs(V @ np.diag(lam) @ V.T - S).max() <= tol
        assert eigvalsh(S).tobytes() == lam.tobytes()


def test_eigh_nan_in_nan_out_and_diagonal_untouched():
    assert np.isnan(eigh(np.full((3, 3), np.nan))[0]).all()
    D = np.diag([3.0, 1.0, 2.0])
    lam, V = eigh(D)
    assert lam.tolist() == [1.0, 2.0, 3.0] and np.abs(V).sum() == 3.0  # a permutation, no rotation


def test_orthonormalise_is_the_polar_factor():
    """The rotation nearest a perturbed one (SVD's ``U V^T``) to 1e-14, orthonormal with det 1 to 1e-14;
    a rotation stays itself to rounding."""
    rng = np.random.default_rng(1)
    for _ in range(500):
        R0 = so3_exp(rng.normal(size=3))
        R = R0 + rng.normal(size=(3, 3)) * 10 ** rng.uniform(-12, -4)
        U, _, Vt = np.linalg.svd(R)
        X = orthonormalise(R)
        assert np.abs(X - U @ Vt).max() <= 1e-14
        assert np.abs(X.T @ X - np.eye(3)).max() <= 1e-14 and abs(np.linalg.det(X) - 1) <= 1e-14
        assert np.abs(orthonormalise(R0) - R0).max() <= 2e-15  # so3_exp is orthonormal to rounding only


def test_small_products_sum_in_their_documented_order():
    """``mv``, ``dot3``, ``rigid``, ``centre``, ``norm3``, ``quad_form``: numpy's values to rounding, and the
    bits of the written-out order (separate IEEE multiplies and adds: no BLAS, no fused multiply-add)."""
    rng = np.random.default_rng(2)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp(rng.normal(size=3)), rng.normal(size=3) * 10
    R, t = T[:3, :3], T[:3, 3]
    X = rng.normal(size=(50, 3)) * 100
    x, y = rng.normal(size=3), rng.normal(size=3)
    m = mv(X, x)
    assert m.tobytes() == ((X[:, 0] * x[0] + X[:, 1] * x[1]) + X[:, 2] * x[2]).tobytes()
    assert np.allclose(m, X @ x, rtol=1e-14, atol=1e-12)
    assert dot3(x, y) == (x[0] * y[0] + x[1] * y[1]) + x[2] * y[2]
    P = rigid(X, R, t)
    assert P.tobytes() == (((X[:, 0:1] * R[:, 0] + X[:, 1:2] * R[:, 1]) + X[:, 2:3] * R[:, 2]) + t).tobytes()
    assert np.allclose(P, X @ R.T + t, rtol=0, atol=1e-12)
    X32 = X.astype(np.float32)
    assert rigid(X32, R).dtype == np.float32
    assert np.allclose(centre(T), -R.T @ t, rtol=0, atol=1e-13)
    assert norm3(x) == pytest.approx(np.linalg.norm(x), rel=1e-15)
    W = _symmetric(rng, 6, 0)
    v = rng.normal(size=6)
    assert quad_form(v, W) == pytest.approx(float(v @ W @ v), rel=1e-13)


@pytest.mark.parametrize("shape", [(240, 320), (37, 51), (12, 12)])
def test_smoothed_gradient_is_opencvs_blur_and_sobel_to_float32_rounding(shape):
    """The render edges' inverse-depth gradient: ``cv2.GaussianBlur`` (sigma 1 px) then ``cv2.Sobel`` (3x3),
    borders included (reflect-101), within a few float32 ulps of the gradient's scale (OpenCV sums in another
    order, which also differs between its SIMD variants)."""
    from mst.pipeline.tracking.edgelets import smoothed_gradient

    rng = np.random.default_rng(3)
    img = np.where(rng.random(shape) < 0.7, 1.0 / rng.uniform(1.0, 3.0, shape), 0.0)  # inverse depth with holes
    gx, gy = smoothed_gradient(img)
    b = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)
    for g, ref in ((gx, cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3)), (gy, cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3))):
        assert g.dtype == np.float32 and g.shape == shape
        assert np.abs(g - ref).max() <= 16 * np.finfo(np.float32).eps * np.abs(ref).max()
    # a window too small for the 9-tap kernel: no gradient rather than an out-of-range read
    assert not any(g.any() for g in smoothed_gradient(np.ones((3, 40))))
