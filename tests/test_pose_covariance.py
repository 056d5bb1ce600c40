"""The edge pose's covariance (pipeline/tracking/covariance.py): the delete-one-edge jackknife floored by the
classical ``rms^2 W^-1``, its bound against known synthetic error distributions, and what ``mst track`` writes.

The synthetic case is test_vvs.py's cube (a 20 cm cube 1 m in front of a 640x480 camera) with 40
samples on each of its 12 edges (60 runs of CHUNK_SAMPLES = 8: enough clusters for the cluster term),
matches on the true projected edges moved along the edge normal by (a) i.i.d. noise and (b) a random
offset per run of 8 consecutive samples (a moving edge pulled by texture or blur moves its neighbouring
samples together; measured along real edges: correlated over up to 4-8 samples) plus a smaller i.i.d.
noise. Measured over the draws: ``err / sigma`` of the camera centre (RMS of ``|e|^2 / tr C_vv``; 1 is
calibrated) and the share of draws whose error is within 2 sigma (``|e| <= 2 sqrt(tr C_vv)``, the error
budget's bound). Budget: 120 draws give the RMS ratio to ~7 % and the share to ~3 % (1 SE); the goal is
a bound right within a factor 2, so the asserted bands are [0.5, 2] on the ratio and >= 0.85 on the
share (a Gaussian error is within 2 sigma of its trace in >= 95 % of draws).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_vvs import K, _cube, _normals, _project, _start, _true_pose  # noqa: E402

from mst.core.poses import inv_T, se3_log  # noqa: E402
from mst.pipeline.tracking.vvs import solve_pose  # noqa: E402


def _dense_cube(per_edge: int = 40):
    X5, edge5, A, B = _cube()
    t = np.linspace(0.05, 0.95, per_edge)
    X = np.concatenate([A[k] + t[:, None] * (B[k] - A[k]) for k in range(len(A))])
    return X, np.repeat(np.arange(len(A)), per_edge), A, B


def _draws(sigma_run_px: float, sigma_px: float, n: int = 120, seed: int = 0) -> dict:
    from mst.pipeline.tracking.covariance import CHUNK_SAMPLES, edge_chunks

    X, edge, A, B = _dense_cube()
    run, n_runs = edge_chunks(edge, CHUNK_SAMPLES)
    T = _true_pose()
    nrm, uv0 = _normals(T, A, B, edge), _project(T, X)
    rng = np.random.default_rng(seed)
    q = {"new": [], "classical": []}
    for _ in range(n):
        off = rng.normal(0, sigma_run_px, n_runs)[run] + rng.normal(0, sigma_px, len(X))
        res = solve_pose(_start(T), K, X, edge, A, B, (uv0 + off[:, None] * nrm)[:, None, :], min_mad_px=0.3, iters=50)
        assert res.has_pose
        e = se3_log(T @ inv_T(res.T_cam_model))[:3]
        for name, C in (("new", res.cov), ("classical", res.cov_classical)):
            q[name].append(float(e @ e / np.trace(C[:3, :3])))
    return {k: (float(np.sqrt(np.mean(v))), float(np.mean(np.asarray(v) <= 4.0))) for k, v in q.items()}


def test_bound_covers_correlated_errors_along_edges():
    """Offsets per run of 8 samples (0.5 px) over i.i.d. noise (0.2 px): the classical covariance, which
    treats every sample as independent, is optimistic (measured 2.0x, 64 % of the draws within its 2
    sigma); the cluster-robust bound is right within 2x (1.43x) and covers >= 85 % (88 %)."""
    r = _draws(0.6, 0.1)
    ratio, share = r["new"]
    assert 0.5 <= ratio <= 2.0 and share >= 0.85, r
    # the failure the cluster term is for (this case tells them apart): measured 2.0x, 64 % within 2 sigma
    assert r["classical"][0] > 1.5 and r["classical"][1] < 0.75, r


def test_bound_not_pessimistic_with_independent_errors():
    """I.i.d. noise (0.5 px), where the classical covariance is right (measured 0.58: pessimistic, the
    Tukey weights' normalisation): the floored cluster term is never below it and stays within 2x."""
    r = _draws(0.0, 0.5)
    ratio, share = r["new"]
    assert 0.5 <= ratio <= 2.0 and share >= 0.85, r
    assert ratio <= r["classical"][0] * (1 + 1e-9), r  # floored by the classical one: never more optimistic


def test_klt_points_are_no_evidence():
    """KLT points in the fit leave the bound the edges': the points' model coordinates are lifted under
    an earlier pose and carry its error. The steady view (issue 11's 250 m survey): the earlier pose
    is this view's own edges-only fit, so the points (100 on the faces, seen at their true pixels +
    0.1 px) agree with the edges' error and add none of their own. The KLT-aided fit's covariance
    must still cover its error as the edges' does (the bands of
    :func:`test_bound_covers_correlated_errors_along_edges`). Counted as evidence (their information
    capped at the edges', ``klt_info_cap`` 1), they halved the variance while the error stayed:
    ratio 2.09x, 56 % of the draws within 2 sigma; the edges' bound: 1.38x, 92 % (session 16)."""
    from mst.pipeline.tracking.covariance import CHUNK_SAMPLES, edge_chunks

    X, edge, A, B = _dense_cube()
    run, n_runs = edge_chunks(edge, CHUNK_SAMPLES)
    T = _true_pose()
    nrm, uv0 = _normals(T, A, B, edge), _project(T, X)
    rng = np.random.default_rng(1)
    Xk = rng.uniform(-0.1, 0.1, (100, 3))
    Xk[np.arange(100), rng.integers(0, 3, 100)] = rng.choice([-0.1, 0.1], 100)  # on the faces
    Xk = Xk[(Xk @ T[:3, :3].T + T[:3, 3])[:, 2] < T[2, 3]]  # the faces towards the camera (roughly)
    q = []
    for _ in range(120):
        off = rng.normal(0, 0.6, n_runs)[run] + rng.normal(0, 0.1, len(X))
        cand = (uv0 + off[:, None] * nrm)[:, None, :]
        T_e = solve_pose(_start(T), K, X, edge, A, B, cand, min_mad_px=0.3, iters=50).T_cam_model
        Ti = inv_T(T_e)
        Xk_model = (Xk @ T[:3, :3].T + T[:3, 3]) @ Ti[:3, :3].T + Ti[:3, 3]  # lifted under the edges' fit
        uk = _project(T, Xk) + rng.normal(0, 0.1, (len(Xk), 2))
        res = solve_pose(T_e, K, X, edge, A, B, cand, min_mad_px=0.3, iters=50, klt_X_model=Xk_model, klt_uv=uk,
                         klt_info_cap=1.0)
        assert res.has_pose and not np.array_equal(res.W_edges, res.W)  # the KLT points took part
        e = se3_log(T @ inv_T(res.T_cam_model))[:3]
        q.append(float(e @ e / np.trace(res.cov[:3, :3])))
    ratio, share = float(np.sqrt(np.mean(q))), float(np.mean(np.asarray(q) <= 4.0))
    assert 0.5 <= ratio <= 2.0 and share >= 0.85, (ratio, share)


def test_psd_max_is_the_larger_along_every_direction():
    """psd_max(Cf, Cj) against numpy's generalized eigen-decomposition: it contains both ellipsoids
    (out - Cf and out - Cj positive semi-definite) and equals the reference to rounding."""
    from mst.pipeline.tracking.covariance import psd_max

    rng = np.random.default_rng(1)
    for _ in range(20):
        A, B = rng.standard_normal((6, 6)), rng.standard_normal((6, 6))
        Cf, Cj = A @ A.T + 1e-3 * np.eye(6), B @ B.T * rng.uniform(0.1, 10)
        out = psd_max(Cf, Cj)
        L = np.linalg.cholesky(Cf)
        Li = np.linalg.inv(L)
        lam, U = np.linalg.eigh(Li @ Cj @ Li.T)
        ref = L @ U @ np.diag(np.maximum(lam, 1.0)) @ U.T @ L.T
        np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        assert np.array_equal(out, out.T)
        for C in (Cf, Cj):
            assert np.linalg.eigvalsh(out - C).min() > -1e-9 * np.abs(out).max()


def test_no_cluster_term_with_too_few_clusters():
    """The 5-sample cube: 12 clusters, fewer than MIN_CLUSTERS: no cluster term, the classical covariance
    stays (solve_pose's cov is its cov_classical)."""
    from mst.pipeline.tracking.covariance import MIN_CLUSTERS, edge_cluster_cov

    X, edge, A, B = _cube()
    T = _true_pose()
    C, m = edge_cluster_cov(T, K, X, edge, A, B, np.ones(len(X)), np.full(len(X), 0.1))
    assert C is None and m == 12 < MIN_CLUSTERS
    res = solve_pose(_start(T), K, X, edge, A, B, _project(T, X)[:, None, :], min_mad_px=0.3, iters=50)
    assert np.array_equal(res.cov, res.cov_classical)


def _row_cov(row):
    return None if row[6] == "" else np.array([float(x) for x in row[6:]]).reshape(6, 6)


def test_written_covariance_is_positive_definite_or_absent():
    """The row of a singular fit (negative variances of 1e10, as written at a re-acquisition of the rgbd
    corridor at 6 fps, frame 111) is empty; a valid but strongly correlated covariance (0.9999999: long
    range, depth against rotation) is written with enough digits to stay positive definite as read back."""
    from mst.pipeline.tracking.runner import cov_row

    T = np.eye(4)
    bad = np.diag([1e-4, 1e-4, -1e10, 1e-6, 1e-6, 1e-6])
    assert _row_cov(cov_row(3, "model", bad, T)) is None
    rank1 = np.outer(np.arange(1.0, 7.0), np.arange(1.0, 7.0)) * 1e-4
    assert _row_cov(cov_row(4, "model", rank1, T)) is None
    assert _row_cov(cov_row(5, "model", np.full((6, 6), np.inf), T)) is None
    s = np.array([0.02, 0.02, 3.0, 1e-4, 1e-4, 1e-4])
    R = np.eye(6)
    R[2, 4] = R[4, 2] = 0.9999999
    good = R * np.outer(s, s)
    C = _row_cov(cov_row(6, "model", good, T))
    assert C is not None and np.array_equal(C, C.T) and np.linalg.eigvalsh(C).min() > 0
    np.testing.assert_allclose(C, good, rtol=1e-6)
    # a map pose's row holds its propagated drift covariance; a lost frame has no pose, so no row
    np.testing.assert_allclose(_row_cov(cov_row(7, "slam", good, T)), good, rtol=1e-6)
    assert _row_cov(cov_row(8, "lost", good, T)) is None


def test_non_finite_covariance_is_beyond_the_budget():
    from mst.pipeline.tracking.budget import PoseBudget, beyond_budget

    T = np.eye(4)
    T[2, 3] = 10.0
    assert beyond_budget(PoseBudget(), np.full((6, 6), np.inf), T, lambda T: 10.0).startswith("pose uncertain")
    assert beyond_budget(PoseBudget(), np.eye(6) * 1e-8, T, lambda T: 10.0) == ""


@pytest.mark.parametrize("cr2", [True, False])
def test_cluster_term_identical_to_a_numpy_reference(cr2):
    """The kernel against a plain numpy formulation of the same fit (rounding only): per run of 8
    samples ``g``, with ``H = L L^T`` and ``L^-1 H_g L^-T = U diag(l) U^T``, ``D_g = L^-T U diag(f(l)) U^T
    L^-1 s_g``; CR2 ``f = (1 - l)^-1/2``, ``C = sum D_g D_g^T``; the delete-one jackknife (``cr2=False``)
    ``D_g = (H - H_g)^-1 s_g``, ``C = (G - 1) / G sum D_g D_g^T``."""
    from mst.pipeline.tracking.covariance import edge_chunks, edge_cluster_cov

    X, edge, A, B = _dense_cube()
    T = _true_pose()
    rng = np.random.default_rng(int(cr2))
    w, r = rng.uniform(0.2, 1.0, len(X)), rng.normal(0, 0.5, len(X))
    C, m = edge_cluster_cov(T, K, X, edge, A, B, w, r, cr2=cr2)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    x, y, iz = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2], 1 / Xc[:, 2]
    nx, ny = _normals(T, A, B, edge).T
    a, b = nx * K[0, 0], ny * K[1, 1]
    J = np.column_stack([a * iz, b * iz, -(a * x + b * y) * iz, -a * x * y - b * (1 + y * y), a * (1 + x * x) + b * x * y,
                         b * x - a * y])
    H = (J * w[:, None]).T @ J
    L = np.linalg.cholesky(H)
    Li = np.linalg.inv(L)
    run, G = edge_chunks(edge)
    D = []
    for g in range(G):
        s = run == g
        Hg, sg = (J[s] * w[s, None]).T @ J[s], (J[s] * (w[s] * r[s])[:, None]).sum(0)
        if cr2:
            lam, U = np.linalg.eigh(Li @ Hg @ Li.T)
            D.append(Li.T @ U @ np.diag((1 - lam) ** -0.5) @ U.T @ Li @ sg)
        else:
            D.append(np.linalg.solve(H - Hg, sg))
    D = np.array(D)
    ref = D.T @ D * (1.0 if cr2 else (G - 1) / G)
    assert m == G == 60
    np.testing.assert_allclose(C, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())


