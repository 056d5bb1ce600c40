"""The ``mst`` command group.

Subcommands are loaded lazily (rasterio/flask style) so that ``mst --help`` and light commands never
import open3d, pycolmap or pymeshlab. Each subcommand module under :mod:`mst.cli` imports only click
and light helpers at module level; heavy libraries are imported inside the stage functions.
"""

from __future__ import annotations

import importlib
import sys
import warnings

import click

from mst import ConfigError, MstError, __version__
from mst.cpu import pin_blas_kernels

pin_blas_kernels()  # before anything loads numpy: the same BLAS kernels on every CPU (mst.cpu)

#: command name -> "module:attribute" (module relative to mst.cli)
COMMANDS: dict[str, str] = {
    "convert-model": "convert_model:convert_model",
    "synth": "synth:synth",
    "init": "init_pose:init_pose",
    "track": "track:track",
    "fuse": "fuse:fuse",
    "c2m": "c2m:c2m",
    "eval": "eval_cmd:eval_group",
    "nav": "nav:nav_group",
    "refine": "refine:refine",
    "batch": "batch:batch",
    "report": "report:report",
    "c2m-tiles": "c2m_tiles:c2m_tiles",
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        spec = COMMANDS.get(name)
        if spec is None:
            return None
        mod_name, attr = spec.split(":")
        try:
            mod = importlib.import_module(f"mst.cli.{mod_name}")
        except ModuleNotFoundError as e:  # a stage not built in this checkout
            if e.name == f"mst.cli.{mod_name}":
                return None
            raise
        return getattr(mod, attr)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "--version", prog_name="mst")
def cli() -> None:
    """mst: model-based survey tracking.

    \b
    Stages, chained through files:
      mst convert-model tin.obj -o bldg.wrl         TIN -> polygon model (.wrl/.cao/.obj)
      mst synth orbit --model bldg.obj -o seq/      synthetic video/RGB-D with ground truth
      mst init --model bldg.wrl --camera cam.json --clicks clicks.txt -o pose0.txt
      mst track video.mp4 --model bldg.wrl --camera cam.json --init pose0.txt -o traj.txt
      mst fuse --traj traj.txt --depth depth/ --camera cam.json -o cloud.ply
      mst c2m cloud.ply mesh.obj                    cloud-to-mesh statistics (Table 1)
      mst eval traj traj.txt gt.txt                 trajectory errors (ATE/RPE, dX dY dZ dyaw)
      mst nav fuse --traj traj.txt --nav nav.csv -o fused.txt   GPS/AHRS + vision fusion
      mst refine --traj traj.txt --model bldg.wrl --camera cam.json --depth depth/ -o refined.txt

    Results and --json summaries go to stdout, progress and messages to stderr.
    """


def _warning_line(w: warnings.WarningMessage) -> str:
    return f"{w.category.__name__}: {w.message}"


def _option_named(args: list[str], field: str) -> str | None:
    """The ``--option`` of the invoked (sub)command that carries config field ``field``, or None."""
    flag = "--" + field.replace("_", "-")
    try:
        cmd = cli.get_command(None, args[0]) if args else None
        if isinstance(cmd, click.Group) and len(args) > 1:
            cmd = cmd.get_command(None, args[1])
    except Exception:  # noqa: BLE001 - only a nicer name; the message stands without it
        return None
    if cmd is None:
        return None
    opts = {o for p in cmd.params for o in getattr(p, "opts", ())}
    return flag if flag in opts else None


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: one clean error line and exit code 1 for every error.

    The rule: success exits 0; EVERY error exits 1 -- bad input (:class:`mst.InputError`), bad
    usage (a missing option, an invalid choice, a folder given as a file, an unknown command) and
    an output that cannot be written; an interrupt (Ctrl-C) exits 130, a closed pipe 141. Python
    warnings (e.g. numpy ``RuntimeWarning``) raised while a command runs are held back: after an
    error only the error line is printed; after success each distinct warning is printed once.
    """
    prog = "mst"
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] in COMMANDS:
        prog = f"mst {args[0]}"
        if args[0] == "eval" and len(args) > 1 and not args[1].startswith("-"):
            prog = f"mst eval {args[1]}"
    code = 0
    with warnings.catch_warnings(record=True) as caught:  # the filters in force decide what is recorded
        try:
            rv = cli.main(args=args, prog_name="mst", standalone_mode=False)
            code = rv if isinstance(rv, int) else 0
        except ConfigError as e:
            # a setting the library refused: named by the option that set it, when the command has one
            flag = None if e.source else _option_named(args, e.field)
            click.echo(f"{prog}: error: {flag}: {e.problem}" if flag else f"{prog}: error: {e}", err=True)
            code = 1
        except MstError as e:
            click.echo(f"{prog}: error: {e}", err=True)
            code = 1
        except click.exceptions.Abort:
            click.echo(f"{prog}: interrupted", err=True)
            code = 130
        except click.ClickException as e:  # usage errors: click's own code is 2, the rule is 1
            msg = e.format_message().replace("\n", " ")
            click.echo(f"{prog}: error: {msg}", err=True)
            code = 1
        except click.exceptions.Exit as e:
            code = e.exit_code
        except KeyboardInterrupt:
            click.echo(f"{prog}: interrupted", err=True)
            code = 130
        except BrokenPipeError:
            code = 141
        except (IsADirectoryError, NotADirectoryError, PermissionError, FileNotFoundError) as e:
            # an OS-level refusal on a named file that a reader did not turn into an InputError
            where = f"{e.filename}: " if e.filename else ""
            click.echo(f"{prog}: error: {where}{e.strerror or e}", err=True)
            code = 1
    if code == 0:
        for text in dict.fromkeys(_warning_line(w) for w in caught):
            click.echo(f"{prog}: warning: {text}", err=True)
    sys.exit(code)


if __name__ == "__main__":
    main()
