"""Tracking overlays: the projected model edges and the moving-edge samples drawn on a frame.

Colours (BGR): visible projected model edges blue-orange, samples green (inliers of the robust
pose) or red (outliers / no edge found), KLT points yellow, the frame status on top. Overlays go to
a video (.mp4/.avi, OpenCV ``mp4v``) or to a folder of PNGs, written under a temporary name and
renamed into place only when tracking succeeds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mst import InputError


def draw_overlay(bgr: np.ndarray, fr, status: str) -> np.ndarray:
    """Draw a :class:`mst.pipeline.tracking.FrameResult` ``fr`` (pixels) on a copy of ``bgr``."""
    import cv2

    out = bgr.copy()
    for a, b in fr.edge_uv:
        cv2.line(out, (int(round(a[0])), int(round(a[1]))), (int(round(b[0])), int(round(b[1]))), (255, 128, 0), 1, cv2.LINE_AA)
    if len(fr.uv):
        H, W = out.shape[:2]
        ix = np.clip(np.rint(fr.uv[:, 0]).astype(int), 0, W - 1)
        iy = np.clip(np.rint(fr.uv[:, 1]).astype(int), 0, H - 1)
        inl = fr.inlier if len(fr.inlier) == len(ix) else np.zeros(len(ix), bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                yy, xx = np.clip(iy + dy, 0, H - 1), np.clip(ix + dx, 0, W - 1)
                out[yy[inl], xx[inl]] = (0, 255, 0)
                out[yy[~inl], xx[~inl]] = (0, 0, 255)
    for p in fr.klt_uv:
        cv2.circle(out, (int(round(p[0])), int(round(p[1]))), 2, (0, 255, 255), -1)
    col = (0, 200, 0) if status in ("model", "slam") else (0, 0, 255)
    cv2.putText(out, f"{status} in={fr.n_inliers}/{fr.n_samples} res={fr.residual_px:.2f}px pe={fr.proj_error_deg:.1f}deg",
                (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, col, 1, cv2.LINE_AA)
    return out


class OverlayWriter:
    """Writes overlay frames to an .mp4/.avi (OpenCV ``mp4v``) or a folder of PNGs."""

    def __init__(self, path: Path, fps: float):
        self.final = Path(path)
        if not self.final.parent.exists():
            raise InputError(self.final, "output folder does not exist")
        self.is_video = self.final.suffix.lower() in (".mp4", ".avi", ".mov", ".mkv")
        # written under a temporary name, renamed by commit() (no partial overlay on failure)
        self.path = self.final.with_name(f".{self.final.stem}.{os.getpid()}.tmp{self.final.suffix}")
        self.fps = fps
        self.writer = None
        self.count = 0
        if not self.is_video:
            self.path.mkdir(parents=True, exist_ok=True)

    def write(self, img: np.ndarray, index: int) -> None:
        import cv2

        if self.is_video:
            if self.writer is None:
                self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                              (img.shape[1], img.shape[0]))
            self.writer.write(img)
        else:
            cv2.imwrite(str(self.path / f"{index:06d}.png"), img)
        self.count += 1

    def close(self, commit: bool = False) -> None:
        """Finish; with ``commit`` move the result onto the target, else delete it."""
        import shutil

        if self.writer is not None:
            self.writer.release()
            self.writer = None
        if not self.path.exists():
            return
        if commit:
            if self.final.is_dir() and not self.is_video:
                shutil.rmtree(self.final)
            os.replace(self.path, self.final)
        elif self.path.is_dir():
            shutil.rmtree(self.path)
        else:
            self.path.unlink()
