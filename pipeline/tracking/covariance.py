"""The edge pose's 6x6 covariance (issues #11/#12/#13): a cluster-robust (CR2) covariance of the robust VVS.

The classical ``rms^2 (J^T W J)^-1`` of :func:`mst.pipeline.tracking.vvs.solve_pose` assumes that the
residuals of all samples are independent. They are not: a moving edge pulled by texture, blur or a
rendering offset moves neighbouring samples of one model edge together (measured: the residuals'
autocorrelation along an edge is 0.2-0.6 at the next sample and gone beyond 4-8 samples, see
:data:`CHUNK_SAMPLES`), which an i.i.d. model cannot see.

Clusters: runs of :data:`CHUNK_SAMPLES` consecutive samples of one model edge (the edge samples only: a
hybrid fit's KLT points are not the pose's evidence, :mod:`mst.pipeline.tracking.vvs`). With ``s_g = sum_{i in g} w_i r_i J_i``, ``H_g = sum_{i in g} w_i J_i J_i^T``, ``H = sum_g
H_g = L L^T`` and ``L^-1 H_g L^-T = U diag(l) U^T`` (``l`` the cluster's leverages), each cluster
contributes ``D_g = L^-T U diag((1 - l)^-1/2) U^T L^-1 s_g`` and the covariance is ``sum_g D_g D_g^T``
(Bell & McCaffrey's bias-reduced linearisation: exact for i.i.d. residuals, and the residuals of a
high-leverage cluster, which the fit has absorbed, are scaled back). It is floored by the classical
covariance along every direction (:func:`psd_max`), and used only with :data:`MIN_CLUSTERS` clusters
or more. Symmetric and positive semi-definite by construction (sums of outer products, each in one
fixed order: the same bits on every CPU, no BLAS, :mod:`mst.pipeline.tracking.exact`).

Measured against the truth (``err / sigma`` of the camera centre, RMS over the frames that were output
or refused by the error budget; 1 is calibrated), classical -> this: demo UAV pass 2.15 -> 2.02,
Rotterdam FPV 6.07 -> 2.88 (7 frames, two of them 2.1 / 2.9 % off in a wrong minimum: the ambiguity
test's), Rotterdam 250 m survey band 1.61 -> 1.22 (poses > 1 % off within the 2 sigma budget: 4 -> 1, 1.07 % off, not output: the aid's map pose was chosen and withheld),
turntable 320x240 1.66 -> 1.35, its 640x480 variant 1.05 -> 0.99, synthetic teabox 1.03 -> 1.02,
fast x10 orbit 320x240 1.98 -> 1.32, corridor 320x240 0.67 (fewer than 20 clusters: classical).
Rejected: the delete-one-cluster jackknife (CR3, ``D_g = (H - H_g)^-1 s_g``): FPV 1.42 and demo UAV
1.70, but 0.27 on the corridor (3.7x pessimistic: every correct pose refused) and, with whole edges as
clusters, 2 sigma = 2.9-3.2 % on the real teabox's edges-only poses (classical 0.33 %, mst against
ViSP's hybrid tracker 1.2 mm RMS); Huber-White clustered by edge with ``G / (G - 1)`` (CR1): FPV 4.1,
demo UAV 1.78 (biased low with few, unequal clusters). Frames: twists ``(v m, w rad)`` of the left
perturbation in the camera frame, as :class:`mst.pipeline.tracking.vvs.VVSResult`.
"""

from __future__ import annotations

import numpy as np

#: the kernels (:mod:`mst.pipeline.tracking.covariance_kernels`: compiled ahead of time or numba's JIT)
from mst.pipeline.tracking.compiled import covariance as _ck

#: samples per cluster along a model edge: runs of this many consecutive samples (32 px at the default
#: 4 px sample step). Measured autocorrelation of the VVS residuals along an edge at lags 1 / 2 / 4 / 8 /
#: 16 samples: demo UAV 0.24 / 0.08 / 0.06 / 0.04 / -0.01, Rotterdam FPV 0.16 / -0.01 / -0.11 / 0.08 /
#: 0.2, Rotterdam 250 m survey band 0.58 / 0.53 / 0.51 / 0.03 / 0.0, turntable 320x240 0.44 / 0.17 / -0.01 / -0.29
#: / 0.0, synthetic teabox 0.2 / -0.01 / -0.04 / -0.02 / -0.02: correlated over up to 4-8 samples, not
#: beyond. The real teabox keeps 0.18-0.29 at 8-16 samples (its model edges sit 0.2-1 px off the box's
#: rounded edges, a per-edge offset): a run of 8 does not count that part, and whole edges as clusters
#: (2 sigma 2.9-3.2 % of the distance there, 10x the classical 0.33 %) refused every edges-only pose of
#: the real video; with runs of 8, 0.52 %. On the synthetic sequences runs of 8 and whole edges agree
#: within 15 % (err / sigma: demo UAV 1.93 / 1.70, FPV 1.60 / 1.42, 250 m 1.15 / 1.15)
CHUNK_SAMPLES = 8

