"""`mst track`'s one configuration (TrackConfig): config files, --set, presets, the echoed config, strict keys.

The tea-box video (first frames, in-process): a config file sets one edges and one slam parameter
and the run shows both effects; the `config` block of a `--json` summary given back as `--config`
repeats the run exactly; an unknown key fails naming its dotted path.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from mst.errors import ConfigError
from mst.pipeline.tracking.config import TrackConfig, read_tracker_xml


@pytest.fixture(scope="module")
def teabox(shared_data, tmp_path_factory):
    from conftest import run_mst

    t = shared_data / "visp-teabox"
    d = tmp_path_factory.mktemp("teabox_cfg")
    run_mst("init", "--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--clicks", t / "teabox.clicks",
            "--points", t / "teabox.init", "-o", d / "p0.txt", "-q")
    return t, d


def _track(t, d, name, *extra, check=True, frames="0:8"):
    from conftest import run_mst

    out = d / f"{name}.txt"
    r = run_mst("track", t / "teabox.mp4", "--model", t / "teabox.cao", "--camera", t / "teabox.xml", "--init",
                d / "p0.txt", "-o", out, "--frames", frames, "--json", "-q", *extra, check=check)
    return r, out


def test_unknown_keys_fail_naming_the_key(tmp_path):
    with pytest.raises(ConfigError) as e:
        TrackConfig.from_dict({"edges": {"xyz": 1}})
    assert e.value.field == "edges.xyz"
    with pytest.raises(ConfigError) as e:
        TrackConfig().merged({"klt.window": 5})
    assert e.value.field == "klt.window"


def test_cli_unknown_key_in_a_config_file(teabox, tmp_path):
    t, d = teabox
    f = tmp_path / "bad.yaml"
    f.write_text("track:\n  slam:\n    xyz: 2\n")
    r, out = _track(t, d, "bad", "--config", f, check=False)
    assert r.returncode == 1 and not out.exists()
    assert "slam.xyz" in r.stderr and str(f) in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_config_file_sets_an_edges_and_a_slam_parameter(teabox, tmp_path):
    """edges.max_samples caps the samples per frame (traj.csv); slam.klt.max_features caps the
    SLAM's corners, so its map (--landmarks, mono aid: the whole video, ~280 landmarks with 400)."""
    t, d = teabox
    r0, out0 = _track(t, d, "plain", "--slam", "mono", "--landmarks", d / "lm0.ply", frames="0:39")
    s0 = json.loads(r0.stdout)
    f = tmp_path / "run.yaml"
    f.write_text("track:\n  edges:\n    max_samples: 40\n  slam:\n    klt:\n      max_features: 30\n")
    r1, out1 = _track(t, d, "capped", "--slam", "mono", "--landmarks", d / "lm1.ply", "--config", f, frames="0:39")
    s1 = json.loads(r1.stdout)
    n0 = [int(r["samples"]) for r in csv.DictReader(open(out0.with_suffix(".csv")))]
    n1 = [int(r["samples"]) for r in csv.DictReader(open(out1.with_suffix(".csv")))]
    assert max(n0) > 40 >= max(n1) > 0
    assert s0["landmarks"] > 100 and 0 < s1["landmarks"] <= 30
    assert s1["config"]["edges"]["max_samples"] == 40 and s1["config"]["slam"]["klt"]["max_features"] == 30
    assert s1["config"]["slam"]["klt"]["max_iterations"] == 10  # the SLAM's own KLT defaults kept


def test_echoed_config_repeats_the_run(teabox, tmp_path):
    """The `config` of --json, given back with --config (and none of the options), gives the same trajectory."""
    t, d = teabox
    r0, out0 = _track(t, d, "first", "--set", "edges.search_range_px=6", "--range", "7", "--no-relocalise")
    cfg = json.loads(r0.stdout)["config"]
    assert cfg["edges"]["search_range_px"] == 7 and cfg["relocalise"] is False  # the explicit option wins over --set
    assert cfg["use_klt"] is True and cfg["aid"] == "auto"  # the default mode, resolved
    f = tmp_path / "again.json"
    f.write_text(json.dumps(cfg))
    r1, out1 = _track(t, d, "again", "--config", f)
    assert out1.read_text() == out0.read_text()
    assert json.loads(r1.stdout)["config"] == cfg


