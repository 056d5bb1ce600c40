"""``TrajConfig``: the settings of ``mst eval traj`` on :mod:`mst.core.config` (seconds, metres,
degrees in the names; bounds checked once, here; a bad CSV column spec is a ConfigError of csv_columns)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mst.core.config import Config, param
from mst.core.trajectory import TRAJECTORY_FORMATS, parse_csv_columns

_INF = math.inf


@dataclass
class TrajConfig(Config):
    """Settings of the trajectory comparison (``mst eval traj``)."""

    align: str = param("se3", choices=("none", "se3", "sim3", "first"),
                       help="alignment of the estimate onto the reference: Umeyama without/with scale, first pose, none")
    t_max_diff_s: float = param(0.01, min=0, max=_INF, max_open=True,
                                help="association tolerance (evo's default): poses match within this, s")
    t_offset_s: float = param(0.0, min=-_INF, min_open=True, max=_INF, max_open=True,
                              help="added to the estimate's timestamps, s")
    delta_frames: int = param(1, min=1, help="RPE step in frames")
    delta_m: float = param(1.0, min=0, min_open=True, max=_INF, max_open=True, help="RPE step in metres of path")
    yaw_offset_deg: float = param(0.0, min=-_INF, min_open=True, max=_INF, max_open=True,
                                  help="constant camera-mount yaw offset removed from d-yaw, deg")
    format: str = param("auto", choices=TRAJECTORY_FORMATS,
                        help="trajectory file format (auto: .csv -> csv, 12 numbers per line -> kitti, else tum)")
    csv_columns: str | None = param(None, help="CSV columns as key=column pairs, e.g. t=time,x=e,y=n,z=h "
                                               "(keys t x y z qx qy qz qw; unnamed keys: the column of that name)")
    fps: float | None = param(None, min=0, min_open=True, max=_INF, max_open=True,
                              help="KITTI files: timestamps are line index / fps (null: the index)")

    def check(self) -> None:
        parse_csv_columns(self.csv_columns)  # a bad spec is a ConfigError of csv_columns
