"""The SLAM aid's settings (mst.pipeline.slam.config): strict keys, bounds in the fields, every
setting reachable from a config file, the sections (klt, standby) and the depth section."""

from __future__ import annotations

import numpy as np
import pytest

from mst.core.camera import Camera
from mst.core.config import resolve
from mst.errors import ConfigError
from mst.pipeline import slam
from mst.pipeline.depth_io import DepthConfig

CAM = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)


def _texture(seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.uint8), (0, 0), 2)


@pytest.mark.parametrize("d, field", [({"klt": {"fb_max": 2}}, "klt.fb_max"), ({"max_points": 400}, "max_points"),
                                      ({"standby": {"buffer": 3}}, "standby.buffer"), ({"depth_min_m": 0.1}, "depth_min_m")])
def test_unknown_key_is_an_error_naming_it(d, field):
    """Before #10 SlamConfig.from_dict dropped unknown keys; the old flat names are unknown now."""
    with pytest.raises(ConfigError) as e:
        slam.SlamConfig.from_dict(d)
    assert e.value.field == field
    with pytest.raises(ConfigError):
        slam.make_aid("mono", CAM, d)


@pytest.mark.parametrize("d, field", [({"klt": {"window_px": 10}}, "klt.window_px"), ({"gate_chi2": 0}, "gate_chi2"),
                                      ({"grid": [8, 0]}, "grid"), ({"kf_track_ratio": 1.5}, "kf_track_ratio")])
def test_bounds_are_checked_once_in_the_fields(d, field):
    with pytest.raises(ConfigError) as e:
        slam.SlamConfig.from_dict(d)
    assert e.value.field == field


def test_defaults_are_the_aids_values_before_the_move():
    cfg = slam.SlamConfig()
    k = cfg.klt
    assert (k.window_px, k.pyramid_levels, k.fb_max_px, k.backward_from_start, k.max_iterations) == (11, 3, 1.0, True, 10)
    assert (k.max_features, k.quality, k.min_distance_px, k.block_px) == (400, 0.005, 10.0, 5)
    assert slam.slam_depth_config() == DepthConfig(scale=1000.0, min_m=0.05, max_m=50.0, edge_rel=0.03)
    assert cfg.tri_min_depth_m == 0.05 and cfg.standby.buffer_frames == 20
    assert slam.SlamConfig.from_dict(cfg.to_dict()) == cfg   # the echoed config repeats the run


def test_a_config_file_setting_reaches_the_aid(tmp_path):
    """``slam: {klt: {max_features: 60}}`` in a YAML file caps the corners the aid tracks."""
    f = tmp_path / "track.yaml"
    f.write_text("slam:\n  klt:\n    max_features: 60\n  standby:\n    buffer_frames: 5\n")
    cfg = resolve(slam.SlamConfig, file=f, section_name="slam")
    assert cfg.klt.max_features == 60 and cfg.klt.window_px == 11   # the rest keeps the SLAM's defaults
    counts = {}
    for name, c in (("default", None), ("file", cfg)):
        aid = slam.make_aid("mono", CAM, c)
        T = np.eye(4)
        T[2, 3] = 3.0
        aid.predict(0, _texture(), T)
        aid.update(0, _texture(), T, np.eye(6) * 1e6, True)
        counts[name] = len(aid.pts)
    assert counts["file"] <= 60 < counts["default"]
    assert slam.make_aid("standby", CAM, cfg).buf.maxlen == 5


def test_make_aid_takes_the_depth_section(tmp_path):
    (tmp_path / "d").mkdir()
    np.save(tmp_path / "d" / "000000.npy", np.full((240, 320), 2.0, np.float32))
    aid = slam.make_aid("rgbd", CAM, {}, tmp_path / "d", depth=DepthConfig(min_m=0.2, max_m=1.5))
    uv = np.array([[100.0, 100.0], [200.0, 120.0]])
    assert np.isnan(aid._depth_at(aid._depth_frame(0), uv)).all()   # 2 m is beyond max_m
    aid = slam.make_aid("rgbd", CAM, {}, tmp_path / "d")             # the SLAM's defaults: 0.05-50 m
    assert np.allclose(aid._depth_at(aid._depth_frame(0), uv)[:, 2], 2.0)
