"""The SLAM aid's settings (``track``'s ``slam`` section) on :mod:`mst.core.config`.

Strict like every stage config: an unknown key is a :class:`~mst.errors.ConfigError` naming it
(``slam.klt.fb_max_px``, not silently dropped); bounds live in the fields. Units in the names
(``_px``, ``_m``, ``_deg``); ``_rel`` values are fractions of the median scene depth.

The depth frames of the rgbd aid are read and trusted by the track's shared ``depth`` section
(:class:`mst.pipeline.depth_io.DepthConfig`), handed to :func:`mst.pipeline.slam.make_aid`;
:func:`slam_depth_config` gives the SLAM's defaults for it.
"""

from __future__ import annotations

from dataclasses import dataclass

from mst.core.config import Config, param, section
from mst.core.klt import KltConfig
from mst.pipeline.depth_io import DepthConfig


def slam_klt_config() -> KltConfig:
    """The SLAM's KLT, unchanged by the move onto the shared front end: an 11 px window, 3 pyramid
    levels, at most 10 iterations per level (0.01 px), forward-backward bound 1 px with the backward
    pass started at the original points; corners: 400 tracked at most, quality 0.005, 10 px apart,
    5 px blocks (``border_px`` and ``harris_k`` are not used: the whole image, Shi-Tomasi corners)."""
    return KltConfig(window_px=11, pyramid_levels=3, fb_max_px=1.0, backward_from_start=True, max_iterations=10,
                     eps_px=0.01, max_features=400, quality=0.005, min_distance_px=10.0, block_px=5)


def slam_depth_config() -> DepthConfig:
    """The depth section the rgbd aid had before the shared one: millimetre integers, 0.05-50 m,
    3x3 spread < 0.03 x depth (DepthConfig's own default near bound is fuse's 0.1 m)."""
    return DepthConfig(scale=1000.0, min_m=0.05, max_m=50.0, edge_rel=0.03)


@dataclass
class StandbyConfig(Config):
    """The default aid's standby (aid auto without depth frames: the mono aid switched on when needed)."""

    buffer_frames: int = param(20, min=2, max=10_000, help="recent frames kept asleep, replayed on waking")
    wake_info_ratio: float = param(0.7, min=0, help="asleep, an edge pose with trace(W) below this x its running mean wakes the aid")
    sleep_after_frames: int = param(30, min=1, max=1_000_000, help="strong model frames in a row that send the aid back to standby")


