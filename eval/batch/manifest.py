"""The batch manifest: which sequences ``mst batch`` runs, from a YAML or CSV file.

YAML::

    defaults:                      # shared by every sequence; a sequence's own keys override them
      fps: 30
      options:
        track: {slam: "off"}       # options of the stage's command, by their long name
        eval: {align: none}
    sequences:
      - name: house-orbit          # the folder OUT/house-orbit
        frames: seq1/rgb           # image folder, video, glob or printf pattern
        model: house.obj           # TIN: converted once per model (convert-model); .wrl/.cao used as is
        camera: seq1/camera.json
        clicks: seq1/clicks.txt    # the first pose: clicks (+ points), init (a pose file) or nav
        depth: seq1/depth          # optional: fuse runs when given
        reference: seq1/scene.ply  # optional: c2m of the fused cloud against this mesh
        gt: seq1/gt.txt            # optional: eval traj against it
        options: {"track.range": 8}

CSV: one row per sequence, the same keys as columns, options as ``stage.option`` columns (an
empty cell is "not given"). Paths are relative to the manifest's folder. Every check that needs no
computation runs here, before anything is written: a missing file, a duplicate or bad name, an
unknown key or option, an option the batch sets itself, a value the option's type refuses.
"""

from __future__ import annotations

import csv
import glob
import io
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mst import InputError, read_text

#: stage name -> the ``mst`` command words that run it
STAGE_COMMANDS: dict[str, tuple[str, ...]] = {
    "convert-model": ("convert-model",),
    "init": ("init",),
    "track": ("track",),
    "fuse": ("fuse",),
    "c2m": ("c2m",),
    "eval": ("eval", "traj"),
}
STAGES = tuple(STAGE_COMMANDS)

#: stage name -> its click command (given by the command layer)
CommandOf = Callable[[str], Any]

#: keys of a sequence entry that name input files (relative to the manifest)
PATH_KEYS = ("frames", "model", "camera", "init", "clicks", "points", "nav", "depth", "gt", "reference")
SEQUENCE_KEYS = ("name", *PATH_KEYS, "video", "fps", "options")

#: options the batch sets itself (from the sequence's keys and its own output names)
_ALWAYS = {"json", "quiet", "help", "show-config", "verbose"}
RESERVED: dict[str, set[str]] = {
    "convert-model": {"output"},
    "init": {"model", "camera", "clicks", "points", "from-nav", "image", "output", "show-points"},
    "track": {"model", "camera", "init", "output", "depth", "fps"},
    "fuse": {"traj", "depth", "camera", "output", "fps"},
    "c2m": {"output", "markdown", "plot", "csv"},
    "eval": {"plot"},
}
#: path options that are outputs (placed in the sequence's folder), not inputs
OUTPUT_OPTIONS: dict[str, set[str]] = {"init": {"overlay"}, "track": {"overlay", "landmarks"}}

#: marks an output option's value in StageOptions.args: a name inside the sequence's folder
OUT_PREFIX = "@sequence/"

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass
class StageOptions:
    """The extra arguments of one stage's command, with the files they read and write."""

    args: tuple[str, ...] = ()
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()


@dataclass
class SequenceSpec:
    """One sequence of the manifest, paths absolute."""

    name: str
    frames: str
    model: str
    camera: str
    init: str | None = None
    clicks: str | None = None
    points: str | None = None
    nav: str | None = None
    depth: str | None = None
    gt: str | None = None
    reference: str | None = None
    fps: float | None = None
    #: stage -> its options (output options still relative to the sequence folder)
    options: dict[str, StageOptions] = field(default_factory=dict)


@dataclass
class Manifest:
    path: Path
    sequences: list[SequenceSpec]


def _long_names(opt) -> list[str]:
    return [o[2:] for o in (*opt.opts, *opt.secondary_opts) if o.startswith("--")]


def _is_path_type(tp) -> bool:
    import click

    return isinstance(tp, (click.Path, click.File))


