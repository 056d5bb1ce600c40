"""Absurd tracker settings (issue 9) are refused at parse time, naming the setting and the file.

Every numeric tracker setting, from a ViSP tracker XML, a config file or a `mst track` option, is
checked against its bounds (the ``param`` of its :class:`mst.pipeline.tracking.config.TrackConfig`
field) before anything is allocated or written: a moving-edge search range of 10^8 px once asked
for 547 GiB. In-process (the XML reader and the CLI entry point), no subprocess.
"""

from __future__ import annotations

import pytest

from mst import InputError
from mst.errors import ConfigError
from mst.pipeline.tracking.config import EdgesConfig, TrackConfig, lod_thresholds, read_tracker_xml

# (tag path under <conf>, value) -> refused; the message must name the tag
BAD_XML = [
    ("ecm/range/tracking", "100000000"),  # the 547 GiB case
    ("ecm/range/tracking", "0"),
    ("ecm/range/tracking", "-5"),
    ("ecm/range/tracking", "nan"),
    ("ecm/range/tracking", "inf"),
    ("ecm/range/tracking", "2.5"),
    ("ecm/mask/size", "4"),
    ("ecm/mask/size", "1"),
    ("ecm/mask/size", "1e9"),
    ("ecm/mask/size", "NaN"),
    ("ecm/mask/nb_mask", "0"),
    ("ecm/mask/nb_mask", "1000000"),
    ("ecm/contrast/edge_threshold", "nan"),
    ("ecm/contrast/edge_threshold", "-1"),
    ("ecm/contrast/edge_threshold", "inf"),
    ("ecm/contrast/mu1", "nan"),
    ("ecm/contrast/mu1", "-0.1"),
    ("ecm/contrast/mu1", "1.5"),
    ("ecm/contrast/mu2", "nan"),
    ("ecm/contrast/mu2", "-1"),
    ("ecm/contrast/mu2", "inf"),
    ("ecm/sample/step", "nan"),
    ("ecm/sample/step", "0"),
    ("ecm/sample/step", "-4"),
    ("ecm/sample/step", "inf"),
    ("ecm/sample/step", "1e9"),
    ("face/angle_appear", "nan"),
    ("face/angle_appear", "-10"),
    ("face/angle_appear", "120"),
    ("face/angle_disappear", "200"),
    ("face/angle_disappear", "-inf"),
    ("face/near_clipping", "0"),
    ("face/near_clipping", "-0.1"),
    ("face/near_clipping", "nan"),
    ("face/far_clipping", "nan"),
    ("face/far_clipping", "-1"),
    ("face/far_clipping", "inf"),
    ("klt/window_size", "nan"),
    ("klt/max_features", "-1"),
    ("klt/quality", "0"),
    ("klt/pyramid_lvl", "100"),
    ("klt/harris", "nan"),
    ("lod/min_line_length_threshold", "-1"),
    ("lod/min_polygon_area_threshold", "nan"),
]


def _xml(tmp_path, tag: str, value: str, name: str = "settings.xml"):
    parts = tag.split("/")
    body = value
    for p in reversed(parts):
        body = f"<{p}>{body}</{p}>"
    f = tmp_path / name
    f.write_text(f"<?xml version='1.0'?>\n<conf>{body}</conf>\n")
    return f


@pytest.mark.parametrize("tag,value", BAD_XML, ids=[f"{t.split('/')[-1]}={v}" for t, v in BAD_XML])
def test_bad_xml_setting_names_the_tag_and_the_file(tmp_path, tag, value):
    f = _xml(tmp_path, tag, value)
    before = f.read_bytes()
    with pytest.raises(InputError) as e:
        read_tracker_xml(f)
    msg = str(e.value)
    assert msg.startswith(str(f) + ": ")
    assert f"<{tag}>" in msg
    assert "\n" not in msg
    assert f.read_bytes() == before  # input untouched


