"""The settings of ``mst refine`` (:class:`RefineConfig`): units in the names; ``_rel`` = x the
median depth of the keyframes' depth samples (so one file suits a tea box and a building)."""

from __future__ import annotations

from dataclasses import dataclass

from mst.core.config import Config, param, section
from mst.core.klt import KltConfig
from mst.pipeline.depth_io import DepthConfig
from mst.pipeline.nav.fusion import FusionConfig


@dataclass
class RefineConfig(Config):
    """Settings of the offline global refinement (metres, degrees, pixels)."""

    depth: DepthConfig = section(DepthConfig)
    fps: float | None = param(None, min=0, min_open=True,
                              help="trajectory time -> frame index k = round(t * fps); null: times are frame indices")
    keyframe_every: int = param(5, min=1, help="every N-th pose of the trajectory is a keyframe")
    pixel_step: int = param(4, min=1, max=64, help="depth pixels sampled on a grid of this step, px")
    model_samples: int = param(50_000, min=1000, help="points sampled on the model surface (the ICP target)")
    icp_max_rel: tuple[float, float, float] = param(
        (0.08, 0.04, 0.02), help="ICP correspondence distances coarse to fine, x median depth")
    icp_iterations: int = param(30, min=1, help="ICP iterations per distance")
    tukey_rel: float = param(0.01, min=0, min_open=True, help="Tukey kernel width of the ICP residuals, x median depth")
    max_normal_deg: float = param(30.0, min=0, min_open=True, max=90,
                                  help="an ICP match needs the depth's and the model's normals within this, deg")
    min_points: int = param(100, min=6, help="a keyframe ICP is a prior only when this many samples found the model")
    prior_points_eff: float = param(200.0, min=1,
                                    help="a prior's information is capped at this many independent samples "
                                         "(neighbouring depth errors are correlated)")
    between_sigma_rel: float = param(0.002, min=0, min_open=True,
                                     help="sigma of a tracked relative motion between keyframes, x median depth")
    between_sigma_deg: float = param(0.2, min=0, min_open=True, help="sigma of its rotation, deg")
    rounds: int = param(4, min=1, max=50, help="at most this many rounds (global ICP + keyframe pose graph)")
    min_gain: float = param(0.01, min=0, max=1, help="stop when a round lowers the mean C2M by less than this share")
    c2m_max_rel: float = param(0.02, min=0, min_open=True,
                               help="C2M statistics over the samples nearer the model than this x median depth at the "
                                    "given poses (the rest is the scene around it), distances capped at it")
    seed: int = param(0, help="seed of the model surface sampling")
    ba: bool = param(True, help="bundle adjustment of the keyframes (KLT tie points, tracked-pose priors, nav "
                                "factors) before the ICP rounds; needs the frames")
    ba_sigma_px: float = param(1.0, min=0, min_open=True, help="tie point reprojection sigma, px")
    ba_huber: float = param(3.0, min=0, min_open=True, help="Huber kernel of every whitened BA residual, sigmas")
    ba_min_track: int = param(3, min=2, help="a tie point needs this many keyframes")
    ba_max_px: float = param(20.0, min=0, min_open=True,
                             help="a tie observation off by more than this at the tracked poses is a wrong match, px")
    ba_prior_scale: float = param(1.0, min=0, min_open=True,
                                  help="x the tracker's pose covariances (traj.cov.csv) in the BA priors")
    ba_fallback_sigma_rel: float = param(0.01, min=0, min_open=True,
                                         help="prior position sigma of a keyframe without a covariance (SLAM, "
                                              "relocalised), x median depth")
    ba_fallback_sigma_deg: float = param(1.0, min=0, min_open=True, help="its rotation sigma, deg")
    ba_iterations: int = param(30, min=1, help="BA function evaluations, at most")
    klt: KltConfig = section(KltConfig)
    nav: FusionConfig = section(FusionConfig)

    def check(self) -> None:
        from mst.errors import ConfigError

        if any(not (v > 0) for v in self.icp_max_rel):
            raise ConfigError("icp_max_rel", f"must be positive distances, got {list(self.icp_max_rel)}")
