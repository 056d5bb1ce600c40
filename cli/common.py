"""Shared click options and output helpers for every ``mst`` subcommand (light imports only)."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import click


class FiniteFloat(click.FloatRange):
    """A float option that must be finite (NaN and inf refused) and optionally within a range.

    Bad values are reported by click as a problem of the option (``Invalid value for '--voxel'``),
    never as a problem of an input file.
    """

    name = "number"

    def __init__(self, *a, allow_inf: bool = False, **k):
        super().__init__(*a, **k)
        self.allow_inf = allow_inf

    def convert(self, value, param, ctx):
        rv = super().convert(value, param, ctx)
        if math.isnan(rv) or (math.isinf(rv) and not self.allow_inf):
            self.fail(f"{value!r} is not a {'number' if self.allow_inf else 'finite number'}", param, ctx)
        return rv


#: common option types: finite floats > 0 and >= 0, finite float of any sign
POSITIVE = FiniteFloat(min=0, min_open=True)
NON_NEGATIVE = FiniteFloat(min=0)
FINITE = FiniteFloat()


json_option = click.option("--json", "as_json", is_flag=True, help="Print a machine-readable JSON summary on stdout.")
quiet_option = click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary on stderr.")


def _finite_or_none(o: Any) -> Any:
    """``o`` with numpy values converted and every NaN/inf float replaced by None (JSON null)."""
    if hasattr(o, "tolist"):
        o = o.tolist()
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite_or_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_none(v) for v in o]
    if hasattr(o, "__fspath__"):
        return str(o)
    return o


def emit_json(obj: Any) -> None:
    """Write ``obj`` as one JSON document on stdout (numpy scalars/arrays converted).

    Strict JSON: a NaN/inf value (a statistic of nothing, an unbounded setting) is written as null,
    never as the invalid tokens ``NaN``/``Infinity`` that ``jq`` and other parsers reject.
    """

    def default(o: Any) -> Any:
        if hasattr(o, "tolist"):
            return o.tolist()
        if hasattr(o, "__fspath__"):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o).__name__}")

    try:
        text = json.dumps(obj, indent=2, default=default, allow_nan=False)
    except ValueError:  # a non-finite float somewhere: nulls instead
        text = json.dumps(_finite_or_none(obj), indent=2, default=default, allow_nan=False)
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def info(msg: str, quiet: bool = False) -> None:
    """A human message on stderr."""
    if not quiet:
        click.echo(msg, err=True)


def stderr_console():
    """A rich console on stderr (rich is imported lazily: it is not needed for --help)."""
    from rich.console import Console

    return Console(stderr=True)


@contextmanager
def progress_bar(total: int | None, description: str, quiet: bool = False) -> Iterator[Any]:
    """A rich progress bar on stderr; yields ``advance(n=1)``. Silent with ``quiet``; erased on an error."""
    if quiet:
        yield lambda n=1: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*cols, console=stderr_console(), transient=False) as prog:
        task = prog.add_task(description, total=total)
        try:
            yield lambda n=1: prog.advance(task, n)
        except BaseException:
            # an error (a corrupt frame found on the way): the bar is removed, the error line stays alone
            prog.live.transient = True
            raise


def print_table(title: str, columns: Iterable[str], rows: Iterable[Iterable[Any]], quiet: bool = False) -> None:
    """A rich table on stderr."""
    if quiet:
        return
    from rich.table import Table

    t = Table(title=title)
    for c in columns:
        t.add_column(str(c), justify="right")
    for r in rows:
        t.add_row(*[str(x) for x in r])
    stderr_console().print(t)


# -- configuration: --config FILE, --preset NAME, --set KEY=VALUE, shared by every command -------

def config_options(presets: bool = False):
    """Decorator adding ``--config FILE`` (``.yaml``/``.json``), ``--set KEY=VALUE`` (repeatable,
    dotted names) and, with ``presets``, ``--preset NAME`` to a command. Explicit options of the
    command override ``--set``, which overrides the file, which overrides the preset."""

    def deco(f):
        f = click.option("--show-config", is_flag=True, is_eager=True, expose_value=False, callback=_show_config,
                         help="List every setting of this command (dotted name, default, help), its "
                              "presets, and exit.")(f)
        f = click.option("--set", "set_values", multiple=True, metavar="KEY=VALUE",
                         help="Set one setting by its dotted name (e.g. slam.klt.fb_max_px=2); repeatable; "
                              "overrides --config. `mst <command> --show-config` lists them.")(f)
        f = click.option("--config", "config_file", type=click.Path(dir_okay=False), default=None,
                         help="Settings file (.yaml/.yml/.json), e.g. the 'config' block of an earlier "
                              "run's --json summary, to repeat it exactly.")(f)
        if presets:
            f = click.option("--preset", default=None, metavar="NAME",
                             help="Named settings preset (listed by --show-config).")(f)
        return f

    return deco


#: command path -> "module:ConfigClass" of the settings it takes (read by --show-config)
CONFIG_CLASSES: dict[str, str] = {}


def config_class(command_path: str):
    """The config class of ``command_path`` (``"mst track"``), or None."""
    import importlib

    spec = CONFIG_CLASSES.get(command_path)
    if spec is None:
        return None
    mod, _, attr = spec.partition(":")
    return getattr(importlib.import_module(mod), attr)


def _show_config(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if not value or ctx.resilient_parsing:
        return
    cls = config_class(ctx.command_path)
    if cls is None:
        click.echo(f"{ctx.command_path} has no settings beyond its options")
        ctx.exit(0)
    from mst.core.config import presets_of

    rows = cls.describe()
    width = max(len(r[0]) for r in rows)
    for name, _tp, default, help_ in rows:
        click.echo(f"{name:<{width}}  {json.dumps(default)!s:<12}  {help_}")
    presets = presets_of(cls)
    if presets:
        click.echo("\npresets (--preset NAME):")
        for n, doc in presets.items():
            click.echo(f"  {n}: {doc}")
    ctx.exit(0)


def parse_set_values(values: Iterable[str]) -> dict[str, Any]:
    """``["slam.klt.fb_max_px=2", "edges.passes=3"]`` -> ``{"slam.klt.fb_max_px": 2, "edges.passes": 3}``.

    Values are read as YAML scalars/lists (``2``, ``true``, ``null``, ``[8, 6]``; ``off`` and ``on``
    are words, as in YAML 1.2: :func:`mst.core.config.load_yaml_text`); a malformed item is a usage
    error naming ``--set``.
    """
    out: dict[str, Any] = {}
    for item in values:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise click.BadParameter(f"{item!r} is not KEY=VALUE", param_hint="'--set'")
        try:
            from mst.core.config import load_yaml_text

            val = load_yaml_text(raw) if raw.strip() else ""
        except Exception:  # noqa: BLE001 - any YAML problem: keep the text as a string
            val = raw
        out[key] = val
    return out


def build_config(cls, *, config_file=None, set_values: Iterable[str] = (), preset: str | None = None,
                 options: dict[str, Any] | None = None, flags: dict[str, str] | None = None,
                 section_name: str | None = None, base: dict[str, Any] | None = None):
    """The effective ``cls`` config of a command: defaults < ``base`` < preset < ``--config`` <
    ``--set`` < explicit ``options`` (dotted field -> value; ``None`` values are "not given").

    A :class:`~mst.errors.ConfigError` on a field that an option sets is reported under the
    option's name (``flags``: dotted field -> ``"--voxel"``), so the user reads the flag they typed.
    """
    from mst.core.config import resolve
    from mst.errors import ConfigError

    overrides = parse_set_values(set_values)
    overrides.update({k: v for k, v in (options or {}).items() if v is not None})
    try:
        return resolve(cls, preset=preset, file=config_file, section_name=section_name,
                       overrides=overrides, base=base)
    except ConfigError as e:
        flag = (flags or {}).get(e.field)
        if flag is not None and e.source is None and options and options.get(e.field) is not None:
            raise click.BadParameter(e.problem, param_hint=f"'{flag}'") from None
        raise


def verbosity_options(f):
    """``-q/--quiet`` (no progress, summary or notes on stderr) and ``-v/--verbose`` (debug notes)."""
    f = click.option("-v", "--verbose", count=True, help="More messages on stderr (-vv: debug).")(f)
    return f


def setup_logging(quiet: bool = False, verbose: int = 0, prog: str = "mst") -> None:
    """Route the library's ``logging`` messages (``mst.*`` loggers) to stderr as ``prog: note: ...``.

    Default level INFO (the notes a user should read: a derived setting, a skipped frame);
    ``quiet`` shows errors only, ``verbose`` DEBUG.
    """
    import logging

    class Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            kind = {logging.DEBUG: "debug", logging.INFO: "note", logging.WARNING: "warning"}.get(record.levelno, "error")
            click.echo(f"{prog}: {kind}: {record.getMessage()}", err=True)

    log = logging.getLogger("mst")
    for h in list(log.handlers):
        if getattr(h, "_mst_cli", False):
            log.removeHandler(h)
    h = Handler()
    h._mst_cli = True
    log.addHandler(h)
    log.propagate = False
    log.setLevel(logging.ERROR if quiet else (logging.DEBUG if verbose else logging.INFO))