@pytest.mark.parametrize("conf", [
    "<face><angle_appear>85</angle_appear><angle_disappear>60</angle_disappear></face>",
    "<face><near_clipping>10</near_clipping><far_clipping>5</far_clipping></face>",
], ids=["appear>disappear", "near>=far"])
def test_inconsistent_pairs_name_both_tags(tmp_path, conf):
    f = tmp_path / "pair.xml"
    f.write_text(f"<conf>{conf}</conf>")
    with pytest.raises(InputError) as e:
        read_tracker_xml(f)
    msg = str(e.value)
    assert msg.startswith(str(f))
    tags = [t for t in ("<face/angle_appear>", "<face/angle_disappear>", "<face/near_clipping>", "<face/far_clipping>")
            if t.split("/")[1][:-1] in conf]
    assert all(t in msg for t in tags), msg


BAD_OPTIONS = [
    ("--range", "100000000"),
    ("--range", "-1"),
    ("--range", "0"),
    ("--step", "nan"),
    ("--step", "inf"),
    ("--step", "-4"),
    ("--step", "0"),
    ("--pyramid", "0"),
    ("--pyramid", "100"),
]


@pytest.mark.parametrize("opt,value", BAD_OPTIONS, ids=[f"{o}={v}" for o, v in BAD_OPTIONS])
def test_bad_track_option_is_named_exit_1_no_output(tmp_path, capsys, opt, value):
    from mst.cli.main import main

    out = tmp_path / "traj.txt"
    with pytest.raises(SystemExit) as e:
        main(["track", str(tmp_path / "v.mp4"), "--model", str(tmp_path / "m.obj"), "--camera", str(tmp_path / "c.json"),
              "--init", str(tmp_path / "p.txt"), "-o", str(out), opt, value, "-q"])
    assert e.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"Invalid value for '{opt}'" in err[0], err
    assert not list(tmp_path.iterdir())  # nothing written


def test_every_bound_is_enforced_on_the_dataclass():
    """Each bounded field: its default passes, a NaN and a value past a bound are refused, naming it."""
    import dataclasses

    cfg = TrackConfig()
    assert cfg.edges.far_clip_m is None and cfg.edges.near_clip_m is None  # survey-scale defaults: no far plane
    n = 0
    for f in dataclasses.fields(EdgesConfig):
        lo, hi = f.metadata.get("min"), f.metadata.get("max")
        if lo is None and hi is None:
            continue
        bad = [float("nan")] + ([hi * 2 + 1] if hi is not None else []) + ([lo - 1] if lo is not None else [])
        for v in bad:
            with pytest.raises(ConfigError) as e:
                cfg.merged({f"edges.{f.name}": v})
            assert e.value.field == f"edges.{f.name}"
            n += 1
    assert n >= 3 * 25


def test_visp_teabox_values_still_apply(shared_data):
    """The tea-box XML's explicit 0.1 / 100 m clipping is kept as given (not replaced by the defaults)."""
    c = read_tracker_xml(shared_data / "visp-teabox/teabox.xml")
    assert (c.edges.near_clip_m, c.edges.far_clip_m, c.edges.search_range_px) == (0.1, 100.0, 8)


def test_visp_lod_tags(tmp_path):
    """ViSP's <lod> section: thresholds as given, use_lod 0 turns the rule off; default derived."""
    assert lod_thresholds(TrackConfig().edges) == (12.0, 64.0)  # 3 x 4 px step, 8 px range squared
    f = tmp_path / "lod.xml"
    f.write_text("<conf><lod><use_lod>1</use_lod><min_line_length_threshold>50</min_line_length_threshold>"
                 "<min_polygon_area_threshold>2500</min_polygon_area_threshold></lod></conf>")
    assert lod_thresholds(read_tracker_xml(f).edges) == (50.0, 2500.0)
    f.write_text("<conf><lod><use_lod>0</use_lod></lod></conf>")
    assert lod_thresholds(read_tracker_xml(f).edges) == (0.0, 0.0)
