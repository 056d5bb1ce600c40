"""Motion models and the Kalman-filter driver of :mod:`mst.pipeline.nav.fusion`: constant-velocity
and constant-acceleration transition/noise matrices, a robust KF/RTS run over sorted measurements,
and the innovation likelihood that ``adapt_motion_noise`` uses to choose the process noise."""

from __future__ import annotations

import numpy as np

from mst.pipeline.nav.compiled import kernels as _nk  # ahead of time or numba JIT


# ------------------------------------------------------------------------------ Kalman / RTS kernel
def _cv_model(dt: np.ndarray, q: float, extra: int = 0, q_extra: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity model in 3-D for steps dt (K,): F, Q (K, n, n), n = 6 + 3*extra; state
    [value(3), rate(3), extra random walks(3 each)] with white 2nd-derivative PSD q and walk PSD q_extra."""
    K = len(dt)
    n = 6 + 3 * extra
    F = np.tile(np.eye(n), (K, 1, 1))
    Q = np.zeros((K, n, n))
    i3 = np.arange(3)
    F[:, i3, i3 + 3] = dt[:, None]
    Q[:, i3, i3] = (q * dt**3 / 3)[:, None]
    Q[:, i3, i3 + 3] = Q[:, i3 + 3, i3] = (q * dt**2 / 2)[:, None]
    Q[:, i3 + 3, i3 + 3] = (q * dt)[:, None]
    for e in range(extra):
        j = 6 + 3 * e + i3
        Q[:, j, j] = (q_extra * dt)[:, None]
    return F, Q


def _ca_model(dt: np.ndarray, q_jerk: float, q_extra: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-acceleration model in 3-D for steps dt (K,): F, Q (K, 12, 12); state [value(3),
    rate(3), 2nd derivative(3), a random walk(3)] with white 3rd-derivative (jerk) PSD ``q_jerk`` and
    walk PSD ``q_extra``."""
    K = len(dt)
    F = np.tile(np.eye(12), (K, 1, 1))
    Q = np.zeros((K, 12, 12))
    i3 = np.arange(3)
    F[:, i3, i3 + 3] = F[:, i3 + 3, i3 + 6] = dt[:, None]
    F[:, i3, i3 + 6] = (dt**2 / 2)[:, None]
    blk = np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2], [dt**3 / 6, dt**2 / 2, dt]])
    for a in range(3):
        for b in range(3):
            Q[:, 3 * a + i3, 3 * b + i3] = (q_jerk * blk[a, b])[:, None]
    Q[:, 9 + i3, 9 + i3] = (q_extra * dt)[:, None]
    return F, Q


#: process-noise scales (of the PSD, i.e. sigma^2) tried by ``adapt_motion_noise``
MOTION_NOISE_SCALES = 4.0 ** np.arange(-2, 9)


def _innovation_loglik(F, Q, x0, P0, step, z, H, R, gate_k: float = 3.0) -> float:
    """Log-likelihood of the measurements under the model (F, Q): the sum over measurements of
    ``log N(nu; 0, S)`` with the innovations ``nu`` of a causal filter run (Huber-robust: beyond
    ``gate_k`` the Mahalanobis distance counts linearly; measurements of one step each against the
    step's prediction). The prediction error decomposition of the likelihood, used to choose Q."""
    K = F.shape[0]
    order = np.argsort(step, kind="stable")
    st, zz, HH, RR = step[order], np.ascontiguousarray(z[order]), np.ascontiguousarray(H[order]), np.ascontiguousarray(R[order])
    ptr = np.searchsorted(st, np.arange(K + 1)).astype(np.int64)
    x, P, _ = _nk.kf_rts(F, Q, x0, P0, ptr, zz, HH, RR, np.ones(len(st)), gate_k, False)
    xp = x.copy()
    Pp = P.copy()
    xp[1:] = np.einsum("kij,kj->ki", F[1:], x[:-1])
    Pp[1:] = F[1:] @ P[:-1] @ np.swapaxes(F[1:], 1, 2) + Q[1:]
    Pp[0] = P0
    xp[0] = x0
    nu = zz - np.einsum("lmn,ln->lm", HH, xp[st])
    S = HH @ Pp[st] @ np.swapaxes(HH, 1, 2) + RR
    sign, logdet = np.linalg.slogdet(S)
    d = np.sqrt(np.maximum(np.einsum("lm,lm->l", nu, np.linalg.solve(S, nu[..., None])[..., 0]), 0.0))
    rho = np.where(d <= gate_k, d**2, 2 * gate_k * d - gate_k**2)  # Huber: outliers count linearly
    return float(-0.5 * np.sum(rho + logdet))


