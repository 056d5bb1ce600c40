"""The configuration system (mst.core.config): strict parsing, bounds once, layering, round trip."""

from __future__ import annotations

import json
from dataclasses import dataclass

import click
import pytest

from mst.cli.common import build_config, parse_set_values
from mst.core.config import Config, expand_dotted, load_config_file, param, register_preset, resolve, section
from mst.errors import ConfigError, InputError


@dataclass
class Inner(Config):
    """An inner section."""

    scale: float = param(1000.0, min=0, min_open=True, help="units per metre")
    min_m: float = param(0.1, min=0)
    max_m: float = param(50.0, min=0)

    def check(self) -> None:
        if not self.min_m < self.max_m:
            raise ConfigError("min_m", f"must be below max_m ({self.max_m:g} m), got {self.min_m:g}")


@dataclass
class Outer(Config):
    """An outer config."""

    depth: Inner = section(Inner)
    mask_px: int = param(5, min=3, max=31, odd=True)
    far_m: float | None = param(None, min=0, min_open=True)
    grid: tuple[int, int] = (8, 6)
    mode: str = param("auto", choices=("auto", "off"))
    ba: bool | None = None


register_preset(Outer, "tabletop", {"far_m": 2.0, "depth.max_m": 3.0}, "a test preset")


def test_defaults_round_trip_through_json():
    cfg = Outer()
    d = json.loads(json.dumps(cfg.to_dict()))
    assert Outer.from_dict(d) == cfg
    assert d["depth"] == {"scale": 1000.0, "min_m": 0.1, "max_m": 50.0}


def test_types_are_converted_from_text_and_yaml_values():
    cfg = Outer.from_dict({"mask_px": "7", "far_m": "1e3", "grid": [4, 3], "ba": "on", "depth": {"scale": 5000}})
    assert (cfg.mask_px, cfg.far_m, cfg.grid, cfg.ba, cfg.depth.scale) == (7, 1000.0, (4, 3), True, 5000.0)
    assert Outer.from_dict({"far_m": None, "ba": "null"}).ba is None


@pytest.mark.parametrize("d, field, words", [
    ({"depth": {"scal": 1}}, "depth.scal", "unknown key"),
    ({"mask": 5}, "mask", "unknown key"),
    ({"depth": {"scale": 0}}, "depth.scale", "> 0"),
    ({"mask_px": 6}, "mask_px", "odd"),
    ({"mask_px": 2.5}, "mask_px", "integer"),
    ({"mask_px": 33}, "mask_px", "<= 31"),
    ({"far_m": "nan"}, "far_m", "NaN"),
    ({"far_m": [1]}, "far_m", "number"),
    ({"grid": [1, 2, 3]}, "grid", "2 values"),
    ({"mode": "sometimes"}, "mode", "one of"),
    ({"ba": "maybe"}, "ba", "true or false"),
    ({"depth": 3}, "depth", "section"),
    ({"depth": {"min_m": 60}}, "depth.min_m", "below max_m"),
])
def test_bad_values_name_the_dotted_field_and_the_source(d, field, words):
    with pytest.raises(ConfigError) as e:
        Outer.from_dict(d, source="run.yaml")
    assert e.value.field == field
    assert words in e.value.problem
    assert str(e.value).startswith(f"run.yaml: {field}: ")


def test_bounds_hold_for_library_callers_too():
    with pytest.raises(ConfigError, match="scale"):
        Inner(scale=-1.0)
    with pytest.raises(ConfigError, match="mask_px"):
        Outer().replace(mask_px=4)


def test_layers_file_over_preset_over_defaults_and_overrides_last(tmp_path):
    f = tmp_path / "run.yaml"
    f.write_text("track:\n  far_m: 5\n  depth:\n    scale: 5000\nfuse:\n  other: 1\n")
    cfg = resolve(Outer, preset="tabletop", file=f, section_name="track", overrides={"depth.min_m": 0.2})
    assert (cfg.far_m, cfg.depth.max_m, cfg.depth.scale, cfg.depth.min_m) == (5.0, 3.0, 5000.0, 0.2)
    # a bad value in the file is reported with the file's name
    f.write_text("depth:\n  scale: -5\n")
    with pytest.raises(ConfigError, match=r"run\.yaml: depth\.scale"):
        resolve(Outer, file=f)
    with pytest.raises(ConfigError, match="unknown preset 'uav'.*tabletop"):
        resolve(Outer, preset="uav")