def test_visp_xml_is_the_base_layer(shared_data, tmp_path):
    """teabox.xml's tags land on the fields; a preset and --set override them."""
    from mst.cli.common import build_config
    from mst.pipeline.tracking.config import visp_xml_settings

    xml = shared_data / "visp-teabox" / "teabox.xml"
    assert read_tracker_xml(xml).edges.far_clip_m == 100.0
    base = visp_xml_settings(xml)
    c = build_config(TrackConfig, base=base, preset="uav-480p", set_values=["edges.passes=2"])
    assert c.edges.far_clip_m is None and c.edges.angle_appear_deg == 80.0 and c.edges.passes == 2
    assert c.klt.window_px == 5  # <window_size>5</window_size>: the window's side (ViSP's vpKltOpencv)


def test_show_config_lists_the_sections(tmp_path):
    from conftest import run_mst

    r = run_mst("track", "--show-config")
    for key in ("edges.search_range_px", "klt.window_px", "slam.klt.fb_max_px", "depth.scale", "reloc.every",
                "uav-480p", "tabletop"):
        assert key in r.stdout, key


def test_option_bounds_name_the_option(teabox):
    t, d = teabox
    r, out = _track(t, d, "badopt", "--range", "0", check=False)
    assert r.returncode == 1 and "'--range'" in r.stderr and not out.exists()


def test_depth_scale_reaches_the_rgbd_aid(tmp_path):
    """16-bit depth written at 2000 units per metre, tracked with --depth-scale 2000, gives the same
    trajectory as the millimetre depth with the default (1000): track reads depth through its
    depth section (before, track read 16-bit depth as millimetres only)."""
    from pathlib import Path

    import cv2
    from conftest import run_mst

    from mst.pipeline.synth import SynthConfig, synthesize

    model = Path(__file__).resolve().parents[1] / "samples" / "building_tin.obj"
    if not model.exists():
        pytest.skip("samples/building_tin.obj missing")
    seq = tmp_path / "seq"
    synthesize("orbit", model, seq, SynthConfig(width=320, height=240, frames=8))
    mm, half_mm = tmp_path / "depth_mm", tmp_path / "depth_2000"
    mm.mkdir()
    half_mm.mkdir()
    for p in sorted((seq / "depth").glob("*.png")):
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert d.dtype == np.uint16
        d[d > 32767] = 0  # beyond 32.8 m (the 2000/m copy's 16-bit range): no depth in both copies
        cv2.imwrite(str(mm / p.name), d)
        cv2.imwrite(str(half_mm / p.name), d * 2)
    outs = []
    for name, depth, extra in (("mm", mm, ()), ("s2000", half_mm, ("--depth-scale", "2000")), ("wrong", half_mm, ())):
        out = tmp_path / f"{name}.txt"
        r = run_mst("track", seq / "rgb", "--fps", "30", "--model", seq / "model.obj", "--camera", seq / "camera.json",
                    "--init", seq / "cMo" / "000000.txt", "--depth", depth, "-o", out, "--json", "-q", *extra)
        assert json.loads(r.stdout)["aid"] == "rgbd"
        outs.append(out)
    assert outs[0].read_text() == outs[1].read_text()
    assert outs[2].read_text() != outs[0].read_text()  # the same depth read as millimetres: twice as far


def test_search_range_and_retry_levels_follow_the_image_width():
    """The width-derived defaults (issue 11): ViSP's 8 px and no coarse-to-fine retry up to 640 /
    1279 px wide (the real teabox, the 320x240 tests), the same angular range above; explicit
    values and the LOD face rule (range^2) follow."""
    from mst.core.camera import Camera
    from mst.meshtools.generate import box_model
    from mst.pipeline.tracking import EdgeTracker
    from mst.pipeline.tracking.config import (
        EdgesConfig,
        lod_thresholds,
        retry_pyramid_levels,
        search_range_px,
    )

    e = EdgesConfig()
    assert [search_range_px(e, w) for w in (0, 320, 640, 1280, 1920, 3840)] == [8, 8, 8, 16, 24, 48]
    assert [retry_pyramid_levels(e, w) for w in (0, 639, 640, 1279, 1280, 1920, 2559, 2560, 3840)] == [1, 1, 2, 2, 2, 2, 2, 3, 3]
    assert lod_thresholds(e, 1920)[1] == 24.0**2 and lod_thresholds(e)[1] == 64.0
    fixed = EdgesConfig(search_range_px=10, retry_pyramid_levels=1)
    assert search_range_px(fixed, 1920) == 10 and retry_pyramid_levels(fixed, 1920) == 1
    tr = EdgeTracker(box_model(), Camera(1575.0, 1575.0, 959.5, 539.5, 1920, 1080), TrackConfig())
    assert (tr.cfg.search_range_px, tr.cfg.retry_pyramid_levels, tr.lod[1]) == (24, 2, 576.0)
