"""``C2MConfig``: the settings of ``mst c2m`` on :mod:`mst.core.config` (distances in metres, the
model's units; bounds checked once, here)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mst.core.config import Config, param
from mst.errors import ConfigError

DEFAULT_THRESHOLDS = (0.1, 0.2, 0.5, 1.0)


@dataclass
class C2MConfig(Config):
    """Settings of the cloud-to-mesh distance stage (``mst c2m``)."""

    thresholds_m: tuple[float, ...] = param(DEFAULT_THRESHOLDS, min=0, min_open=True, max=math.inf, max_open=True,
                                            help="Table-1 columns: max. C2M distances, m")
    signed: bool = param(False, help="also signed distances (+ on the side the faces point to)")
    max_dist_m: float | None = param(None, min=0, min_open=True, max=math.inf, max_open=True,
                                     help="points farther are counted as beyond it and left out of the "
                                          "overall statistics, m (null: no limit)")
    chunk_points: int = param(1_000_000, min=1000, help="points per streamed chunk (memory bound)")
    workers: int = param(2, min=1, help="chunks processed concurrently by the BVH engine (threads)")
    small_mesh_triangles: int = param(5000, min=0, help="grid engine: meshes up to this many triangles use the "
                                                         "dense grid of candidate lists, larger ones the binned grid")
    engine: str = param("auto", choices=("auto", "grid", "bvh"),
                        help="nearest-triangle search: auto (= grid, compiled exact float64) or bvh (Open3D's "
                             "float32 BVH + exact float64 recheck)")

    def check(self) -> None:
        if not self.thresholds_m:
            raise ConfigError("thresholds_m", "needs at least one threshold")