@pytest.mark.parametrize("text, suffix, words", [
    ("a: [1, 2", ".yaml", "not valid YAML"),
    ("{\"a\": 1", ".json", "not valid JSON"),
    ("- 1\n- 2\n", ".yaml", "mapping"),
    ("a: 1", ".toml", "unknown config format"),
])
def test_bad_config_files_are_input_errors_naming_the_file(tmp_path, text, suffix, words):
    f = tmp_path / f"c{suffix}"
    f.write_text(text)
    with pytest.raises(InputError, match=words) as e:
        load_config_file(f)
    assert e.value.path == str(f)


def test_dotted_keys_expand_and_merge():
    assert expand_dotted({"a.b": 1, "a": {"c": 2}, "d": 3}) == {"a": {"b": 1, "c": 2}, "d": 3}
    assert Outer().merged({"depth.scale": 2.0, "grid": [2, 2]}).to_dict()["depth"]["scale"] == 2.0


def test_cli_set_values_and_explicit_options_win(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"far_m": 9, "mask_px": 7}))
    assert parse_set_values(["a.b=2", "c=[8, 6]", "d=null"]) == {"a.b": 2, "c": [8, 6], "d": None}
    cfg = build_config(Outer, config_file=f, set_values=["mask_px=9"], options={"far_m": 3.0, "depth.scale": None})
    assert (cfg.far_m, cfg.mask_px, cfg.depth.scale) == (3.0, 9, 1000.0)
    # a bad explicit option is a usage error under the flag the user typed
    with pytest.raises(click.BadParameter) as e:
        build_config(Outer, options={"far_m": -1.0}, flags={"far_m": "--far"})
    assert "--far" in e.value.format_message() or e.value.param_hint == "'--far'"
    with pytest.raises(click.BadParameter, match="KEY=VALUE"):
        parse_set_values(["novalue"])


def test_off_is_a_word_in_set_values_and_settings_files(tmp_path):
    """A choice whose value is ``off`` (``klt.reanchor off``, ``aid off``) can be written as documented:
    in ``--set`` and in a YAML settings file ``off``/``on``/``yes``/``no`` stay words (YAML 1.2), where
    PyYAML's YAML 1.1 had turned ``off`` into ``false`` and the setting refused it ("needs a string").
    Booleans are still booleans: ``true``/``false`` parse as such, and a boolean setting takes the words."""
    from mst.pipeline.tracking.config import TrackConfig

    assert parse_set_values(["mode=off", "ba=on", "x=true", "y=False", "z=no"]) == {
        "mode": "off", "ba": "on", "x": True, "y": False, "z": "no"}
    cfg = build_config(Outer, set_values=["mode=off", "ba=off"])
    assert (cfg.mode, cfg.ba) == ("off", False)
    (tmp_path / "o.yaml").write_text("mode: off\nba: yes\n")
    cfg = build_config(Outer, config_file=tmp_path / "o.yaml")
    assert (cfg.mode, cfg.ba) == ("off", True)
    (tmp_path / "t.yaml").write_text("klt:\n  reanchor: off\naid: off\n")
    tc = build_config(TrackConfig, config_file=tmp_path / "t.yaml")
    assert (tc.klt.reanchor, tc.aid) == ("off", "off")
    assert build_config(TrackConfig, set_values=["klt.reanchor=off"]).klt.reanchor == "off"


def test_infinite_values_survive_the_json_round_trip():
    """``max_m = inf`` (no far limit) is echoed as "inf" and read back, so --config of it repeats the run."""
    cfg = Inner(max_m=float("inf"))
    d = json.loads(json.dumps(cfg.to_dict(), allow_nan=False))
    assert d["max_m"] == "inf"
    assert Inner.from_dict(d) == cfg