def _option_args(stage: str, name: str, value: Any, base: Path, where: str, manifest: Path,
                 command_of: CommandOf) -> StageOptions:
    """``--name value`` arguments of ``stage``'s command, checked against the command's options."""
    import click

    cmd = command_of(stage)
    name = str(name).lstrip("-")
    if name in _ALWAYS or name in RESERVED[stage]:
        raise InputError(manifest, f"{where}: option --{name} of mst {stage} is set by the batch itself")
    opts = {n: p for p in cmd.params if isinstance(p, click.Option) for n in _long_names(p)}
    opt = opts.get(name)
    if opt is None:
        known = ", ".join(sorted(n for n in opts if n not in _ALWAYS and n not in RESERVED[stage]))
        raise InputError(manifest, f"{where}: unknown option --{name} of mst {stage} (known: {known})")
    flag = f"--{name}"
    if opt.is_flag:
        if isinstance(value, str) and value.strip().lower() in ("yes", "on", "no", "off"):  # YAML 1.1's booleans
            value = value.strip().lower() in ("yes", "on")
        if not isinstance(value, bool):
            raise InputError(manifest, f"{where}: --{name} is a flag, give true or false, got {value!r}")
        if value:
            return StageOptions((flag,))
        negative = [o for o in opt.secondary_opts if o != flag] if flag in opt.opts else list(opt.opts)
        return StageOptions(tuple(negative[:1]))
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    if opt.nargs > 1 and not opt.multiple:
        values = [values]
    args: list[str] = []
    inputs: list[str] = []
    outputs: list[str] = []
    for v in values:
        parts = list(v) if isinstance(v, list) else [v]
        if opt.nargs > 1 and len(parts) != opt.nargs:
            raise InputError(manifest, f"{where}: --{name} takes {opt.nargs} values, got {len(parts)}")
        texts = []
        for p in parts:
            text = ("on" if p else "off") if isinstance(p, bool) else str(p)
            if _is_path_type(opt.type):
                if name in OUTPUT_OPTIONS.get(stage, ()):
                    if os.path.isabs(text) or ".." in Path(text).parts:
                        raise InputError(manifest, f"{where}: --{name} is an output: give a name inside the "
                                                   f"sequence's folder, got {text!r}")
                    outputs.append(text)
                    text = OUT_PREFIX + text
                else:
                    full = (base / text).resolve()
                    if not full.exists():
                        raise InputError(manifest, f"{where}: --{name} file {text} does not exist")
                    text = str(full)
                    inputs.append(text)
            else:
                try:
                    opt.type.convert(text, opt, None)
                except click.BadParameter as e:
                    raise InputError(manifest, f"{where}: --{name}: {e.format_message()}") from None
            texts.append(text)
        args += [flag, *texts]
    return StageOptions(tuple(args), tuple(inputs), tuple(outputs))


