"""``mst track``'s settings: one nested :class:`TrackConfig` on :mod:`mst.core.config`, and the ViSP XML map.

``TrackConfig(edges, klt, slam, depth, reloc)`` plus the mode switches (``aid``, ``use_klt``,
``relocalise``, ``health_score``, ``edge_source``). Units in the names (``_px``, ``_m``, ``_deg``);
bounds live once, in the fields (checked whoever builds the config: a file, a preset, an option,
a library caller). The upper bounds keep the per-frame work and memory bounded: the moving-edge
search reads samples x (2 range + 1) x mask^2 pixels, so a search range of 10^8 px asked for
547 GiB; 256 px (half a VGA frame each side) is far beyond any useful inter-frame motion and costs
< 0.5 GiB at the 600-sample cap with the largest mask.

ViSP's tracker XML (e.g. ``teabox.xml``) is read by :func:`visp_xml_settings` into a mapping of
dotted names (the ``base`` layer of :func:`mst.cli.common.build_config`)::

    <conf>
      <ecm><mask><size>5</size><nb_mask>180</nb_mask></mask><range><tracking>8</tracking></range>
           <contrast><edge_threshold_type>1</edge_threshold_type><edge_threshold>20</edge_threshold>
           <mu1>0.5</mu1><mu2>0.5</mu2></contrast><sample><step>4</step></sample></ecm>
      <klt><max_features>300</max_features><window_size>5</window_size><quality>0.015</quality>
           <min_distance>8</min_distance><harris>0.01</harris><size_block>3</size_block>
           <pyramid_lvl>3</pyramid_lvl><mask_border>5</mask_border></klt>
      <face><angle_appear>70</angle_appear><angle_disappear>80</angle_disappear>
            <near_clipping>0.1</near_clipping><far_clipping>100</far_clipping></face>
    </conf>
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst.core.config import Config, expand_dotted, param, register_preset, section
from mst.core.klt import KltConfig
from mst.errors import ConfigError, InputError
from mst.pipeline.depth_io import DepthConfig
from mst.pipeline.slam.config import SlamConfig, slam_depth_config
from mst.pipeline.tracking.relocalise import RelocConfig

#: default near plane: this fraction of the scene depth (median depth of the model vertices in
#: front of the camera at the first tracked pose); ViSP's fixed 0.1 m clips a 5 cm part entirely
NEAR_CLIP_REL = 1e-3


def scene_near_m(vertices_m: np.ndarray, T_cam_model: np.ndarray, near_clip_m: float | None = None) -> float:
    """Near clipping distance (m): ``near_clip_m`` when set, else ``NEAR_CLIP_REL`` x the median
    camera-frame depth of the model vertices ``(N, 3)`` in front of the camera at ``T_cam_model``."""
    if near_clip_m is not None:
        return float(near_clip_m)
    from mst.pipeline.tracking.exact import mv

    z = mv(np.asarray(vertices_m, float), T_cam_model[2, :3]) + T_cam_model[2, 3]
    z = z[z > 0]
    return max(float(NEAR_CLIP_REL * np.median(z)) if len(z) else 1e-3, 1e-6)


#: default level-of-detail line length, in sample steps (3 samples: the edge's own line is
#: over-determined and its residual spread measurable)
LOD_LINE_SAMPLES = 3

#: the default moving-edge search range: ViSP's 8 px (``ecm/range/tracking``) for images up to 640 px
#: wide, scaled with the width above (:func:`search_range_px`)
SEARCH_RANGE_REF_PX = 8
SEARCH_RANGE_REF_WIDTH_PX = 640


@dataclass
class EdgesConfig(Config):
    """The edge tracker: moving edges, faces and clipping, level of detail, VVS, health.

    Defaults are ViSP's tracker defaults / teabox.xml values, except the face angles: 80/85 deg
    instead of teabox.xml's 70/80, so that obliquely seen faces still constrain the pose; without
    them a nearly fronto-parallel wall leaves the pose weakly observable (rotation about the object
    vs. sideways translation).

    Moving edges (ViSP ``vpMe``): a candidate's contrast must lie in ``[1-mu1, 1+mu2]`` times the
    reference contrast; ``n_candidates`` positions are kept per sample (the pose solver picks the
    one closest to the moving line). Faces: angles between face normal and viewing ray, with
    hysteresis. Survey-scale clipping (not ViSP's tabletop 0.1 m / 100 m, which stopped a 211 m UAV
    flyover at frame 0): no far plane unless given (``None``), and a near plane of
    ``NEAR_CLIP_REL`` x the scene depth at the first tracked pose (``None``; resolved by the
    tracker). Explicit values (a ViSP XML) apply as given.

    Level of detail (ViSP ``setLod``): an edge whose projection (clipped at the near/far planes) is
    shorter than ``lod_min_line_px`` is skipped, and so is an edge whose faces all project smaller
    than ``lod_min_face_px2``. ``None`` derives them (:func:`lod_thresholds`): ``LOD_LINE_SAMPLES``
    x ``sample_step_px`` (an edge with fewer samples does not fix its own line, and the per-edge
    spread weighting of the pose solver needs several) and ``search_range_px^2`` (in a face smaller
    than that, opposite edges lie within each other's search windows, so their moving edges jump
    between them: far, tiny facades add noise). Measured on 10-frame Rotterdam flyovers (edges
    only): (2 x range)^2 dropped so many roofs at 120 m, 320x240 that frame 0 locked 23 m off, and
    at 250 m, 640x480 nothing trackable was left. ViSP's XML ``<lod><use_lod>0</use_lod>`` turns
    the rule off; ``<min_line_length_threshold>`` and ``<min_polygon_area_threshold>`` set it.

    Pose: ``fine_mad_px`` is the floor of a second VVS stage from the converged pose with the same
    matches: 0.15 px, above the 0.11 px worst sub-pixel error of a clean step edge, so a
    near-perfect fit keeps its own samples, while 0.3 let 1.4 px mismatches of far facades keep
    weight: Rotterdam 211 m flyover ATE 0.50 -> 0.26 m edges only, 40 m 0.17 -> 0.06 m; real video
    has a larger MAD and is unaffected; >= ``min_mad_px`` turns the stage off.
    Health: the projection error is computed at samples whose gradient is strong.
    Coarse-to-fine: the first frame and recoveries use 3 passes with shrinking ranges.
    """

    # moving edges
    mask_px: int = param(5, min=3, max=31, odd=True, help="moving-edge mask size, px (odd) [ecm/mask/size]")
    n_masks: int = param(180, min=4, max=360, help="mask orientations over 180 deg [ecm/mask/nb_mask]")
    search_range_px: int | None = param(None, min=1, max=256, help="search range each side of the projected edge, px (null: 8 px, x width / 640 above 640 px) [ecm/range/tracking]")
    edge_threshold: float = param(20.0, min=0, max=255, help="contrast of a step edge, gray levels [ecm/contrast/edge_threshold]")
    mu1: float = param(0.5, min=0, max=1, help="contrast ratio tolerance below the reference [ecm/contrast/mu1]")
    mu2: float = param(0.5, min=0, max=10, help="contrast ratio tolerance above the reference [ecm/contrast/mu2]")
    sample_step_px: float = param(4.0, min=0.5, max=1000, help="distance between samples along a projected edge, px [ecm/sample/step]")
    n_candidates: int = param(2, min=1, max=16, help="candidate positions kept per sample")
    # faces, clipping, hidden lines
    angle_appear_deg: float = param(80.0, min=0, max=90, help="a face appears below this angle to the viewing ray, deg [face/angle_appear]")
    angle_disappear_deg: float = param(85.0, min=0, max=90, help="a face disappears above this angle, deg [face/angle_disappear]")
    near_clip_m: float | None = param(None, min=1e-9, max=1e12, help="near clipping distance, m (null: 1e-3 x the scene depth) [face/near_clipping]")
    far_clip_m: float | None = param(None, min=1e-9, max=1e15, help="far clipping distance, m (null: none) [face/far_clipping]")
    hidden_lines: bool = param(True, help="hidden-line removal for non-convex models")
    zbuffer_scale: float = param(0.5, min=0.05, max=2.0, help="resolution of the hidden-line depth buffer, x image size")
    max_samples: int = param(600, min=0, max=1_000_000, help="samples per frame at most (0: no cap)")
    # level of detail
    lod_min_line_px: float | None = param(None, min=0, max=1e4, help="shorter projected edges are skipped, px (null: 3 x sample step) [lod/min_line_length_threshold]")
    lod_min_face_px2: float | None = param(None, min=0, max=1e8, help="edges of smaller projected faces are skipped, px^2 (null: range^2) [lod/min_polygon_area_threshold]")
    # pose (robust VVS)
    vvs_iters: int = param(30, min=1, max=1000, help="VVS iterations at most")
    lm_mu: float = param(0.01, min=0, max=1e6, help="Levenberg-Marquardt damping")
    min_mad_px: float = param(0.3, min=1e-6, max=100, help="floor of the robust scale, px")
    fine_mad_px: float = param(0.15, min=1e-6, max=100, help="floor of the fine VVS stage, px (>= min_mad_px: off)")
    tukey_c: float = param(4.6851, min=0.1, max=100, help="Tukey constant, MAD units")
    klt_weight: float = param(1.0, min=0, max=1e3, help="weight of the KLT points relative to the edge samples")
    #: the KLT points' model coordinates come from the pose at their detection, whose error all of
    #: them share: together they know the pose no better than the edges did (vvs.klt_info_scale)
    klt_info_cap: float | None = param(1.0, min=0, min_open=True, max=1e6,
                                       help="the KLT points' information at most this x the edge samples' (null: no cap)")
    # health
    max_proj_error_deg: float = param(25.0, min=0, max=90, help="mean gradient / model-normal angle above which a frame is lost, deg")
    min_inlier_ratio: float = param(0.25, min=0, max=1, help="robust inliers / samples at least")
    min_support: float = param(0.3, min=0, max=1, help="fraction of samples on a strong gradient at least")
    min_samples: int = param(12, min=6, max=100_000, help="visible samples at least")
    # prediction, coarse-to-fine
    pyramid_levels: int = param(1, min=1, max=6, help="coarse-to-fine levels (1: none, 2: a half-resolution pass first)")
    retry_pyramid_levels: int | None = param(None, min=1, max=6, help="a tracked frame these levels lose is searched again coarse-to-fine with this many (1: no retry; null: 1 below 640 px wide, 2 from 640 px, one more per doubling from 2560 px)")
    passes: int = param(1, min=1, max=10, help="search + VVS rounds per frame")
    recover_range_factor: float = param(2.0, min=1, max=10, help="search range after a loss, x search_range_px")
    constant_velocity: bool = param(False, help="predict each pose by repeating the last motion (when no SLAM aid predicts)")

    def check(self) -> None:
        if not self.angle_appear_deg <= self.angle_disappear_deg:
            raise ConfigError("angle_appear_deg", f"{self.angle_appear_deg:g} > angle_disappear_deg "
                                                  f"{self.angle_disappear_deg:g} (need appear <= disappear)")
        if self.near_clip_m is not None and self.far_clip_m is not None and not self.near_clip_m < self.far_clip_m:
            raise ConfigError("near_clip_m", f"{self.near_clip_m:g} m >= far_clip_m {self.far_clip_m:g} m (need near < far)")


@dataclass
class TrackKltConfig(KltConfig):
    """KLT points of the hybrid edges+KLT tracker: an 11 px window, 3 levels, at most 30 iterations
    per level (0.01 px), ViSP's ``<klt>`` corner defaults, and the tracker's own forward-backward test
    (0.5 px, backward pass from the tracked points). A ViSP tracker XML (:func:`visp_xml_settings`)
    sets ViSP's own LK: ``<window_size>`` as the window's side (``vpKltOpencv`` hands it to OpenCV as
    ``cv::Size(window_size, window_size)``: 5 px for teabox.xml) and its criteria (20 iterations,
    0.03 px). Issue #14: on the real tea-box video those agree better with ViSP's hybrid tracker
    (0.768 -> 0.754 px) at less cost; on the 320x240 synthetic UAV demo a 5 px window lost 50 more
    frames than the 11 px one, hence the default."""

    fb_max_px: float = param(0.5, min=0, min_open=True, help="forward-backward error bound, px")
    backward_from_start: bool = param(False, help="start the backward pass at the original points (else at the tracked ones)")
    reanchor: str = param("mean", choices=("mean", "off"),
                          help="the kept KLT points' model coordinates: mean = the mean of their pixels cast onto their "
                               "face planes under every pose since their detection; off = lifted at their detection (ViSP)")


@dataclass
class TrackConfig(Config):
    """All of ``mst track``'s settings (``--config``, ``--set``, ``--preset``; echoed in ``--json``)."""

    aid: str = param("auto", choices=("auto", "mono", "rgbd", "off"),
                     help="SLAM aid: auto = rgbd with depth, else the mono aid on standby; off = edges only")
    use_klt: bool | None = param(None, help="KLT points in the edge optimisation (null: on for aid auto without depth)")
    relocalise: bool = param(True, help="learn the object's keypoints and re-acquire a lost pose")
    health_score: bool = param(True, help="reject edge poses whose calibrated health score is <= 0")
    edge_source: str = param("auto", choices=("auto", "polygon", "render"), help="edges to track")
    edges: EdgesConfig = section(EdgesConfig)
    klt: TrackKltConfig = section(TrackKltConfig)
    slam: SlamConfig = section(SlamConfig)
    #: the rgbd aid's depth frames: the SLAM's defaults (a 0.05 m near bound; fuse's shared default is 0.1 m)
    depth: DepthConfig = param(default_factory=slam_depth_config, help=(DepthConfig.__doc__ or "").split("\n")[0])
    reloc: RelocConfig = section(RelocConfig)


