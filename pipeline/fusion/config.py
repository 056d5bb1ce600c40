"""The settings of ``mst fuse`` (:class:`FuseConfig`): one section per concern, units in the names."""

from __future__ import annotations

from dataclasses import dataclass

from mst.core.config import Config, param, section
from mst.pipeline.depth_io import DepthConfig


@dataclass
class FuseConfig(Config):
    """Settings of the depth fusion (metres, degrees, pixels).

    ``depth`` is the depth section shared with ``mst track`` (raw units per metre, the trusted
    depth range, the discontinuity bound); fuse keeps DepthConfig's defaults (1000 per metre,
    0.1-50 m, 0.03 x depth). With ``tsdf`` the grid is ``tsdf_voxel_m``; otherwise ``voxel_m``
    (0: keep every sample).
    """

    depth: DepthConfig = section(DepthConfig)
    max_angle_deg: float = param(80.0, min=0, min_open=True, max=90,
                                 help="drop samples seen more obliquely than this to their surface, deg (90: off)")
    smooth_px: int = param(0, min=0, max=99, help="bilateral filter diameter applied to each depth frame, px (0: off)")
    smooth_rel: float = param(0.02, min=0, min_open=True,
                              help="bilateral range sigma, relative depth difference (0.02 = 2 % of z)")
    voxel_m: float = param(0.005, min=0, help="voxel of the down-sampling grid, m: one averaged point per voxel "
                                              "(0: keep every sample)")
    stride: int = param(1, min=1, help="fuse every stride-th depth frame")
    fps: float | None = param(None, min=0, min_open=True,
                              help="trajectory time -> frame index k = round(t * fps); null: times are frame indices")
    tsdf: bool = param(False, help="fuse a TSDF (Open3D VoxelBlockGrid) and output its surface points")
    tsdf_voxel_m: float = param(0.01, min=0, min_open=True, help="TSDF voxel, m")
    tsdf_trunc_voxels: float = param(4.0, min=0, min_open=True, help="TSDF truncation distance, voxels")
    tsdf_weight_threshold: float = param(1.0, min=0,
                                         help="extract TSDF voxels with weight > this (Open3D's test is strict)")

    @property
    def mode(self) -> str:
        """``tsdf``, ``voxel`` (one averaged point per voxel) or ``points`` (every sample)."""
        return "tsdf" if self.tsdf else ("voxel" if self.voxel_m > 0 else "points")

    @property
    def grid_m(self) -> float:
        """The grid the output is made on, m (``tsdf_voxel_m`` with ``tsdf``, else ``voxel_m``)."""
        return self.tsdf_voxel_m if self.tsdf else self.voxel_m
