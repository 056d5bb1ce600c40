"""One configuration system for every stage: nested dataclasses, units in field names, strict parsing.

A stage's configuration is a ``@dataclass`` that inherits :class:`Config`; a field that is itself a
:class:`Config` is a nested section (``TrackConfig(edges, klt, slam, depth)``). Field names carry
their units (``_px``, ``_m``, ``_deg``, ``_s``); bounds live once, in the field's metadata
(:func:`param`), and are checked when the object is built, whoever builds it (a file, a preset, a
command-line option, a library caller)::

    @dataclass
    class DepthConfig(Config):
        scale: float = param(1000.0, min=0, min_open=True, help="raw depth units per metre")
        min_m: float = param(0.1, min=0, help="nearer depth is invalid (m)")

    DepthConfig.from_dict({"scale": 5000})            # TUM RGB-D depth
    DepthConfig.from_dict({"scal": 5000})             # ConfigError: scal: unknown key (known: ...)

Sources are layered by :func:`resolve`: defaults < preset < config file < explicit overrides (the
command line's options and ``--set key=value``). The effective configuration goes back out with
:meth:`Config.to_dict` (echoed in every ``--json`` summary, so that a run can be repeated exactly
with ``--config``).

Imports the standard library, :mod:`mst.errors` and (lazily, for ``.yaml`` files) PyYAML only.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from mst.errors import ConfigError, InputError

C = TypeVar("C", bound="Config")


def param(default: Any = dataclasses.MISSING, *, min: float | None = None, max: float | None = None,
          min_open: bool = False, max_open: bool = False, choices: tuple | None = None, odd: bool = False,
          help: str = "", default_factory: Any = dataclasses.MISSING) -> Any:
    """A config field with its bounds and help text (the one place a setting's rule is written).

    ``min``/``max`` bound numbers (closed unless ``min_open``/``max_open``; ``None`` values pass:
    ``None`` means "derived" or "off" where a field's type allows it); ``choices`` restricts
    strings; ``odd`` requires an odd integer (mask sizes).
    """
    md = {"min": min, "max": max, "min_open": min_open, "max_open": max_open, "choices": choices,
          "odd": odd, "help": help}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def section(cls: type[C]) -> Any:
    """A nested config section field with ``cls()``'s defaults."""
    return dataclasses.field(default_factory=cls, metadata={"help": (cls.__doc__ or "").strip().split("\n")[0]})


def _hints(cls: type) -> dict[str, Any]:
    cache = cls.__dict__.get("_mst_hints")
    if cache is None:
        cache = typing.get_type_hints(cls)
        cls._mst_hints = cache
    return cache


def _is_config(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, Config)


def _optional_of(tp: Any) -> tuple[bool, Any]:
    """(``None`` allowed, the non-None type) of an annotation such as ``float | None``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        none_ok = len(args) < len(typing.get_args(tp))
        return none_ok, (args[0] if len(args) == 1 else typing.Union[tuple(args)])  # noqa: UP007
    return False, tp


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, name: str) -> Any:
    """``value`` converted to the annotation ``tp``; ConfigError naming ``name`` when it cannot be."""
    none_ok, base = _optional_of(tp)
    if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null") and none_ok):
        if none_ok:
            return None
        raise ConfigError(name, f"needs a {_type_name(base)}, got null")
    if _is_config(base):
        if isinstance(value, base):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(name, f"is a section, expected a mapping of its keys, got {value!r}")
        return base.from_dict(value, prefix=name)
    origin = typing.get_origin(base)
    if base is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
            return value.strip().lower() in ("true", "yes", "on", "1")
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ConfigError(name, f"needs true or false, got {value!r}")
    if base is int:
        if isinstance(value, bool):
            raise ConfigError(name, f"needs an integer, got {value!r}")
        try:
            f = float(value)
        except (TypeError, ValueError):
            raise ConfigError(name, f"needs an integer, got {value!r}") from None
        if not math.isfinite(f) or f != int(f):
            raise ConfigError(name, f"needs an integer, got {value!r}")
        return int(f)
    if base is float:
        if isinstance(value, bool):
            raise ConfigError(name, f"needs a number, got {value!r}")
        try:
            f = float(value)
        except (TypeError, ValueError):
            raise ConfigError(name, f"needs a number, got {value!r}") from None
        if math.isnan(f):
            raise ConfigError(name, "needs a number, got NaN")
        return f
    if base is str:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(name, f"needs a string, got {value!r}")
        return str(value)
    if origin is tuple:
        args = typing.get_args(base)
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split() if v]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(name, f"needs a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{name}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(name, f"needs {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{name}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin is typing.Literal:
        if value not in typing.get_args(base):
            raise ConfigError(name, f"must be one of {', '.join(map(str, typing.get_args(base)))}, got {value!r}")
        return value
    return value


def _check(value: Any, md: Mapping[str, Any], name: str) -> None:
    """Bounds and choices of one field (``None`` passes: it means derived/off)."""
    if value is None:
        return
    choices = md.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(name, f"must be one of {', '.join(map(str, choices))}, got {value!r}")
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if isinstance(v, float) and math.isnan(v):
            raise ConfigError(name, "must be a number, got NaN")
        lo, hi = md.get("min"), md.get("max")
        if lo is not None and (v < lo or (md.get("min_open") and v == lo)):
            raise ConfigError(name, f"must be {'>' if md.get('min_open') else '>='} {lo:g}, got {v:g}")
        if hi is not None and (v > hi or (md.get("max_open") and v == hi)):
            raise ConfigError(name, f"must be {'<' if md.get('max_open') else '<='} {hi:g}, got {v:g}")
        if md.get("odd") and int(v) % 2 == 0:
            raise ConfigError(name, f"must be odd, got {v:g}")


class Config:
    """Base of every stage configuration (use with ``@dataclass``).

    Building an instance validates every field against its :func:`param` bounds (a
    :class:`~mst.errors.ConfigError` names the field); subclasses add cross-field rules in
    :meth:`check` (call ``super().check()`` first is not needed: field bounds run before it).
    """

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not _is_config(_optional_of(hints.get(f.name))[1]):
                _check(v, f.metadata, f.name)
        self.check()

    def check(self) -> None:
        """Cross-field rules; raise ``ConfigError(field, problem)``. The default has none."""

    # -- building ---------------------------------------------------------------------------
    @classmethod
    def from_dict(cls: type[C], d: Mapping[str, Any] | C | None, *, prefix: str = "",
                  source: str | os.PathLike | None = None) -> C:
        """An instance from a mapping of field names (nested mappings for sections).

        Strict: an unknown key is a :class:`ConfigError` naming it (with its dotted ``prefix``) and
        the known keys; values are converted to the field types (``"5"`` -> 5, ``"on"`` -> True,
        ``null`` -> None where allowed). ``source`` names the file/preset in errors.
        """
        if isinstance(d, cls):
            return d
        d = {} if d is None else d
        dotted = f"{prefix}." if prefix else ""
        try:
            if not isinstance(d, Mapping):
                raise ConfigError(prefix or cls.__name__, f"expected a mapping of settings, got {type(d).__name__}")
            hints = _hints(cls)
            known = {f.name: f for f in dataclasses.fields(cls) if f.init}
            kw = {}
            for k, v in d.items():
                if k not in known:
                    raise ConfigError(f"{dotted}{k}", f"unknown key (known: {', '.join(sorted(known))})")
                factory = known[k].default_factory
                if isinstance(v, Mapping) and _is_config(_optional_of(hints[k])[1]) and factory is not dataclasses.MISSING:
                    # a partial section keeps the stage's own defaults for it (e.g. the SLAM's KLT),
                    # not the section class's
                    v = deep_merge(factory().to_dict(), v)
                kw[k] = _coerce(v, hints[k], f"{dotted}{k}")
            try:
                return cls(**kw)
            except ConfigError as e:
                if prefix and not e.field.startswith(dotted):
                    raise ConfigError(f"{dotted}{e.field}", e.problem, e.source) from None
                raise
        except ConfigError as e:
            raise e.with_source(source) from None

    def to_dict(self) -> dict[str, Any]:
        """The configuration as plain JSON-ready values (sections nested, tuples as lists)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Config):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            elif isinstance(v, float) and math.isinf(v):
                v = "inf" if v > 0 else "-inf"  # JSON has no infinity; from_dict reads the text back
            out[f.name] = v
        return out

    def merged(self: C, overrides: Mapping[str, Any] | None, *, source: str | os.PathLike | None = None) -> C:
        """A copy with ``overrides`` (nested or dotted keys: ``{"slam.fb_max_px": 2}``) applied, strictly."""
        if not overrides:
            return self
        return type(self).from_dict(deep_merge(self.to_dict(), expand_dotted(overrides)), source=source)

    def replace(self: C, **changes: Any) -> C:
        """``dataclasses.replace`` with validation (the new object is checked like any other)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def describe(cls, prefix: str = "") -> list[tuple[str, str, Any, str]]:
        """Every setting as ``(dotted name, type, default, help)`` rows, sections expanded."""
        rows = []
        hints = _hints(cls)
        inst = cls()
        for f in dataclasses.fields(cls):
            tp = _optional_of(hints[f.name])[1]
            name = f"{prefix}{f.name}"
            if _is_config(tp):
                rows += tp.describe(prefix=f"{name}.")
            else:
                rows.append((name, _type_name(hints[f.name]), getattr(inst, f.name), f.metadata.get("help", "")))
        return rows


def expand_dotted(d: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a.b": 1, "c": {"d.e": 2}}`` -> ``{"a": {"b": 1}, "c": {"d": {"e": 2}}}``."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        v = expand_dotted(v) if isinstance(v, Mapping) else v
        parts = str(k).split(".")
        node = out
        for p in parts[:-1]:
            nxt = node.get(p)
            if not isinstance(nxt, dict):
                nxt = node[p] = {}
            node = nxt
        last = parts[-1]
        if isinstance(v, dict) and isinstance(node.get(last), dict):
            node[last] = deep_merge(node[last], v)
        else:
            node[last] = v
    return out


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` applied; mappings merge key by key, anything else replaces."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


_LOADER = None


def yaml_loader():
    """PyYAML's ``SafeLoader`` with YAML 1.2's booleans: only ``true``/``false`` (any case) are
    booleans, so ``off``, ``on``, ``yes``, ``no`` stay the words they are. YAML 1.1 (PyYAML's
    default) reads ``reanchor: off`` as ``false``, and a setting whose choices include ``off``
    (``klt.reanchor``, ``aid``) could not be written as its documented value in a settings file or
    in ``--set``. A boolean setting still takes those words (:func:`_coerce` maps them)."""
    global _LOADER
    if _LOADER is None:
        import re

        import yaml

        class Yaml12BoolLoader(yaml.SafeLoader):
            pass

        resolvers = {}
        for ch, items in yaml.SafeLoader.yaml_implicit_resolvers.items():
            resolvers[ch] = [(tag, rx) for tag, rx in items if tag != "tag:yaml.org,2002:bool"]
        Yaml12BoolLoader.yaml_implicit_resolvers = resolvers
        Yaml12BoolLoader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                               list("tTfF"))
        _LOADER = Yaml12BoolLoader
    return _LOADER


def load_yaml_text(text: str) -> Any:
    """``text`` parsed as YAML with :func:`yaml_loader` (raises PyYAML's errors)."""
    import yaml

    return yaml.load(text, Loader=yaml_loader())  # noqa: S506 - a SafeLoader subclass


def parse_yaml(path: str | os.PathLike, text: str) -> Any:
    """``text`` (the contents of ``path``) parsed as YAML (:func:`load_yaml_text`: ``off`` is a word,
    not ``false``); :class:`InputError` naming the file with the line and column of the first problem."""
    import yaml

    try:
        return load_yaml_text(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise InputError(path, f"not valid YAML: {getattr(e, 'problem', None) or e}{where}") from None


def load_config_file(path: str | os.PathLike, section_name: str | None = None) -> dict[str, Any]:
    """The settings mapping of a ``.yaml``/``.yml``/``.json`` config file.

    A file may hold one stage's settings, or one section per command (``track:``, ``fuse:``, ...,
    as a batch run writes them): with ``section_name`` given and present at the top level, that
    section is returned. Raises :class:`InputError` naming the file when it is missing, not valid
    YAML/JSON, or not a mapping.
    """
    from mst import read_text

    p = Path(path)
    text = read_text(p, "config file")
    suffix = p.suffix.lower()
    if suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(p, f"not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    elif suffix in (".yaml", ".yml"):
        data = parse_yaml(p, text)
    else:
        raise InputError(p, f"unknown config format {p.suffix or '(no suffix)'}: use .yaml, .yml or .json")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(p, f"a config file holds a mapping of settings, found a {type(data).__name__}")
    if section_name is not None and isinstance(data.get(section_name), dict):
        data = data[section_name]
    return data


#: named presets: (config class name, preset name) -> settings mapping (nested or dotted keys)
PRESETS: dict[tuple[str, str], dict[str, Any]] = {}


def register_preset(cls: type[Config], name: str, settings: Mapping[str, Any], doc: str = "") -> None:
    """Register a named preset of ``cls`` (validated now, so that a bad preset fails at import)."""
    cls.from_dict(expand_dotted(settings), source=f"preset {name}")
    PRESETS[(cls.__name__, name)] = {"settings": dict(settings), "doc": doc}


def presets_of(cls: type[Config]) -> dict[str, str]:
    """Preset name -> one-line description, for ``cls``."""
    return {n: v["doc"] for (c, n), v in PRESETS.items() if c == cls.__name__}


def resolve(cls: type[C], *, preset: str | None = None, file: str | os.PathLike | None = None,
            section_name: str | None = None, overrides: Mapping[str, Any] | None = None,
            base: Mapping[str, Any] | None = None) -> C:
    """The effective configuration: defaults < ``base`` < ``preset`` < ``file`` < ``overrides``.

    ``base`` is a mapping from an older settings source (e.g. a ViSP tracker XML); ``overrides``
    are explicit values (command-line options, ``--set``), nested or dotted. Each layer is checked
    strictly and an error names the layer it came from.
    """
    merged: dict[str, Any] = {}
    layers: list[tuple[Mapping[str, Any], str | None]] = []
    if base:
        layers.append((base, None))
    if preset is not None:
        entry = PRESETS.get((cls.__name__, preset))
        if entry is None:
            known = ", ".join(sorted(presets_of(cls))) or "none"
            raise ConfigError("preset", f"unknown preset {preset!r} (known: {known})")
        layers.append((entry["settings"], f"preset {preset}"))
    if file is not None:
        layers.append((load_config_file(file, section_name), str(file)))
    if overrides:
        layers.append((overrides, None))
    for layer, source in layers:
        merged = deep_merge(merged, expand_dotted(layer))
        cls.from_dict(merged, source=source)  # each layer strictly, so an error names its source
    return cls.from_dict(merged)