def search_range_px(cfg: EdgesConfig, width_px: int | None = None) -> int:
    """The moving-edge search range (px each side): explicit, or (``None``) ViSP's
    ``SEARCH_RANGE_REF_PX`` at ``SEARCH_RANGE_REF_WIDTH_PX`` and below, scaled with the image width
    above it (the same angular range: an image motion in px grows with the resolution). Measured on
    Rotterdam survey flyovers at 1920x1080 (default mode, whole-run ATE, % of the distance, 2 seeds):
    8 px at 40 / 120 / 250 m 0.023 / 0.025-0.038 / 0.23-0.26 (the 250 m band beyond the issue's
    0.1 %), 24 px 0.011 / 0.036-0.053 / 0.078-0.092. At 640 px and below the range is unchanged
    (the real teabox video, the 320x240 tests)."""
    if cfg.search_range_px is not None:
        return int(cfg.search_range_px)
    if width_px is None or width_px <= SEARCH_RANGE_REF_WIDTH_PX:
        return SEARCH_RANGE_REF_PX
    return int(round(SEARCH_RANGE_REF_PX * width_px / SEARCH_RANGE_REF_WIDTH_PX))


def retry_pyramid_levels(cfg: EdgesConfig, width_px: int | None = None) -> int:
    """Coarse-to-fine levels of the second search of a tracked frame that the first loses: explicit,
    or (``None``) 1 (no retry) below ``SEARCH_RANGE_REF_WIDTH_PX`` (640 px), 2 (a half-resolution
    pass first) from 640 to 2559 px wide (VGA, 720p, 1080p), one more per doubling above (3 for 4K).
    The search range in px scales
    with the width (:func:`search_range_px`), but a fast camera moves further in angle per frame than
    that range: the FPV facade pass at 10 frames/s (1 m and ~2 deg a frame) at 1920x1080 tracked 2 of
    30 frames with 24 px and one level, 30 of 30 with a half-resolution pass first (ATE 2.6 mm; a
    48 px range 2.3 mm); the coarse pass searches the same range in its own, twice larger, pixels.
    Only as a retry: on every frame it cost the Rotterdam 250 m survey band at 1280x720 its accuracy
    (ATE 0.29 -> 0.66 m: the coarse pass's wide window meets the neighbouring facades of a far,
    dense view). At 640x480 the same pass (8 px, ~5 m/s) tracked 19 of 30 frames without the retry,
    30 of 30 with it (ATE 12 mm at ~30 m); the real teabox video loses no frame, so it never runs
    there (outputs byte-identical). Below 640 px no retry (the 320x240 tests: unchanged)."""
    if cfg.retry_pyramid_levels is not None:
        return int(cfg.retry_pyramid_levels)
    if width_px is None or width_px < SEARCH_RANGE_REF_WIDTH_PX:
        return 1
    return max(2, 1 + int(np.floor(np.log2(width_px / SEARCH_RANGE_REF_WIDTH_PX))))


