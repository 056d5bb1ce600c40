"""What any fusion of a vision track with GPS can reach: an oracle Wiener bound on the position RMSE.

Per axis, on the frame grid (``fps``), three information sources, each seen per DFT bin k as
Gaussian with the power it actually has:

* the vision error ``e`` (the tracked positions minus the truth): power ``|E_k|^2`` of its realised
  values -- the oracle knows the error's spectrum exactly (a slow bias is all in the lowest bins);
* the GPS noise, the rows of each frame interval averaged: white ``sigma`` at ``rate_hz`` plus a
  random-walk bias (``walk`` m/sqrt(s)); its expected power ``P_k`` by Monte Carlo;
* optionally a motion prior: the fusion's constant-acceleration model, white jerk of density ``q``
  (m/s^3/sqrt(Hz)): position power ``fps q^2 / (2 pi f_k)^6`` per bin (it pins only the highest
  bins); or an oracle one, the power ``|X_k|^2`` of the true trajectory itself (minus the ramp
  joining its ends, so the circular DFT sees no jump): what a motion model that knew the flight's
  exact spectrum would add.

The bin's error power is ``1 / (1/|E_k|^2 + 1/P_k [+ 1/|X_k|^2])`` (independent Gaussian evidence);
the bound is the RMS over frames and axes (Parseval). An estimator that knew the spectra exactly
and was linear and time-invariant cannot do better; a real smoother knows less. Metres, seconds.
"""

from __future__ import annotations

import numpy as np


def _power(x: np.ndarray) -> np.ndarray:
    """|DFT|^2 per bin and axis of (N, 3) samples, scaled so that the bins' mean is the samples' mean square."""
    return np.abs(np.fft.fft(x, axis=0)) ** 2 / len(x)


def gps_frame_noise_power(n: int, fps: float, rate_hz: float, sigma_m, walk_m_per_sqrt_s: float,
                          draws: int = 200, seed: int = 0) -> np.ndarray:
    """(n, 3) expected power per bin of the GPS noise averaged over each frame interval (``rate_hz``
    >= ``fps``: at least one row per frame, on average)."""
    if rate_hz < fps:
        raise ValueError("the bound averages the GPS rows of each frame: needs rate_hz >= fps")
    rng = np.random.default_rng(seed)
    rows = int(np.ceil(n * rate_hz / fps))
    frame = np.minimum((np.arange(rows) * fps / rate_hz).astype(np.int64), n - 1)
    cnt = np.bincount(frame, minlength=n).astype(float)
    P = np.zeros((n, 3))
    for _ in range(draws):
        w = rng.normal(size=(rows, 3)) * np.asarray(sigma_m, float)
        w += np.cumsum(rng.normal(0.0, walk_m_per_sqrt_s / np.sqrt(rate_hz), (rows, 3)), axis=0)
        avg = np.stack([np.bincount(frame, w[:, j], minlength=n) for j in range(3)], 1) / cnt[:, None]
        P += _power(avg)
    return P / draws


def oracle_fusion_rmse(err_v: np.ndarray, fps: float, rate_hz: float, sigma_m=(3.0, 3.0, 5.0),
                       walk_m_per_sqrt_s: float = 0.05, jerk_psd: float | None = None,
                       truth: np.ndarray | None = None) -> float:
    """The oracle Wiener bound (module doc) on the fused position RMSE of frames whose vision error is
    ``err_v`` (N, 3) on a regular grid of ``fps``; motion prior: ``jerk_psd`` (the constant-
    acceleration model's white jerk, m/s^3/sqrt(Hz)) and/or ``truth`` (N, 3), the true positions
    (the oracle prior); neither: GPS and vision alone."""
    err_v = np.asarray(err_v, float)
    n = len(err_v)
    inv = 1.0 / np.maximum(_power(err_v), 1e-30)
    inv += 1.0 / gps_frame_noise_power(n, fps, rate_hz, sigma_m, walk_m_per_sqrt_s)
    if jerk_psd is not None and jerk_psd > 0:
        f = np.abs(np.fft.fftfreq(n, 1.0 / fps))
        with np.errstate(divide="ignore"):
            inv += np.where(f > 0, (2 * np.pi * f) ** 6 / (fps * jerk_psd**2), 0.0)[:, None]
    if truth is not None:
        x = np.asarray(truth, float)
        ramp = x[0] + np.linspace(0.0, 1.0, len(x))[:, None] * (x[-1] - x[0])
        inv += 1.0 / np.maximum(_power(x - ramp), 1e-30)
    return float(np.sqrt(np.mean(np.sum(1.0 / inv, axis=1))))


def _filled(grid: np.ndarray, frame: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(N, 3) samples at ``frame`` linearly interpolated onto ``grid``."""
    return np.stack([np.interp(grid, frame, a[:, j]) for j in range(3)], 1)


def tracked_fusion_bound(frame: np.ndarray, err_v: np.ndarray, fps: float, rate_hz: float, sigma_m=(3.0, 3.0, 5.0),
                         walk_m_per_sqrt_s: float = 0.05, jerk_psd: float | None = None,
                         truth: np.ndarray | None = None, max_hole: int = 3) -> float:
    """:func:`oracle_fusion_rmse` over a tracked trajectory with gaps: ``frame`` (N,) increasing frame
    indices of the poses, ``err_v`` (N, 3) their position errors, ``truth`` (N, 3) their true
    positions. Runs of poses whose holes are at most ``max_hole`` frames (filled linearly) are bounded
    each on its own grid (a longer gap carries no vision); the result is their RMS weighted by poses."""
    frame = np.asarray(frame, np.int64)
    cut = np.flatnonzero(np.diff(frame) > max_hole + 1) + 1
    tot, cnt = 0.0, 0
    for idx in np.split(np.arange(len(frame)), cut):
        if len(idx) < 4:
            continue
        grid = np.arange(frame[idx[0]], frame[idx[-1]] + 1)
        b = oracle_fusion_rmse(_filled(grid, frame[idx], np.asarray(err_v, float)[idx]), fps, rate_hz, sigma_m,
                               walk_m_per_sqrt_s, jerk_psd,
                               None if truth is None else _filled(grid, frame[idx], np.asarray(truth, float)[idx]))
        tot += b * b * len(idx)
        cnt += len(idx)
    return float(np.sqrt(tot / cnt)) if cnt else float("nan")
