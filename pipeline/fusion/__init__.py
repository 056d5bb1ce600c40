"""mst.pipeline.fusion: depth frames + trajectory -> one point cloud in model coordinates (``mst fuse``).

Holds the config, the per-frame filters, the accumulators, the pure core :func:`fuse_frames` and
the file runner :func:`fuse`; imports :mod:`mst.core`, :mod:`mst.errors` and ``depth_io`` only.

Frames and units
----------------
* Depth pixels are z-depth in metres in the **depth camera** frame (x right, y down, z forward);
  ``K`` and distortion come from the depth camera file.
* The trajectory (TUM) holds camera poses in model coordinates, ``T_model_cam``. By default the
  trajectory's camera *is* the depth camera. When the trajectory is the **colour** camera's (what
  ``mst track`` writes when it tracks colour frames), ``T_depth_color`` (ViSP's ``depth_M_color``)
  maps colour-camera points to depth-camera points, ``X_depth = T_depth_color @ X_color``, and the
  depth camera pose is ``T_model_depth = T_model_color @ inv(T_depth_color)``.
* Frame association: depth frame ``k`` is the ``k``-th file of the depth folder in natural order.
  A pose at time ``t`` belongs to frame ``k = t`` (``mst track`` on an image sequence writes the
  frame index as time), or ``k = round(t * fps)`` with ``fps`` (videos, ``mst synth``'s ``gt.txt``).
  Frames with no pose (lost while tracking) are skipped and counted.
* Output points are float64 metres in model coordinates (georeferenced coordinates keep their
  precision: all sums are taken relative to a local origin, the first fused camera centre).

Memory is bounded by the output, not by the sequence length: frames are streamed one at a time into
a voxel accumulator (sorted packed int64 voxel keys with running sums and counts, merged per frame
with ``np.unique``/``np.searchsorted``), an Open3D ``VoxelBlockGrid`` TSDF (``tsdf``), or, with
``voxel_m = 0``, a list of per-frame point arrays (the output itself).
"""

from mst.pipeline.fusion.accumulators import PointList, TSDFAccumulator, VoxelAccumulator
from mst.pipeline.fusion.config import FuseConfig
from mst.pipeline.fusion.core import Cloud, FuseFrame, FuseStats, fuse_frames
from mst.pipeline.fusion.filters import (
    backproject,
    depth_edge_mask,
    grazing_mask,
    pixel_rays,
    sample_colors,
    smooth_depth,
)
from mst.pipeline.fusion.ply import read_ply_points, write_ply
from mst.pipeline.fusion.runner import frame_index_of_times, fuse, read_extrinsic

__all__ = ["Cloud", "FuseConfig", "FuseFrame", "FuseStats", "PointList", "TSDFAccumulator", "VoxelAccumulator",
           "backproject", "depth_edge_mask", "frame_index_of_times", "fuse", "fuse_frames", "grazing_mask",
           "pixel_rays", "read_extrinsic", "read_ply_points", "sample_colors", "smooth_depth", "write_ply"]
