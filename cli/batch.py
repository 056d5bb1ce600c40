"""``mst batch``: many sequences through the whole chain as a dask.distributed task graph, resumable."""

from __future__ import annotations

import contextlib
import io
import warnings
from pathlib import Path

import click

from mst import InputError
from mst.cli.common import (
    CONFIG_CLASSES,
    build_config,
    config_options,
    emit_json,
    json_option,
    print_table,
    quiet_option,
    setup_logging,
    stderr_console,
    verbosity_options,
)

CONFIG_CLASSES["mst batch"] = "mst.eval.batch.config:BatchConfig"
FLAGS = {"workers": "--workers", "scheduler": "--scheduler"}


def stage_command(stage: str) -> click.Command:
    """The click command of a batch stage (``eval`` is ``mst eval traj``), loaded lazily."""
    from mst.cli.main import cli
    from mst.eval.batch.manifest import STAGE_COMMANDS

    words = STAGE_COMMANDS[stage]
    cmd = cli.get_command(None, words[0])
    for w in words[1:]:
        cmd = cmd.get_command(None, w)
    return cmd


def call_mst(argv: tuple[str, ...]) -> tuple[int, str, str | None]:
    """Run ``mst ARGV`` in this process: (exit code, stdout, the one-line error or None).

    The error line is the one ``mst`` itself prints (``mst track: error: ...``); tasks run one at a
    time per worker process (stdout is redirected for the call).
    """
    from mst import MstError
    from mst.cli.main import cli

    prog = "mst " + " ".join(argv[:2] if argv[0] == "eval" else argv[:1])
    buf = io.StringIO()
    code, error = 0, None
    with warnings.catch_warnings(), contextlib.redirect_stdout(buf):
        warnings.simplefilter("ignore")
        try:
            rv = cli.main(args=list(argv), prog_name="mst", standalone_mode=False)
            code = rv if isinstance(rv, int) else 0
        except MstError as e:
            code, error = 1, f"{prog}: error: {e}"
        except click.exceptions.Exit as e:
            code = e.exit_code
        except click.ClickException as e:
            code, error = 1, f"{prog}: error: {e.format_message()}".replace("\n", " ")
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except Exception as e:
            # a bug or an unforeseen input problem: reported as one line, the other sequences go on
            code, error = 1, f"{prog}: error: {type(e).__name__}: {e}".replace("\n", " ")
    if code != 0 and error is None:
        error = f"{prog}: error: exit code {code}"
    return code, buf.getvalue(), error


class _Progress:
    """One rich progress bar per stage on stderr (ok + skipped + failed + blocked of its total)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.prog = None
        self.tasks: dict[str, int] = {}

    def plan(self, plan, skipped) -> None:
        if self.quiet:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        from mst.eval.batch.manifest import STAGES

        self.prog = Progress(TextColumn("[bold]{task.description:<14}"), BarColumn(), MofNCompleteColumn(),
                             TextColumn("{task.fields[note]}"), TimeElapsedColumn(), console=stderr_console())
        for name in STAGES:
            n = sum(st.name == name for st in plan)
            if n:
                self.tasks[name] = self.prog.add_task(name, total=n, note="")
        self.prog.start()

    def result(self, stage, res) -> None:
        if self.prog is None:
            return
        task = self.tasks[stage.name]
        t = self.prog.tasks[task]
        counts = dict(t.fields.get("counts", {}))
        counts[res["status"]] = counts.get(res["status"], 0) + 1
        note = " ".join(f"{k} {v}" for k, v in sorted(counts.items()))
        self.prog.update(task, advance=1, note=note, counts=counts)

    def stop(self) -> None:
        if self.prog is not None:
            self.prog.stop()


def _cell(r: dict | None) -> str:
    if r is None:
        return "-"
    if r["status"] == "ok":
        return f"ok {r['elapsed_s']:.1f}s"
    return r["status"]


@click.command("batch")
@click.argument("manifest", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder: one folder per sequence (and models/ for the converted models).")
@click.option("--workers", type=int, default=None, help="Worker processes of the local cluster [default: 2].")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on an existing dask cluster, e.g. tcp://host:8786 (its workers must see the same "
                   "files and have mst installed).")
@click.option("--retry-failed", is_flag=True, default=None,
              help="Run again the stages that failed with unchanged inputs (default: report their recorded error).")
@config_options()
@json_option
@quiet_option
@verbosity_options
def batch(manifest, out, workers, scheduler, retry_failed, config_file, set_values, as_json, quiet, verbose):
    """Run every sequence of MANIFEST (YAML or CSV) through the chain, as a dask task graph.

    \b
    Per sequence, in OUT/<name>/: init (clicks, a pose file or nav) -> track -> fuse (with depth)
    -> c2m (with a reference mesh) -> eval traj (with a ground truth); convert-model runs once per
    model (OUT/models/). The stages run as tasks on a dask LocalCluster (--workers) or an existing
    cluster (--scheduler), each calling the mst command in-process. Resumable: a stage whose command
    line and input contents did not change since it finished is skipped (content hashes in
    OUT/<name>/batch-state.json). A failing sequence is reported with its one-line error and the
    others go on; the exit code is then 1.

    \b
    Examples:
      mst batch flights.yaml -o runs/
      mst batch flights.csv -o runs/ --workers 4 --json > runs/batch.json
      mst batch flights.yaml -o runs/ --scheduler tcp://10.0.0.5:8786

    See README (mst batch) for the manifest's keys and options.
    """
    setup_logging(quiet, verbose, "mst batch")
    from mst.eval.batch.config import BatchConfig
    from mst.eval.batch.manifest import load_manifest
    from mst.eval.batch.runner import run_batch

    cfg = build_config(BatchConfig, config_file=config_file, set_values=set_values, section_name="batch",
                       options={"workers": workers, "scheduler": scheduler, "retry_failed": retry_failed},
                       flags=FLAGS)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output folder is a file")
    m = load_manifest(manifest, stage_command)
    progress = _Progress(quiet)
    try:
        res = run_batch(m, out, call_mst, cfg, on_result=progress.result, on_plan=progress.plan)
    finally:
        progress.stop()
    rows = []
    for s in res.sequences:
        rows.append([s.name, *[_cell(s.stages.get(n)) for n in ("init", "track", "fuse", "c2m", "eval")],
                     s.status])
    print_table(f"mst batch: {len(res.sequences) - len(res.failed)} of {len(res.sequences)} sequences ok "
                f"({res.elapsed_s:.1f} s)", ["sequence", "init", "track", "fuse", "c2m", "eval", "result"],
                rows, quiet)
    if as_json:
        emit_json(res.to_json())
    if res.failed:
        for s in res.failed:
            click.echo(f"mst batch: {s.name}: {s.error}", err=True)
        click.echo(f"mst batch: error: {len(res.failed)} of {len(res.sequences)} sequences failed", err=True)
        return 1
    return 0
