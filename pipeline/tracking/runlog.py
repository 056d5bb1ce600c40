"""What a tracking run keeps of its frames until it writes its outputs: :class:`RunLog`.

A run of ``mst track`` writes its trajectory, per-frame CSV and covariance CSV at the end (all or nothing,
through temporary files). Until then it holds, per frame, only what those outputs and the summary read: the
frame's CSV line (as written), its time, status, timing, health score and the rounded residual and
projection-error values that the summary averages, and the output pose (12 numbers) and covariance (36) in
preallocated float64 blocks that double when full. Kept as one :class:`~mst.pipeline.tracking.session.FrameRecord`
per frame (session 20: without its per-sample arrays), a run had grown by ~3.4 KB a frame edges only and
~6 KB with the rgbd aid (Python objects, small arrays and the allocator's fragmentation between them); this
log's layout is ~0.5 KB a frame (up to twice its numbers' part just after a doubling), and the ping-pong orbit's
peak RSS grew by 0.23-0.33 KB a frame (README).
"""

from __future__ import annotations

import csv
import io

import numpy as np

from mst.pipeline.tracking.session import OUTPUT_STATUSES as STATUSES  # a frame's status, stored as its index


class RunLog:
    """Per-frame results of a run, appended in frame order (:meth:`add`); ``first`` the first frame's record
    (the error message of a run that tracked nothing reads its edge evidence)."""

    def __init__(self, capacity: int = 256):
        self.n = 0
        self.first = None
        self.index = np.empty(capacity, np.int64)
        self.time_s = np.empty(capacity)
        self.ms = np.empty(capacity)
        self.score = np.empty(capacity)
        self.residual_px = np.empty(capacity)    # as written to the CSV (rounded), NaN where not finite
        self.proj_error_deg = np.empty(capacity)  # as written
        self.status = np.empty(capacity, np.int8)
        self.pose = np.empty((capacity, 12))      # T_cam_model's first 3 rows; NaN where no output pose
        self.cov = np.empty((capacity, 36))       # NaN where no covariance
        self.lines: list[str] = []                # the traj.csv line of each frame, without its end of line

    def __len__(self) -> int:
        return self.n

    def _grow(self) -> None:
        for name in ("index", "time_s", "ms", "score", "residual_px", "proj_error_deg", "status", "pose", "cov"):
            a = getattr(self, name)
            b = np.empty((2 * len(a),) + a.shape[1:], a.dtype)
            b[: self.n] = a[: self.n]
            setattr(self, name, b)

    def add(self, rec) -> None:
        """Keep a :class:`~mst.pipeline.tracking.session.FrameRecord` (its per-sample arrays are not kept)."""
        if self.n == len(self.index):
            self._grow()
        if self.first is None:
            self.first = rec.kept()
        i, fr = self.n, rec.result
        row = rec.csv_row()
        self.index[i], self.time_s[i], self.ms[i] = rec.index, rec.time_s, rec.ms
        self.score[i] = fr.score
        self.residual_px[i], self.proj_error_deg[i] = float(row[5]), float(row[6])
        self.status[i] = STATUSES.index(rec.status)
        self.pose[i] = np.nan if rec.T_cam_model is None else np.asarray(rec.T_cam_model, float)[:3].ravel()
        self.cov[i] = np.nan if rec.cov is None else np.asarray(rec.cov, float).ravel()
        buf = io.StringIO()
        csv.writer(buf, lineterminator="").writerow(row)
        self.lines.append(buf.getvalue())
        self.n += 1

    # ------------------------------------------------------------------ reading
    def statuses(self) -> list[str]:
        return [STATUSES[s] for s in self.status[: self.n]]

    def tracked(self) -> np.ndarray:
        """(n,) bool: the frames with an output pose."""
        return np.isfinite(self.pose[: self.n, 0])

    def poses(self, rows: np.ndarray | None = None) -> np.ndarray:
        """(k, 4, 4) ``T_cam_model`` of the frames ``rows`` (default: all; NaN where none)."""
        P = self.pose[: self.n] if rows is None else self.pose[: self.n][rows]
        T = np.zeros((len(P), 4, 4))
        T[:, :3] = P.reshape(-1, 3, 4)
        T[:, 3, 3] = 1.0
        return T

    def covariance(self, i: int) -> np.ndarray | None:
        c = self.cov[i]
        return None if np.isnan(c).all() else c.reshape(6, 6).copy()

    def csv_text(self, header: list[str]) -> str:
        """The whole ``traj.csv``: ``header`` and each frame's line."""
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow(header)
        return buf.getvalue() + "".join(line + "\n" for line in self.lines)