def lod_thresholds(cfg: EdgesConfig, width_px: int | None = None) -> tuple[float, float]:
    """``(min_line_px, min_face_px2)`` of the level-of-detail rule (explicit or derived, see
    :class:`EdgesConfig`) for images ``width_px`` wide."""
    line = cfg.lod_min_line_px if cfg.lod_min_line_px is not None else LOD_LINE_SAMPLES * cfg.sample_step_px
    face = cfg.lod_min_face_px2 if cfg.lod_min_face_px2 is not None else float(search_range_px(cfg, width_px)) ** 2
    return float(line), float(face)


# ---------------------------------------------------------------------------- ViSP tracker XML
#: ViSP tag under ``<conf>`` -> dotted TrackConfig field
XML_MAP = {
    "ecm/mask/size": "edges.mask_px",
    "ecm/mask/nb_mask": "edges.n_masks",
    "ecm/range/tracking": "edges.search_range_px",
    "ecm/contrast/edge_threshold": "edges.edge_threshold",
    "ecm/contrast/mu1": "edges.mu1",
    "ecm/contrast/mu2": "edges.mu2",
    "ecm/sample/step": "edges.sample_step_px",
    "face/angle_appear": "edges.angle_appear_deg",
    "face/angle_disappear": "edges.angle_disappear_deg",
    "face/near_clipping": "edges.near_clip_m",
    "face/far_clipping": "edges.far_clip_m",
    "klt/max_features": "klt.max_features",
    "klt/window_size": "klt.window_px",        # the window's side (vpKltOpencv: cv::Size(window_size, window_size))
    "klt/quality": "klt.quality",
    "klt/min_distance": "klt.min_distance_px",
    "klt/harris": "klt.harris_k",
    "klt/size_block": "klt.block_px",
    "klt/pyramid_lvl": "klt.pyramid_levels",
    "klt/mask_border": "klt.border_px",
    "lod/min_line_length_threshold": "edges.lod_min_line_px",
    "lod/min_polygon_area_threshold": "edges.lod_min_face_px2",
}

