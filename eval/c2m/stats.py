"""Streaming statistics of C2M distances (all in metres) and their typed results.

:class:`Moments` merges chunk statistics exactly (Chan et al.); :class:`DistanceStats` holds count /
mean / median / std (population) / RMS / min / max of one distance kind (unsigned or signed);
:class:`ThresholdRow` one column of the RGB-D paper's Table 1 (share of valid points under a
threshold, mean and std of those distances).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class Moments:
    """Streaming count / mean / M2 (Chan et al. merge), min, max, sum of squares."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0
        self.sumsq = 0.0
        self.min, self.max = np.inf, -np.inf

    def add(self, x: np.ndarray, extremes: bool = True) -> None:
        """Merge the values ``x`` (their min/max too with ``extremes``)."""
        k = len(x)
        if not k:
            return
        x = np.asarray(x, np.float64)
        lo, hi = (float(x.min()), float(x.max())) if extremes else (np.inf, -np.inf)
        self.add_sums(k, float(x.sum()), float(np.dot(x, x)), lo, hi)

    def add_sums(self, k: int, s1: float, s2: float, lo: float = np.inf, hi: float = -np.inf) -> None:
        """Merge a block given its count, sum and sum of squares (and optional min/max)."""
        if not k:
            return
        mu = s1 / k
        m2 = max(s2 - k * mu * mu, 0.0)  # the block's M2; merged exactly below (Chan et al.)
        delta = mu - self.mean
        tot = self.n + k
        self.mean += delta * k / tot
        self.m2 += m2 + delta * delta * self.n * k / tot
        self.n = tot
        self.sumsq += s2
        self.min = min(self.min, lo)
        self.max = max(self.max, hi)

    def std(self) -> float:
        return float(np.sqrt(self.m2 / self.n)) if self.n else float("nan")


@dataclass(frozen=True)
class DistanceStats:
    """Overall statistics of one distance kind; every value None when no point counted (count 0)."""

    count: int
    mean: float | None = None
    median: float | None = None
    std: float | None = None
    rms: float | None = None
    min: float | None = None
    max: float | None = None

    @classmethod
    def from_moments(cls, mo: Moments, values: np.ndarray) -> DistanceStats:
        """The statistics of the values merged into ``mo``; ``values`` (the same values, any order) give
        the median and are partitioned in place."""
        if mo.n == 0:
            return cls(count=0)
        return cls(count=mo.n, mean=mo.mean, median=median_in_place(values), std=mo.std(),
                   rms=float(np.sqrt(mo.sumsq / mo.n)), min=mo.min, max=mo.max)

    def to_json(self) -> dict:
        return {"count": self.count, "mean": self.mean, "median": self.median, "std": self.std, "rms": self.rms,
                "min": self.min, "max": self.max}


def median_in_place(values: np.ndarray) -> float:
    """The median of the NaN-free 1-D ``values``, partitioning them in place (the stored distances are
    only needed unordered afterwards): ``np.median(values, overwrite_input=True)``'s value, in the
    array's dtype, without its NaN check (whose first use imports numpy.ma, 11 ms of every run)."""
    n = len(values)
    h = n // 2
    if n % 2:
        values.partition(h)
        return float(values[h])
    values.partition([h - 1, h])
    return float((values[h - 1] + values[h]) / 2)


@dataclass(frozen=True)
class ThresholdRow:
    """One Table-1 column: of the ``n_valid`` finite points, ``count`` lie closer than ``max_dist``."""

    max_dist: float
    percent: float
    count: int
    mean: float | None
    std: float | None

    @classmethod
    def from_moments(cls, t: float, mo: Moments, n_valid: int) -> ThresholdRow:
        return cls(max_dist=float(t), percent=100.0 * mo.n / n_valid, count=mo.n,
                   mean=mo.mean if mo.n else None, std=mo.std() if mo.n else None)

    def to_json(self) -> dict:
        return {"max_dist": self.max_dist, "percent": self.percent, "count": self.count, "mean": self.mean,
                "std": self.std}
