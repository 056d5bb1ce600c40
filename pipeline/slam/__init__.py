"""mst.pipeline.slam: the model-aided SLAM aid of ``mst track``: KLT/PnP front end, mono/rgbd
landmarks, keyframes, guarded local BA, the edge/SLAM fusion policy, standby, relocalisation.

May import mst.core, mst.errors and mst.pipeline.depth_io (pycolmap/pyceres lazily, for the BA);
never the tracker, mst.eval or mst.cli. The story is in :mod:`mst.pipeline.slam.aid`; this package
re-exports the public names.
"""

from mst.pipeline.slam.aid import ModelAidedSlam
from mst.pipeline.slam.config import SlamConfig, StandbyConfig, slam_depth_config, slam_klt_config
from mst.pipeline.slam.geometry import pose_information, prior_covariance_wv, triangulate_two_view
from mst.pipeline.slam.landmarks import bilinear_depth
from mst.pipeline.slam.policy import Verdict
from mst.pipeline.slam.standby import StandbyAid, make_aid
from mst.pipeline.slam.state import STATUS_LOST, STATUS_MODEL, STATUS_SLAM, FrameState, Keyframe

__all__ = ["STATUS_LOST", "STATUS_MODEL", "STATUS_SLAM", "FrameState", "Keyframe", "ModelAidedSlam", "SlamConfig",
           "StandbyAid", "StandbyConfig", "Verdict", "bilinear_depth", "make_aid", "pose_information",
           "prior_covariance_wv", "slam_depth_config", "slam_klt_config", "triangulate_two_view"]