@pytest.mark.slow
def test_tracked_corridor_covariances_are_positive_definite(tmp_path):
    """The rgbd corridor (320x240, 90 frames: model frames before and after the stretch away, where a
    re-acquisition of its 6 fps variant had been written with negative variances of 1e10; that variant
    now outputs frame 0 only, here and on main, its other edge poses 1.4-6 % off and refused): every
    written row is symmetric positive definite, and ``mst nav fuse``'s reader takes the file (it refuses
    a non-positive variance)."""
    import csv

    from mst.core.trajectory import read_tum
    from mst.eval.bench.slam import SAMPLE_MODEL
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.run import read_track_cov
    from mst.pipeline.synth import SynthConfig, synthesize
    from mst.pipeline.tracking import TrackConfig, run_track

    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    seq = tmp_path / "corridor"
    synthesize("corridor", SAMPLE_MODEL, seq, SynthConfig(width=320, height=240, frames=90))
    out = tmp_path / "traj.txt"
    run_track(seq / "rgb", seq / "model.obj", seq / "camera.json", seq / "cMo" / "000000.txt", out, TrackConfig(),
              depth_dir=seq / "depth", fps=30.0)
    rows = [r for r in csv.DictReader(open(out.with_suffix(".cov.csv"))) if r["c00"]]
    assert len(rows) >= 10  # the model frames before the stretch away
    for r in rows:
        C = np.array([float(r[f"c{i}{j}"]) for i in range(6) for j in range(6)]).reshape(6, 6)
        assert np.array_equal(C, C.T) and np.linalg.eigvalsh(C).min() > 0, r["frame"]
    t, T = read_tum(out)
    C = read_track_cov(out.with_suffix(".cov.csv"), out, t, T, FusionConfig())
    assert C.shape == (len(t), 6, 6)