def _stage_options(options: Any, base: Path, where: str, manifest: Path,
                   command_of: CommandOf) -> dict[str, StageOptions]:
    """``{"track": {"slam": "off"}, "eval.align": "none"}`` -> stage -> :class:`StageOptions`."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InputError(manifest, f"{where}: options must be a mapping of stage -> {{option: value}}")
    per_stage: dict[str, dict[str, Any]] = {}
    for key, value in options.items():
        stage, dot, opt = str(key).partition(".")
        if stage not in STAGE_COMMANDS:
            raise InputError(manifest, f"{where}: options: unknown stage {stage!r} (stages: {', '.join(STAGES)})")
        if dot:
            per_stage.setdefault(stage, {})[opt] = value
        elif isinstance(value, Mapping):
            per_stage.setdefault(stage, {}).update(value)
        else:
            raise InputError(manifest, f"{where}: options.{stage} must be a mapping of option -> value")
    out: dict[str, StageOptions] = {}
    for stage, items in per_stage.items():
        parts = [_option_args(stage, k, v, base, f"{where}: options.{stage}", manifest, command_of)
                 for k, v in items.items() if v is not None and v != ""]
        out[stage] = StageOptions(tuple(a for p in parts for a in p.args), tuple(a for p in parts for a in p.inputs),
                                  tuple(a for p in parts for a in p.outputs))
    return out


def _exists(text: str) -> bool:
    if any(c in text for c in "*?[") or re.search(r"%0?\d*d", text):
        return bool(glob.glob(re.sub(r"%0?\d*d", "*", text)))
    return os.path.exists(text)


def _merge(defaults: Mapping[str, Any], entry: Mapping[str, Any]) -> dict[str, Any]:
    out = {**defaults, **entry}
    opts: dict[str, Any] = {}
    for src in (defaults.get("options"), entry.get("options")):
        if isinstance(src, Mapping):
            for k, v in src.items():
                if isinstance(v, Mapping) and isinstance(opts.get(k), Mapping):
                    opts[k] = {**opts[k], **v}
                else:
                    opts[k] = v
        elif src is not None:
            opts = src  # reported by _stage_options
    if opts:
        out["options"] = opts
    return out


def _sequence(entry: Mapping[str, Any], index: int, base: Path, manifest: Path, command_of: CommandOf) -> SequenceSpec:
    where = f"sequence {index + 1}"
    if not isinstance(entry, Mapping):
        raise InputError(manifest, f"{where}: expected a mapping of keys, got {type(entry).__name__}")
    for k in entry:
        if k not in SEQUENCE_KEYS:
            raise InputError(manifest, f"{where}: unknown key {k!r} (known: {', '.join(SEQUENCE_KEYS)})")
    name = entry.get("name")
    if name is None or str(name).strip() == "":
        raise InputError(manifest, f"{where}: needs a name")
    name = str(name)
    where = f"sequence {name!r}"
    if not _NAME.match(name) or name == "models":
        raise InputError(manifest, f"{where}: a name is a folder name of letters, digits, '.', '_', '-' "
                                   "(not 'models')")
    d = dict(entry)
    if d.get("video") is not None:
        if d.get("frames") is not None:
            raise InputError(manifest, f"{where}: give frames or video, not both")
        d["frames"] = d.pop("video")
    for k in ("frames", "model", "camera"):
        if d.get(k) is None or str(d[k]).strip() == "":
            raise InputError(manifest, f"{where}: needs {k}")
    sources = [k for k in ("init", "clicks", "nav") if d.get(k) is not None]
    if len(sources) != 1:
        raise InputError(manifest, f"{where}: needs exactly one first-pose source: init (a pose file), clicks "
                                   f"or nav (got {', '.join(sources) or 'none'})")
    if d.get("points") is not None and d.get("clicks") is None:
        raise InputError(manifest, f"{where}: points pair with clicks")
    paths: dict[str, str] = {}
    for k in PATH_KEYS:
        v = d.get(k)
        if v is None or str(v).strip() == "":
            continue
        full = str((base / str(v)).resolve()) if not re.search(r"[*?\[%]", str(v)) else str(base / str(v))
        if not _exists(full):
            raise InputError(manifest, f"{where}: {k} {v} does not exist")
        paths[k] = full
    fps = d.get("fps")
    if fps is not None and fps != "":
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise InputError(manifest, f"{where}: fps needs a number, got {fps!r}") from None
        if not fps > 0 or fps == float("inf"):
            raise InputError(manifest, f"{where}: fps must be > 0, got {fps:g}")
    else:
        fps = None
    options = _stage_options(d.get("options"), base, where, manifest, command_of)
    return SequenceSpec(name=name, fps=fps, options=options, **paths)


def _read_entries(path: Path) -> tuple[dict[str, Any], list[Any]]:
    text = read_text(path, "manifest")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        rows = list(csv.DictReader(io.StringIO(text)))
        entries = []
        for r in rows:
            e: dict[str, Any] = {}
            for k, v in r.items():
                if k is None:
                    raise InputError(path, f"row {len(entries) + 2}: more cells than columns")
                k, v = k.strip(), (v or "").strip()
                if v == "":
                    continue
                if "." in k:
                    e.setdefault("options", {})[k] = _csv_value(v)
                else:
                    e[k] = v
            entries.append(e)
        return {}, entries
    if suffix not in (".yaml", ".yml", ".json"):
        raise InputError(path, f"unknown manifest format {path.suffix or '(no suffix)'}: use .yaml, .yml, .json or .csv")
    from mst.core.config import parse_yaml

    data = parse_yaml(path, text)  # JSON is YAML too
    if isinstance(data, list):
        return {}, data
    if not isinstance(data, dict):
        raise InputError(path, "a manifest holds 'sequences' (a list) and optional 'defaults'")
    for k in data:
        if k not in ("defaults", "sequences"):
            raise InputError(path, f"unknown top-level key {k!r} (known: defaults, sequences)")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise InputError(path, "defaults must be a mapping of sequence keys")
    for k in defaults:
        if k not in SEQUENCE_KEYS or k == "name":
            raise InputError(path, f"defaults: unknown key {k!r}")
    seqs = data.get("sequences")
    if not isinstance(seqs, list):
        raise InputError(path, "sequences must be a list")
    return defaults, seqs


def _csv_value(v: str) -> Any:
    """A CSV option cell as YAML reads a scalar (``true``, ``8``, ``[1, 2]``); text otherwise."""
    import yaml

    from mst.core.config import load_yaml_text

    try:
        return load_yaml_text(v)
    except yaml.YAMLError:
        return v


def load_manifest(path: str | os.PathLike, command_of: CommandOf) -> Manifest:
    """Read and check a manifest; raises :class:`InputError` naming the manifest and the problem.

    ``command_of(stage)`` is the click command of a stage (``mst.cli.batch.stage_command``): the
    options are checked against it (this package does not import the command layer)."""
    p = Path(path)
    defaults, entries = _read_entries(p)
    if not entries:
        raise InputError(p, "no sequences")
    base = p.resolve().parent
    seqs = [_sequence(_merge(defaults, e) if isinstance(e, Mapping) else e, i, base, p, command_of)
            for i, e in enumerate(entries)]
    seen: dict[str, int] = {}
    for i, s in enumerate(seqs):
        if s.name in seen:
            raise InputError(p, f"sequences {seen[s.name] + 1} and {i + 1} are both named {s.name!r}")
        seen[s.name] = i
    return Manifest(p, seqs)
