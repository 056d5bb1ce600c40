"""What a run folder holds: the summaries, tables and images ``mst report`` puts on the page.

A *run folder* is the output of one chain (the demo's ``demo-out/``, or one sequence of a batch):
``c2m.json``, ``eval.json``, ``traj.txt``/``traj.csv``, ``traj.json``, ``fuse.json``, ``init.json``,
``convert-model.json``, images written by ``--plot`` (``c2m_hist.png``, ``eval_traj.png``), the exact
commands: ``commands.sh`` (the run log ``make demo`` writes: one shell-quoted command line per line, in
the order run, ``> FILE`` where its stdout went) or, for a batch, ``batch-state.json``. A *batch folder* holds run
folders (each with a ``batch-state.json``) and ``models/``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mst import InputError

SUMMARIES = ("convert-model", "init", "track", "fuse", "c2m", "eval")


@dataclass
class RunFiles:
    folder: Path
    name: str
    summaries: dict[str, dict[str, Any]] = field(default_factory=dict)  #: stage -> its --json summary
    commands: dict[str, list[str]] = field(default_factory=dict)        #: stage -> the exact argv (no "mst")
    command_lines: list[str] = field(default_factory=list)              #: commands.sh, in the order run
    states: dict[str, dict[str, Any]] = field(default_factory=dict)     #: stage -> batch state entry
    traj: Path | None = None
    traj_csv: Path | None = None
    frames: str | None = None
    model: str | None = None
    camera: str | None = None
    fps: float | None = None

    def file(self, name: str) -> Path | None:
        p = self.folder / name
        return p if p.is_file() else None


def _json(p: Path) -> dict[str, Any] | None:
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def resolve_path(text: str | None, folder: Path) -> Path | None:
    """A path recorded in a summary: as written (relative to the current folder), else inside ``folder``."""
    if not text:
        return None
    p = Path(text)
    for cand in (p, folder / p, folder / p.name):
        if cand.exists():
            return cand
    return None


def _arg(argv: list[str], flag: str) -> str | None:
    return argv[argv.index(flag) + 1] if flag in argv and argv.index(flag) + 1 < len(argv) else None


def read_run(folder: Path, frames: str | None = None, model: str | None = None,
             camera: str | None = None, fps: float | None = None) -> RunFiles:
    """The files of one run folder (missing ones are None / absent)."""
    run = RunFiles(folder, folder.name)
    for stage in SUMMARIES:
        d = _json(folder / f"{stage}.json")
        if d is not None:
            run.summaries[stage] = d
    tj = _json(folder / "traj.json")
    if tj is not None:
        run.summaries.setdefault("track", tj)
    state = _json(folder / "batch-state.json")
    for stage, entry in ((state or {}).get("stages") or {}).items():
        run.states[stage] = entry
        if entry.get("argv"):
            run.commands[stage] = list(entry["argv"])
    log = folder / "commands.sh"
    if log.is_file():
        run.command_lines, argvs = read_command_log(log)
        for argv in argvs:
            run.commands.setdefault(argv[0], argv)  # the batch state's record first; else the first such command
    run.traj = run.file("traj.txt")
    run.traj_csv = run.file("traj.csv")
    argv = run.commands.get("track", [])
    run.frames = frames or (argv[1] if len(argv) > 1 else None)
    run.model = model or _arg(argv, "--model")
    run.camera = camera or _arg(argv, "--camera")
    f = fps if fps is not None else _arg(argv, "--fps")
    run.fps = float(f) if f is not None else None
    return run


def read_command_log(path: Path) -> tuple[list[str], list[list[str]]]:
    """A run log: (its command lines as written, the argv after ``mst`` of each mst command, without its
    ``> FILE`` redirection). Blank lines and ``#`` comments are skipped; an unparsable line is shown only."""
    import shlex

    lines, argvs = [], []
    for line in path.read_text(errors="replace").splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        lines.append(line)
        try:
            tok = shlex.split(line)
        except ValueError:
            continue
        if ">" in tok:
            tok = tok[: tok.index(">")]
        if len(tok) > 1 and Path(tok[0]).name == "mst":
            argvs.append(tok[1:])
    return lines, argvs


def is_run(folder: Path) -> bool:
    return any((folder / n).is_file() for n in ("traj.txt", "c2m.json", "eval.json", "batch-state.json",
                                                 "commands.sh"))


def find_runs(root: str | os.PathLike) -> tuple[list[RunFiles], bool]:
    """(the run folders of ``root``, whether it is a batch folder). ``root`` itself or its sub-folders."""
    root = Path(root)
    if not root.exists():
        raise InputError(root, "run folder does not exist")
    if not root.is_dir():
        raise InputError(root, "not a folder (give a run folder or a batch folder)")
    subs = sorted(p for p in root.iterdir() if p.is_dir() and p.name != "models" and (p / "batch-state.json").is_file())
    if subs:
        return [read_run(p) for p in subs], True
    if is_run(root):
        return [read_run(root)], False
    raise InputError(root, "holds no run: no traj.txt, c2m.json, eval.json or batch sequence folders")
