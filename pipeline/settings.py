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

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields, replace
from pathlib import Path

from mst import InputError


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
    hysteresis), ``near_clip``/``far_clip`` (metres along the optical axis).
    Pose: ``vvs_iters``, ``lm_mu`` (Levenberg-Marquardt damping), ``min_mad_px`` (floor of the
    robust scale, px), ``tukey_c``.
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
    near_clip: float = 0.1
    far_clip: float = 100.0
    hidden_lines: bool = True
    zbuffer_scale: float = 0.5
    vvs_iters: int = 30
    lm_mu: float = 0.01
    min_mad_px: float = 0.3
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
}


def read_tracker_xml(path: str | os.PathLike, base: TrackerConfig | None = None) -> TrackerConfig:
    """Read ViSP tracker settings (``<conf>`` XML); absent tags keep ``base`` (default) values.

    Raises :class:`mst.InputError` for unparsable XML or non-numeric values. A camera in the same
    file is ignored here (read it with :func:`mst.pipeline.camera.read_camera`).
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
        try:
            kw[name] = typ(float(el.text.strip()))
        except ValueError:
            raise InputError(p, f"<{tag}> is not a number: {el.text.strip()!r}") from None
    cfg = replace(cfg, **kw)
    validate_config(cfg, p)
    return cfg


def validate_config(cfg: TrackerConfig, path: str | os.PathLike | None = None) -> None:
    """Raise :class:`mst.InputError` for values the tracker cannot work with."""
    bad = []
    if cfg.mask_size < 3:
        bad.append(f"mask size {cfg.mask_size} < 3")
    if cfg.n_masks < 4:
        bad.append(f"{cfg.n_masks} masks < 4")
    if cfg.search_range < 1:
        bad.append(f"search range {cfg.search_range} < 1")
    if cfg.sample_step <= 0:
        bad.append(f"sample step {cfg.sample_step} <= 0")
    if not 0 <= cfg.angle_appear <= cfg.angle_disappear <= 90:
        bad.append(f"face angles appear {cfg.angle_appear} / disappear {cfg.angle_disappear} (need 0 <= appear <= disappear <= 90)")
    if not 0 < cfg.near_clip < cfg.far_clip:
        bad.append(f"clipping near {cfg.near_clip} / far {cfg.far_clip} (need 0 < near < far)")
    if bad:
        raise InputError(path, "bad tracker settings: " + "; ".join(bad))


def config_to_dict(cfg: TrackerConfig) -> dict:
    """Plain dict of all settings (for JSON summaries)."""
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)}