#: a cluster whose leverages sum to less than this takes the power series of ``(1 - l)^-1/2`` (to a
#: 1e-9 relative bound) instead of an eigen-decomposition (Jacobi, ~2 us): the runs
#: among many (kernel for 142 clusters 250 -> 49 us; teabox default, 228 clusters: 1.2 -> 0.6 ms a frame)
SERIES_LEVERAGE = 0.5

#: fewer clusters than this: no cluster-robust term, the classical covariance stays. A cluster-robust
#: covariance from few clusters is itself too noisy to trust (a 6x6 estimate from G outer products; the
#: "few clusters" regime of the literature, G below a few times the parameters): on the 320x240 corridor
#: (40-60 samples: 12-20 runs) it was 1.5-2.5x the classical one while the classical was already 1.5x
#: pessimistic (err / sigma 0.45 against 0.67), and the error budget refused every correct pose after the
#: first frame; with 20 clusters or more the CR2 term is used (demo UAV, FPV, 250 m, teabox: 20-600)
MIN_CLUSTERS = 20


def edge_cluster_cov(T: np.ndarray, K: np.ndarray, X: np.ndarray, e: np.ndarray, A: np.ndarray, B: np.ndarray,
                     w: np.ndarray, r: np.ndarray, gauge: np.ndarray | None = None, gauge_lambda: float = 0.0,
                     cr2: bool = True) -> tuple[np.ndarray | None, int]:
    """The cluster-robust covariance (6, 6) of the edge pose ``T`` (T_cam_model) from the edge samples of its
    last VVS linearisation (``X`` model points, ``e`` edge ids, ``w`` weights, ``r`` residuals px; only
    samples with a candidate; a fit's KLT points are not its evidence, :mod:`mst.pipeline.tracking.vvs`)
    (``gauge``: a unit twist that no image sees, held fixed with ``gauge_lambda``, see
    :meth:`RenderEdgeProvider.gauge_cov`); ``(None, clusters)`` when it has fewer than
    :data:`MIN_CLUSTERS` clusters or a fit without one of them is singular (see
    :func:`cluster_cov_kernel`)."""
    C = np.empty((6, 6))
    cl, nC = edge_chunks(e)
    m, ok = _ck.cluster_cov_kernel(np.ascontiguousarray(X, np.float64), np.ascontiguousarray(e, np.int64), len(A), cl, nC,
                               np.ascontiguousarray(np.concatenate([A, B]), np.float64),
                               np.ascontiguousarray(T, np.float64), float(K[0, 0]), float(K[1, 1]),
                               np.ascontiguousarray(w, np.float64), np.ascontiguousarray(r, np.float64),
                               np.zeros(6) if gauge is None else np.ascontiguousarray(gauge, np.float64),
                               0.0 if gauge is None else float(gauge_lambda), bool(cr2), C)
    if not ok or m < MIN_CLUSTERS:
        return None, int(m)
    return C, int(m)


def psd_max(C_floor: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``C`` floored by ``C_floor`` along every direction (:func:`psd_max_kernel`); ``C`` where
    ``C_floor`` is not positive definite or not finite."""
    if not np.isfinite(C_floor).all():
        return C
    out = np.empty((6, 6))
    if not _ck.psd_max_kernel(np.ascontiguousarray(C_floor, np.float64), np.ascontiguousarray(C, np.float64), out):
        return C
    return out


def edge_chunks(e: np.ndarray, chunk: int = CHUNK_SAMPLES) -> tuple[np.ndarray, int]:
    """Cluster ids ``(n,) int64`` (``0 .. nC - 1``) and their count: runs of ``chunk`` consecutive samples
    of one edge (``e (n,)`` edge ids; the samples of an edge in their order along it). One kernel
    (:func:`edge_chunks_kernel`; issue #14: the sort-and-unique formulation :func:`edge_chunks_numpy`, the
    same ids, took ~0.1 ms a frame); negative ids take that formulation."""
    e = np.ascontiguousarray(e, np.int64)
    if len(e) == 0:
        return np.zeros(0, np.int64), 0
    if e.min() < 0:
        return edge_chunks_numpy(e, chunk)
    cl = np.empty(len(e), np.int64)
    return cl, int(_ck.edge_chunks_kernel(e, max(int(chunk), 1), cl))


def edge_chunks_numpy(e: np.ndarray, chunk: int = CHUNK_SAMPLES) -> tuple[np.ndarray, int]:
    """The numpy formulation of :func:`edge_chunks` (the reference of its kernel's test)."""
    e = np.asarray(e, np.int64)
    n = len(e)
    if n == 0:
        return np.zeros(0, np.int64), 0
    order = np.argsort(e, kind="stable")
    es = e[order]
    start = np.r_[0, np.flatnonzero(np.diff(es)) + 1]
    rank = np.arange(n) - np.repeat(start, np.diff(np.r_[start, n]))
    key = np.empty(n, np.int64)
    key[order] = es * (n + 1) + rank // max(int(chunk), 1)
    u, cl = np.unique(key, return_inverse=True)
    return np.ascontiguousarray(cl.reshape(-1), np.int64), int(len(u))
