"""The README documents only what exists: every `mst <cmd> --opt` in its code is an option of that
command (checked against the command's --help, run in-process with click's CliRunner), and every
`mst <cmd> ... --json | jq .KEY` names a key of that command's JSON summary (the command is run on
the small fixture set of tests/bad_input_fixtures.py)."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
from bad_input_fixtures import build, run_cli
from click.testing import CliRunner

from mst.cli.main import COMMANDS, cli

README = Path(__file__).resolve().parents[1] / "README.md"


def _code_commands(text: str) -> list[str]:
    """`mst ...` command lines of the README: indented code blocks (with `\\` continuations) and inline
    code spans; comments after `#` dropped."""
    cmds: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("    ") and ln.strip():
            full = ln.strip()
            while full.endswith("\\") and i + 1 < len(lines):
                i += 1
                full = full[:-1] + " " + lines[i].strip()
            cmds += _mst_parts(full)
        else:
            for span in re.findall(r"`([^`]+)`", ln):
                cmds += _mst_parts(span)
        i += 1
    return cmds


def _mst_parts(s: str) -> list[str]:
    """Every `mst <known command> ...` inside a line (also after `# =`), cut at the next comment."""
    out = []
    names = "|".join(map(re.escape, COMMANDS))
    for m in re.finditer(r"(?:^|[\s=;(])mst ((?:" + names + r")\b[^#]*)", s):
        out.append(m.group(1).strip())
    return out


def _options(cmd: str) -> tuple[str, list[str]]:
    """(command path such as 'eval traj', options used) of a documented command line."""
    toks = shlex.split(cmd.split("|")[0].replace("...", " "))
    path = toks[0]
    rest = toks[1:]
    if path in ("eval", "nav") and rest and not rest[0].startswith("-"):  # command groups
        path, rest = f"{path} {rest[0]}", rest[1:]
    return path, [t.split("=", 1)[0] for t in rest if re.match(r"^--?[a-zA-Z]", t)]


DOCUMENTED = _code_commands(README.read_text())


def test_readme_has_commands():
    names = {_options(c)[0].split()[0] for c in DOCUMENTED}
    assert set(COMMANDS) <= names, f"README shows no example of {set(COMMANDS) - names}"


_HELP: dict[str, str] = {}


def _help(path: str) -> str:
    if path not in _HELP:
        r = CliRunner().invoke(cli, [*path.split(), "--help"], prog_name="mst")
        assert r.exit_code == 0, r.output
        _HELP[path] = r.output
    return _HELP[path]


@pytest.mark.parametrize("cmd", DOCUMENTED)
def test_documented_options_exist(cmd):
    path, opts = _options(cmd)
    text = _help(path)
    for o in opts:
        found = re.search(r"(?<![\w-])" + re.escape(o) + r"(?![\w-])", text)
        assert found, f"README: `mst {cmd}`: {o} is not an option of `mst {path}`"


JQ = [(m.group(1), m.group(2)) for c in DOCUMENTED for m in [re.search(r"^(\S+).*--json \| jq \.(\w+)", c)] if m]


def test_readme_documents_jq_keys():
    assert JQ, "the README's `--json | jq .KEY` examples were not found"


@pytest.mark.parametrize("cmd,key", JQ)
def test_documented_json_keys_exist(cmd, key, tmp_path):
    f = build(tmp_path / "in")
    o = tmp_path / "out"
    o.mkdir()
    args = {
        "track": ["track", f["frames"], "--model", f["model"], "--camera", f["camera"], "--init", f["pose"],
                  "-o", o / "traj.txt", "--slam", "off"],
        "c2m": ["c2m", f["cloud"], f["model"]],
        "fuse": ["fuse", "--traj", f["traj"], "--depth", f["depth"], "--camera", f["camera"], "-o", o / "c.ply"],
        "init": ["init", "--model", f["model"], "--camera", f["camera"], "--clicks", f["clicks"], "-o", o / "p.txt"],
        "convert-model": ["convert-model", f["model"], "-o", o / "m.wrl"],
    }[cmd]
    code, out, err = run_cli(args + ["--json", "-q"])
    assert code == 0, err
    assert key in json.loads(out), f"README: `mst {cmd} ... --json | jq .{key}`: no key {key!r}"
