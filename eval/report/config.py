"""``ReportConfig``: the settings of ``mst report`` on :mod:`mst.core.config`."""

from __future__ import annotations

from dataclasses import dataclass

from mst.core.config import Config, param


@dataclass
class ReportConfig(Config):
    """Settings of the HTML report (``mst report``)."""

    overlay_frames: int = param(6, min=0, max=48, help="frames in the overlay strip (evenly spaced; 0: none)")
    overlay_width_px: int = param(320, min=64, max=1920, help="width of each overlay frame in the page, px")
    cloud_points: int = param(200_000, min=1000, help="at most this many cloud points are drawn in the views "
                                                      "(evenly subsampled)")
    c2m_max_points: int = param(20_000_000, min=0, help="the C2M distances of the cloud views and histogram are "
                                                        "recomputed for clouds up to this size (larger: coloured by height)")
    dpi: int = param(90, min=30, max=300, help="resolution of the figures")