#: ViSP's KLT termination criteria (``vpKltOpencv``'s constructor; no XML tag): set with a ``<klt>`` section
VISP_KLT_ITERATIONS, VISP_KLT_EPS_PX = 20, 0.03

#: dotted field -> its ViSP tag (how a setting read from an XML file is named in messages)
TAG_OF = {name: f"<{tag}>" for tag, name in XML_MAP.items()}


def _tag_label(field: str) -> str:
    """``edges.far_clip_m`` -> ``<face/far_clipping>`` (the field itself when no tag maps to it)."""
    return TAG_OF.get(field, field)


def visp_xml_settings(path: str | os.PathLike) -> dict:
    """The settings of a ViSP tracker XML (``<conf>``) as dotted :class:`TrackConfig` fields.

    Absent tags are absent from the mapping. Raises :class:`mst.InputError` (naming the file and
    the tag) for unparsable XML, non-numeric values and values the config refuses (its bounds). A
    camera in the same file is ignored here (read it with :func:`mst.core.camera.read_camera`).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "settings file does not exist")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as e:
        raise InputError(p, f"not valid XML ({e})") from None
    out: dict = {}
    for tag, name in XML_MAP.items():
        el = root.find(tag)
        if el is None or el.text is None or not el.text.strip():
            continue
        text = el.text.strip()
        try:
            v = float(text)
        except ValueError:
            raise InputError(p, f"<{tag}> is not a number: {text!r}") from None
        out[name] = v
    if root.find("klt") is not None:  # ViSP's tracker LK criteria (vpKltOpencv: 20 iterations, 0.03 px)
        out.setdefault("klt.max_iterations", VISP_KLT_ITERATIONS)
        out.setdefault("klt.eps_px", VISP_KLT_EPS_PX)
    el = root.find("lod/use_lod")
    if el is not None and (el.text or "").strip() in ("0", "false", "False"):
        out["edges.lod_min_line_px"] = out["edges.lod_min_face_px2"] = 0.0  # ViSP: level of detail off
    try:
        TrackConfig.from_dict(expand_dotted(out))
    except ConfigError as e:
        problem = e.problem
        for f, tag in TAG_OF.items():  # a cross-field rule names the other field too
            problem = problem.replace(f.split(".")[-1], tag)
        raise InputError(p, f"bad tracker setting: {_tag_label(e.field)}: {problem}") from None
    return out


def read_tracker_xml(path: str | os.PathLike) -> TrackConfig:
    """A :class:`TrackConfig` with the settings of a ViSP tracker XML over the defaults."""
    return TrackConfig.from_dict(expand_dotted(visp_xml_settings(path)))


# ---------------------------------------------------------------------------- presets
register_preset(TrackConfig, "tabletop",
                {"edges.near_clip_m": 0.1, "edges.far_clip_m": 100.0, "edges.angle_appear_deg": 70.0,
                 "edges.angle_disappear_deg": 80.0},
                "ViSP's tabletop defaults (teabox.xml): fixed 0.1-100 m clipping, faces at 70/80 deg")
register_preset(TrackConfig, "uav-480p",
                {"edges.near_clip_m": None, "edges.far_clip_m": None, "edges.angle_appear_deg": 80.0,
                 "edges.angle_disappear_deg": 85.0},
                "survey scale (the UAV flyovers of tests/test_track_survey.py, 640x480): no far plane, a near plane "
                "relative to the scene depth, faces at 80/85 deg; overrides a tabletop ViSP XML")

__all__ = ["EdgesConfig", "TrackConfig", "TrackKltConfig", "LOD_LINE_SAMPLES", "NEAR_CLIP_REL",
           "XML_MAP", "lod_thresholds", "read_tracker_xml", "scene_near_m", "visp_xml_settings"]