def _best_noise_scale(model, x0, P0, step, z, H, R) -> float:
    """The scale of :data:`MOTION_NOISE_SCALES` whose ``model(scale) -> (F, Q)`` gives the data the
    highest innovation likelihood."""
    ll = [_innovation_loglik(*model(s), x0, P0, step, z, H, R) for s in MOTION_NOISE_SCALES]
    return float(MOTION_NOISE_SCALES[int(np.argmax(ll))])


def _best_noise_scale_blocks(model, dts, x0_of, P0, step, z, H, R, max_frames: int = 3000, n_blocks: int = 4) -> float:
    """:func:`_best_noise_scale` of ``model(dts, scale) -> (F, Q)`` on at most ``max_frames`` frames:
    beyond that, ``n_blocks`` evenly spaced contiguous blocks of the grid, each filtered from its own
    diffuse start ``x0_of(z of the block)``, their log-likelihoods summed (a 10-minute log at 30 fps:
    18,000 frames, 11 scales; the motion's character is read from 4 x 750 frames)."""
    ll = noise_scale_loglik_blocks(model, dts, x0_of, P0, step, z, H, R, max_frames, n_blocks)
    return float(MOTION_NOISE_SCALES[int(np.argmax(ll))])


def noise_scale_loglik_blocks(model, dts, x0_of, P0, step, z, H, R, max_frames: int = 3000, n_blocks: int = 4
                              ) -> np.ndarray:
    """The innovation log-likelihood of each scale of :data:`MOTION_NOISE_SCALES` (11,), on the frames
    :func:`_best_noise_scale_blocks` reads."""
    K = len(dts)
    blocks = []
    if K > max_frames:
        L = max_frames // n_blocks
        for a in np.linspace(0, K - L, n_blocks).astype(np.int64):
            m = (step >= a) & (step < a + L)
            if m.sum() < 2:
                continue
            d = dts[a:a + L].copy()
            d[0] = 0.0
            blocks.append((d, step[m] - a, z[m], H[m], R[m]))
    if not blocks:
        blocks = [(dts, step, z, H, R)]
    return np.array([sum(_innovation_loglik(*model(d, s), x0_of(zb), P0, sb, zb, Hb, Rb) for d, sb, zb, Hb, Rb in blocks)
                     for s in MOTION_NOISE_SCALES])


def _run_kf(F, Q, x0, P0, step, z, H, R, gate_k, smooth, robust_refit):
    """Sort measurements by step, run the kernel (twice when ``robust_refit``: Huber weights from the
    smoothed residuals). Returns x, P, per-measurement weights (in the input order)."""
    K = F.shape[0]
    order = np.argsort(step, kind="stable")
    st, zz, HH, RR = step[order], np.ascontiguousarray(z[order]), np.ascontiguousarray(H[order]), np.ascontiguousarray(R[order])
    ptr = np.searchsorted(st, np.arange(K + 1)).astype(np.int64)
    w = np.ones(len(st))
    x, P, w = _nk.kf_rts(F, Q, x0, P0, ptr, zz, HH, RR, w, gate_k, smooth)
    if robust_refit and len(st):
        r = zz - np.einsum("lmn,ln->lm", HH, x[st])
        d = np.sqrt(np.einsum("lm,lm->l", r, np.linalg.solve(RR, r[..., None])[..., 0]))
        w = np.where(d > gate_k, gate_k / np.maximum(d, 1e-12), 1.0)
        x, P, w = _nk.kf_rts(F, Q, x0, P0, ptr, zz, HH, RR, w, 0.0, smooth)
    wo = np.empty_like(w)
    wo[order] = w
    return x, P, wo