@dataclass
class SlamConfig(Config):
    """Settings of the model-aided SLAM (pixels, metres, degrees; ``_rel``: x median scene depth)."""

    # front end: KLT corners (klt.max_features tracked at most, replenished per grid cell)
    klt: KltConfig = param(default_factory=slam_klt_config, help="KLT corner detection and tracking")
    grid: tuple[int, int] = param((8, 6), min=1, max=1000, help="replenishing grid (columns, rows)")
    replenish_ratio: float = param(0.8, min=0, max=1, help="detect new corners when fewer than this x klt.max_features are tracked")
    pnp_reproj_px: float = param(3.0, min=0, min_open=True, help="PnP RANSAC inlier bound, px")
    pnp_min_inliers: int = param(12, min=6, max=100_000, help="fewer PnP inliers: no SLAM pose")
    # mono landmarks
    tri_min_angle_deg: float = param(1.0, min=0, max=180, help="mono: parallax needed to triangulate, deg")
    tri_max_reproj_px: float = param(2.0, min=0, min_open=True, help="mono: reprojection bound of a new landmark, px")
    tri_refine_deg: float = param(8.0, min=0, max=180, help="mono: re-triangulate a landmark while its parallax grows, up to this, deg")
    # no far bound for triangulated points: the parallax test bounds their depth error (a 50 m cap
    # rejected every landmark of a 200 m UAV flyover)
    tri_min_depth_m: float = param(0.05, min=0, help="mono: a new landmark lies at least this far in front of both views, m")
    # keyframes
    kf_min_frames: int = param(3, min=1, max=100_000, help="frames between keyframes, at least")
    kf_max_frames: int = param(15, min=1, max=100_000, help="a keyframe at least every this many frames")
    kf_angle_deg: float = param(4.0, min=0, help="keyframe when the view rotated this much since the last one, deg")
    kf_translation_rel: float = param(0.1, min=0, help="... or moved this fraction of the median scene depth")
    kf_track_ratio: float = param(0.6, min=0, max=1, help="... or fewer than this fraction of its landmarks are still tracked")
    # local bundle adjustment
    ba: bool | None = param(None, help="local bundle adjustment at keyframes (null: mono only)")
    ba_window: int = param(6, min=2, max=1000, help="keyframes in the local BA (and in the map's window)")
    ba_max_points: int = param(250, min=10, max=1_000_000, help="landmarks in one local BA (most observed first)")
    ba_iterations: int = param(10, min=1, max=10_000, help="Levenberg-Marquardt iterations per BA solve")
    ba_min_observations: int = param(20, min=0, max=1_000_000, help="a keyframe with fewer landmarks in the BA keeps its pose")
    ba_guard_ratio: float = param(1.1, min=0, help="Lhuillier bound: constrained RMSE <= ratio x e0 + ba_guard_px")
    ba_guard_px: float = param(0.1, min=0, help="additive part of the Lhuillier bound, px")
    ba_loss_px: float = param(2.0, min=0, min_open=True, help="Cauchy loss scale of the reprojection terms, px")
    ba_max_error_px: float = param(4.0, min=0, min_open=True, help="landmarks with a larger mean error after BA are dropped, px")
    # rgbd
    rgbd_reset_on_model: bool = param(True, help="rgbd: re-lift all landmarks from depth under each model pose")
    # fusion with the edge poses
    #: None = by mode: fused for rgbd (metric depth landmarks are precise), the edge pose for mono
    #: (triangulated landmarks are noisier than the model fix; measured on the synthetic orbit:
    #: fusing raised the mono error from 0.07 % to 0.1 % of the distance)
    fuse_output: bool | None = param(None, help="model frames output the fusion of edge and SLAM poses (true) or the edge pose (false); null: fused for rgbd")
    min_info_ratio: float = param(0.5, min=0, help="with a working SLAM, an edge pose needs trace(W) >= this x its running mean")
    edge_sigma_px: float = param(1.0, min=0, min_open=True, help="noise of the edge residuals: cov(edge pose) = sigma^2 W^-1, px")
    slam_sigma_px: float = param(1.0, min=0, min_open=True, help="noise of the KLT points: cov(PnP pose) = sigma^2 (J^T J)^-1, px")
    #: the filter's process noise; None: 0.001 for rgbd, 0.005 for mono (corridor runs: 1.2 % after
    #: 77 frames rgbd)
    drift_rel_per_frame: float | None = param(None, min=0, help="random-walk drift of the SLAM pose per frame, x scene depth (null: 0.001 rgbd, 0.005 mono)")
    drift_deg_per_frame: float | None = param(None, min=0, help="random-walk rotation drift per frame, deg (null: 0.05 rgbd, 0.2 mono)")
    gate_chi2: float = param(22.46, min=0, min_open=True, help="chi-square bound (6 dof, 99.9 %) of the edge/SLAM disagreement")
    gate_min_inliers: int = param(40, min=0, max=1_000_000, help="the SLAM pose gates the edges only with this many PnP inliers")
    gate_max_rejects: int = param(10, min=1, max=1_000_000, help="after this many rejected healthy edge poses in a row, trust the edges")
    consensus_window: int = param(8, min=1, max=10_000, help="recent healthy edge poses compared on the SLAM's offset")
    consensus_min: int = param(4, min=1, max=10_000, help="rejected edge poses are accepted when this many recent ones agree")
    consensus_rel: float = param(0.003, min=0, help="agreement: offsets within this x scene depth ...")
    consensus_deg: float = param(0.5, min=0, help="... and this many degrees")
    #: static-world check: this many healthy, strong edge poses in a row rejected by the gate without
    #: a consensus (each off by a different offset) = the object moves in the map's world; the same
    #: count of agreeing frames ends it
    static_world_frames: int = param(3, min=1, max=10_000, help="static-world check: disagreeing (and then agreeing) frames in a row")
    #: a healthy strong edge pose rejected by the gate that differs from the map pose by more than
    #: this x scene depth or these degrees (the accuracy promised for output poses) leaves the frame
    #: lost: no map pose is output against its image's evidence
    disagree_rel: float = param(0.01, min=0, help="output bound: edge and map poses further apart (x scene depth) leave the frame lost")
    disagree_deg: float = param(2.0, min=0, help="output bound in rotation, deg")
    #: the drift budget (:mod:`mst.pipeline.slam.drift`): a map pose is output only while its
    #: propagated uncertainty bound (drift_sigmas x sigma) is within these (the issue's 1 % / 2 deg)
    drift_budget_rel: float = param(0.01, min=0, help="drift budget: a map pose's uncertainty bound must be within this x its distance to the model")
    drift_budget_deg: float = param(2.0, min=0, help="drift budget in rotation, deg")
    drift_sigmas: float = param(2.0, min=0, min_open=True, help="the uncertainty bound of a map pose, x its propagated 1-sigma")
    #: the edge tracker's covariance is optimistic: RMS error / RMS claimed sigma of the model poses
    #: measured against ground truth up to 3.0 (camera centre, the demo's UAV pass; 0.4-0.5 on the
    #: corridor and the occluder) and 1.4-2.4 (rotation)
    anchor_sigma_scale: float = param(3.0, min=1, help="drift budget: an edge pose overrides a map pose beyond the budget only while its own covariance x this^2 is within it")
    # relocalisation and the exported map
    reloc_keyframes: int = param(40, min=1, max=100_000, help="keyframes kept for relocalisation")
    reloc_min_inliers: int = param(20, min=4, max=100_000, help="ORB matches / PnP inliers needed to relocalise")
    #: a relocalisation of the map may not move the camera further from its last pose of the map
    #: (model or map pose) than reloc_gate_rel x scene depth + reloc_gate_speed x its speed (the 75th
    #: percentile of its steps per frame) x the frames since: a repetitive texture (a tiled ground, rows of windows) gave
    #: PnP poses with 20+ inliers 60 m away on a 40 m UAV survey after its hover turn, from which the
    #: tracker never came back (README, tracking)
    reloc_gate_rel: float = param(0.1, min=0, help="map relocalisation gate: radius at no elapsed frames, x scene depth (inf: no gate)")
    reloc_gate_speed: float = param(3.0, min=0, help="map relocalisation gate: growth per frame since the last map pose, x the camera's speed (75th percentile of its steps per frame)")
    reloc_features: int = param(800, min=1, max=100_000, help="ORB features on a keyframe or a frame being relocalised")
    max_export_points: int = param(200_000, min=0, max=100_000_000, help="cap of the exported landmark map")
    standby: StandbyConfig = section(StandbyConfig)
