"""Figures of the evaluation stages (matplotlib with the Agg backend, imported lazily).

Every function writes one PNG and returns nothing; call it inside :func:`mst.atomic_output`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def c2m_histogram(path: str | os.PathLike, distances_m: np.ndarray, thresholds_m: Sequence[float],
                  title: str = "Cloud-to-mesh distances", signed_m: np.ndarray | None = None,
                  percents: Sequence[float] | None = None) -> None:
    """Histogram of unsigned C2M distances (metres) with the Table-1 thresholds as vertical lines,
    and the percentage of points under each threshold in the legend (``percents``, e.g. Table 1's,
    else computed from ``distances_m``); a second panel with the signed distances when ``signed_m``
    is given."""
    plt = _plt()
    d = np.asarray(distances_m, np.float64)
    panels = 2 if signed_m is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(7 * panels, 4.5), squeeze=False)
    ax = axes[0, 0]
    hi = max(float(max(thresholds_m)) * 1.2, float(np.percentile(d, 99.5)) if len(d) else 1.0)
    ax.hist(np.clip(d, 0, hi), bins=200, range=(0, hi), color="#4477aa")
    for k, (t, c) in enumerate(zip(thresholds_m, ["#cc3311", "#ee7733", "#009988", "#aa3377", "#555555"] * 4)):
        pct = percents[k] if percents is not None else 100.0 * np.count_nonzero(d < t) / max(len(d), 1)
        ax.axvline(t, color=c, ls="--", label=f"< {t:g} m: {pct:.1f} %")
    ax.set_xlabel("unsigned distance [m] (last bin: at or beyond the axis end)")
    ax.set_ylabel("points")
    ax.set_title(f"{title} ({len(d):,} points)")
    ax.legend()
    if signed_m is not None:
        s = np.asarray(signed_m, np.float64)
        ax2 = axes[0, 1]
        ax2.hist(np.clip(s, -hi, hi), bins=200, range=(-hi, hi), color="#66ccee")
        ax2.axvline(0, color="k", lw=0.8)
        ax2.set_xlabel("signed distance [m] (negative: inside / behind the faces)")
        ax2.set_title("signed")
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)


def trajectory_figure(path: str | os.PathLike, t_ref_s: np.ndarray, xyz_ref_m: np.ndarray, t_est_s: np.ndarray,
                      xyz_est_m: np.ndarray, diff_xyz_m: np.ndarray, diff_yaw_deg: np.ndarray | None,
                      gaps_s: Sequence[tuple[float, float]] = (), title: str = "") -> None:
    """Top-down view (X-Y, model frame) of reference and (aligned) estimate, and per-axis differences
    dX dY dZ (metres) and d-yaw (degrees) over time, with the tracking gaps shaded."""
    plt = _plt()
    # break the estimate's lines where tracking was lost (no line drawn across a gap)
    t_est_s = np.asarray(t_est_s, np.float64)
    if len(t_est_s) > 2:
        step = np.median(np.diff(t_est_s))
        cut = np.nonzero(np.diff(t_est_s) > 1.5 * step)[0] + 1
        t_est_s = np.insert(t_est_s, cut, np.nan)
        xyz_est_m = np.insert(np.asarray(xyz_est_m, np.float64), cut, np.nan, axis=0)
        diff_xyz_m = np.insert(np.asarray(diff_xyz_m, np.float64), cut, np.nan, axis=0)
        if diff_yaw_deg is not None:
            diff_yaw_deg = np.insert(np.asarray(diff_yaw_deg, np.float64), cut, np.nan)
    fig = plt.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(xyz_ref_m[:, 0], xyz_ref_m[:, 1], "-", color="#999999", lw=2, label="reference")
    ax.plot(xyz_est_m[:, 0], xyz_est_m[:, 1], ".-", color="#cc3311", ms=2, lw=0.8, label="estimate")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_title(title or "trajectories (top view)")
    ax.legend()
    n = 4 if diff_yaw_deg is not None else 3
    labels = ["dX [m]", "dY [m]", "dZ [m]", "d-yaw [deg]"]
    for k in range(n):
        a = fig.add_subplot(n, 2, 2 * k + 2)
        y = diff_xyz_m[:, k] if k < 3 else diff_yaw_deg
        a.plot(t_est_s, y, ".-", ms=2, lw=0.8, color="#4477aa")
        a.axhline(0, color="k", lw=0.5)
        for g0, g1 in gaps_s:
            a.axvspan(g0, g1, color="#ffcccc", lw=0)
        a.set_ylabel(labels[k])
        if k == n - 1:
            a.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)
