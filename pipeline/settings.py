"""Tracker settings: one dataclass, read from ViSP tracker XML (``<conf><ecm>...``) or defaults.

Units: pixels for mask size, search range, sample step and KLT windows; gray levels for the
edge threshold; degrees for face angles; metres for clipping distances.

ViSP's tracker XML (e.g. ``teabox.xml``) is read directly::

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

import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from mst import InputError

#: default near plane: this fraction of the scene depth (median depth of the model vertices in
#: front of the camera at the first tracked pose); ViSP's fixed 0.1 m clips a 5 cm part entirely
NEAR_CLIP_REL = 1e-3
def scene_near_m(vertices_m: np.ndarray, T_cam_model: np.ndarray, near_clip_m: float | None = None) -> float:
    """Near clipping distance (m): ``near_clip_m`` when set, else ``NEAR_CLIP_REL`` x the median
    camera-frame depth of the model vertices ``(N, 3)`` in front of the camera at ``T_cam_model``."""
    if near_clip_m is not None:
        return float(near_clip_m)
    z = np.asarray(vertices_m, float) @ T_cam_model[2, :3] + T_cam_model[2, 3]
    z = z[z > 0]
    return max(float(NEAR_CLIP_REL * np.median(z)) if len(z) else 1e-3, 1e-6)


#: default level-of-detail line length, in sample steps (3 samples: the edge's own line is
#: over-determined and its residual spread measurable)
LOD_LINE_SAMPLES = 3


@dataclass
class TrackerConfig:
    """All tracker parameters (defaults are ViSP's tracker defaults / teabox.xml values, except the
    face angles: 80/85 deg instead of teabox.xml's 70/80, so that obliquely seen faces still
    constrain the pose; without them a nearly fronto-parallel wall leaves the pose weakly
    observable, e.g. rotation about the object vs. sideways translation).

    Moving edges (ViSP ``vpMe``): ``mask_size`` (px, odd), ``n_masks`` (orientations over 180 deg),
    ``search_range`` (px each side of the projected edge, along its normal), ``edge_threshold``
    (gray levels of a step edge, ViSP's normalised threshold), ``mu1``/``mu2`` (contrast ratio
    tolerance: a candidate's contrast must lie in ``[1-mu1, 1+mu2]`` times the reference contrast),
    ``sample_step`` (px between samples along a projected edge), ``n_candidates`` (candidate
    positions kept per sample; the pose solver picks the one closest to the moving line).
    Faces: ``angle_appear``/``angle_disappear`` (deg between face normal and viewing ray,
    hysteresis), ``near_clip``/``far_clip`` (metres along the optical axis). Survey-scale defaults
    (not ViSP's tabletop 0.1 m / 100 m, which stopped a 211 m UAV flyover at frame 0): no far plane
    unless given (``None``), and a near plane of ``NEAR_CLIP_REL`` x the scene depth at the first
    tracked pose (``None``; resolved by the tracker). Explicit values (a ViSP XML) apply as given.
    Level of detail (ViSP ``setLod``): an edge whose projection (clipped at the near/far planes) is
    shorter than ``lod_min_line_px`` is skipped, and so is an edge whose faces all project smaller
    than ``lod_min_face_px2``. ``None`` derives them from the moving-edge settings (see
    :func:`lod_thresholds`): ``LOD_LINE_SAMPLES`` x ``sample_step`` (an edge with fewer samples
    does not fix its own line, and the per-edge spread weighting of the pose solver needs several)
    and ``search_range^2`` (in a face smaller than that, opposite edges lie within each other's
    search windows, so their moving edges jump between them: far, tiny facades add noise). Measured
    on 10-frame Rotterdam flyovers (edges only): (2 x range)^2 dropped so many roofs at 120 m,
    320x240 that frame 0 locked 23 m off, and at 250 m, 640x480 nothing trackable was left.
    ViSP's XML ``<lod><use_lod>0</use_lod>`` turns the rule off; ``<min_line_length_threshold>``
    and ``<min_polygon_area_threshold>`` set it.
    ``source``: the settings file these values came from (named in error messages).
    Pose: ``vvs_iters``, ``lm_mu`` (Levenberg-Marquardt damping), ``min_mad_px`` (floor of the
    robust scale, px), ``fine_mad_px`` (floor of a second VVS stage from the converged pose with
    the same matches: 0.15 px, above the 0.11 px worst sub-pixel error of a clean step edge, so a
    near-perfect fit keeps its own samples, while 0.3 let 1.4 px mismatches of far facades keep
    weight: Rotterdam 211 m flyover ATE 0.50 -> 0.26 m edges only, 40 m 0.17 -> 0.06 m; real video
    has a larger MAD and is unaffected; >= ``min_mad_px`` turns the stage off), ``tukey_c``.
    Health: ``max_proj_error_deg`` (mean angle between gradient and model normal above which a
    frame is lost; computed at samples whose gradient is strong), ``min_support`` (fraction of samples
    on a strong gradient), ``min_inlier_ratio``, ``min_samples``.
    Prediction: ``constant_velocity`` (the next pose repeats the last inter-frame motion; used
    when no SLAM aid predicts). Coarse-to-fine: ``pyramid_levels`` (1 = none; 2 = a half-resolution pass first); ``passes``
    (search + VVS rounds per frame; the first frame and recoveries use 3 with shrinking ranges).
    KLT (``use_klt``): ViSP ``<klt>`` values.
    """

    mask_size: int = 5
    n_masks: int = 180
    search_range: int = 8
    edge_threshold: float = 20.0
    mu1: float = 0.5
    mu2: float = 0.5
    sample_step: float = 4.0
    n_candidates: int = 2
    angle_appear: float = 80.0
    angle_disappear: float = 85.0
    near_clip: float | None = None
    far_clip: float | None = None
    lod_min_line_px: float | None = None
    lod_min_face_px2: float | None = None
    hidden_lines: bool = True
    zbuffer_scale: float = 0.5
    vvs_iters: int = 30
    lm_mu: float = 0.01
    min_mad_px: float = 0.3
    fine_mad_px: float = 0.15
    tukey_c: float = 4.6851
    max_proj_error_deg: float = 25.0
    min_inlier_ratio: float = 0.25
    min_support: float = 0.3
    min_samples: int = 12
    pyramid_levels: int = 1
    passes: int = 1
    recover_range_factor: float = 2.0
    constant_velocity: bool = False
    max_samples: int = 600
    use_klt: bool = False
    klt_max_features: int = 300
    klt_window: int = 5
    klt_quality: float = 0.015
    klt_min_distance: float = 8.0
    klt_harris: float = 0.01
    klt_block: int = 3
    klt_pyramid: int = 3
    klt_border: int = 5
    klt_weight: float = 1.0
    source: str | None = None

    def updated(self, **kw) -> TrackerConfig:
        """A copy with the given (non-None) fields replaced."""
        return replace(self, **{k: v for k, v in kw.items() if v is not None})


_XML_MAP = {
    "ecm/mask/size": ("mask_size", int),
    "ecm/mask/nb_mask": ("n_masks", int),
    "ecm/range/tracking": ("search_range", int),
    "ecm/contrast/edge_threshold": ("edge_threshold", float),
    "ecm/contrast/mu1": ("mu1", float),
    "ecm/contrast/mu2": ("mu2", float),
    "ecm/sample/step": ("sample_step", float),
    "face/angle_appear": ("angle_appear", float),
    "face/angle_disappear": ("angle_disappear", float),
    "face/near_clipping": ("near_clip", float),
    "face/far_clipping": ("far_clip", float),
    "klt/max_features": ("klt_max_features", int),
    "klt/window_size": ("klt_window", int),
    "klt/quality": ("klt_quality", float),
    "klt/min_distance": ("klt_min_distance", float),
    "klt/harris": ("klt_harris", float),
    "klt/size_block": ("klt_block", int),
    "klt/pyramid_lvl": ("klt_pyramid", int),
    "klt/mask_border": ("klt_border", int),
    "lod/min_line_length_threshold": ("lod_min_line_px", float),
    "lod/min_polygon_area_threshold": ("lod_min_face_px2", float),
}


#: bounds of every numeric setting: field -> (low, high, integer, what). Closed intervals; a value
#: outside is refused at parse time with the setting's name (ViSP tag or option) and the file.
#: The upper bounds keep the per-frame work and memory bounded: the moving-edge search reads
#: samples x (2 range + 1) x mask^2 pixels, so a search range of 10^8 px asked for 547 GiB; 256 px
#: (half a VGA frame each side) is far beyond any useful inter-frame motion and costs < 0.5 GiB
#: at the 600-sample cap with the largest mask.
BOUNDS: dict[str, tuple[float, float, bool, str]] = {
    "mask_size": (3, 31, True, "px, odd"),
    "n_masks": (4, 360, True, "mask orientations"),
    "search_range": (1, 256, True, "px"),
    "edge_threshold": (0.0, 255.0, False, "gray levels"),
    "mu1": (0.0, 1.0, False, "contrast ratio tolerance"),
    "mu2": (0.0, 10.0, False, "contrast ratio tolerance"),
    "sample_step": (0.5, 1000.0, False, "px"),
    "n_candidates": (1, 16, True, "candidates per sample"),
    "angle_appear": (0.0, 90.0, False, "deg"),
    "angle_disappear": (0.0, 90.0, False, "deg"),
    "near_clip": (1e-9, 1e12, False, "m, > 0"),
    "far_clip": (1e-9, 1e15, False, "m, > 0"),
    "lod_min_line_px": (0.0, 1e4, False, "px"),
    "lod_min_face_px2": (0.0, 1e8, False, "px^2"),
    "zbuffer_scale": (0.05, 2.0, False, "x image size"),
    "vvs_iters": (1, 1000, True, "iterations"),
    "lm_mu": (0.0, 1e6, False, "damping"),
    "min_mad_px": (1e-6, 100.0, False, "px"),
    "fine_mad_px": (1e-6, 100.0, False, "px"),
    "tukey_c": (0.1, 100.0, False, "MAD units"),
    "max_proj_error_deg": (0.0, 90.0, False, "deg"),
    "min_inlier_ratio": (0.0, 1.0, False, "fraction"),
    "min_support": (0.0, 1.0, False, "fraction"),
    "min_samples": (6, 100_000, True, "samples"),
    "pyramid_levels": (1, 6, True, "levels"),
    "passes": (1, 10, True, "passes"),
    "recover_range_factor": (1.0, 10.0, False, "x search range"),
    "max_samples": (0, 1_000_000, True, "samples, 0 = no cap"),
    "klt_max_features": (1, 100_000, True, "features"),
    "klt_window": (1, 64, True, "px"),
    "klt_quality": (1e-6, 1.0, False, "fraction"),
    "klt_min_distance": (0.0, 1000.0, False, "px"),
    "klt_harris": (0.0, 1.0, False, "Harris k"),
    "klt_block": (1, 31, True, "px"),
    "klt_pyramid": (0, 8, True, "levels"),
    "klt_border": (0, 1000, True, "px"),
    "klt_weight": (0.0, 1e3, False, "relative weight"),
}

_TAG_OF = {name: f"<{tag}>" for tag, (name, _) in _XML_MAP.items()}


def setting_label(name: str) -> str:
    """How a setting is named in messages: its ViSP XML tag when it has one, else the field name."""
    return _TAG_OF.get(name, name)


def check_setting(name: str, value, label: str | None = None) -> str | None:
    """The problem with one setting's value (None when it is fine): non-finite, non-integral where
    an integer is needed, or outside :data:`BOUNDS`. ``label`` names it (default: its XML tag)."""
    label = label or setting_label(name)
    if value is None or isinstance(value, bool) or name not in BOUNDS:
        return None
    lo, hi, integer, what = BOUNDS[name]
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"{label} is not a number: {value!r}"
    if not math.isfinite(v):
        return f"{label} = {value} is not finite (need {lo:g}..{hi:g} {what})"
    if integer and v != round(v):
        return f"{label} = {value:g} is not an integer ({what})"
    if not lo <= v <= hi:
        return f"{label} = {v:g} is out of range (need {lo:g}..{hi:g} {what})"
    if name == "mask_size" and int(v) % 2 == 0:
        return f"{label} = {int(v)} must be odd (a mask has a centre pixel)"
    return None


def read_tracker_xml(path: str | os.PathLike, base: TrackerConfig | None = None) -> TrackerConfig:
    """Read ViSP tracker settings (``<conf>`` XML); absent tags keep ``base`` (default) values.

    Raises :class:`mst.InputError` (naming the file and the tag) for unparsable XML, non-numeric
    or non-finite values and values outside :data:`BOUNDS`. A camera in the same file is ignored
    here (read it with :func:`mst.core.camera.read_camera`).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "settings file does not exist")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as e:
        raise InputError(p, f"not valid XML ({e})") from None
    cfg = base or TrackerConfig()
    kw = {}
    for tag, (name, typ) in _XML_MAP.items():
        el = root.find(tag)
        if el is None or el.text is None or not el.text.strip():
            continue
        text = el.text.strip()
        try:
            v = float(text)
        except ValueError:
            raise InputError(p, f"<{tag}> is not a number: {text!r}") from None
        problem = check_setting(name, v)
        if problem:
            raise InputError(p, f"bad tracker setting: {problem}")
        kw[name] = typ(v)
    el = root.find("lod/use_lod")
    if el is not None and (el.text or "").strip() in ("0", "false", "False"):
        kw["lod_min_line_px"] = kw["lod_min_face_px2"] = 0.0  # ViSP: level of detail off
    cfg = replace(cfg, **kw, source=str(p))
    validate_config(cfg, p)
    return cfg


def validate_config(cfg: TrackerConfig, path: str | os.PathLike | None = None,
                    labels: dict[str, str] | None = None) -> None:
    """Raise :class:`mst.InputError` for values the tracker cannot work with (each setting against
    :data:`BOUNDS`, then the relations between them). ``labels``: how to name fields in the message
    (e.g. ``{"search_range": "--range"}`` for command-line options); default the XML tag."""
    labels = labels or {}
    bad = [pr for f in fields(cfg) if (pr := check_setting(f.name, getattr(cfg, f.name), labels.get(f.name)))]
    if not bad:
        if not cfg.angle_appear <= cfg.angle_disappear:
            bad.append(f"face angles {setting_label('angle_appear')} {cfg.angle_appear:g} > "
                       f"{setting_label('angle_disappear')} {cfg.angle_disappear:g} (need appear <= disappear)")
        if cfg.near_clip is not None and cfg.far_clip is not None and not cfg.near_clip < cfg.far_clip:
            bad.append(f"clipping {setting_label('near_clip')} {cfg.near_clip:g} m >= {setting_label('far_clip')} "
                       f"{cfg.far_clip:g} m (need near < far)")
    if bad:
        src = path if path is not None else (cfg.source if not labels else None)
        raise InputError(src, "bad tracker settings: " + "; ".join(bad))


def lod_thresholds(cfg: TrackerConfig) -> tuple[float, float]:
    """``(min_line_px, min_face_px2)`` of the level-of-detail rule (explicit or derived, see
    :class:`TrackerConfig`)."""
    line = cfg.lod_min_line_px if cfg.lod_min_line_px is not None else LOD_LINE_SAMPLES * cfg.sample_step
    face = cfg.lod_min_face_px2 if cfg.lod_min_face_px2 is not None else float(cfg.search_range) ** 2
    return float(line), float(face)


def config_to_dict(cfg: TrackerConfig) -> dict:
    """Plain dict of all settings (for JSON summaries)."""
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)}
