"""CLI basics: --help/--version, lazy imports (start-up), one-line errors, atomic outputs."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mst import InputError, atomic_outputs
from mst.cli.main import COMMANDS

HEAVY = ("open3d", "pycolmap", "pymeshlab", "trimesh", "matplotlib", "scipy", "cv2")


def test_version_and_help(mst):
    r = mst("--version")
    assert r.stdout.strip() == "mst, version 0.1.0"
    r = mst("--help")
    for name in COMMANDS:
        assert name in r.stdout, f"{name} missing from mst --help"


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_has_help_with_example_and_imports_no_heavy_library(name):
    code = (
        "import sys, io, contextlib\n"
        "from mst.cli.main import cli\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        f"    cli.main([{name!r}, '--help'], prog_name='mst', standalone_mode=False)\n"
        f"heavy = [m for m in {HEAVY!r} if m in sys.modules]\n"
        "print(repr(heavy)); print(buf.getvalue())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    heavy, _, help_text = r.stdout.partition("\n")
    assert heavy == "[]", f"`mst {name} --help` imported {heavy}"
    assert "Usage: mst" in help_text
    assert f"mst {name}" in help_text.split("Options:")[0].split("Usage:", 1)[1], "no example in --help"


def test_unknown_command_is_one_error_line(mst):
    r = mst("no-such-command", check=False)
    assert r.returncode == 1  # every error exits 1 (README), click's own usage code 2 included
    assert r.stderr.strip().count("\n") == 0 and "error" in r.stderr


def test_atomic_outputs_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.csv"
    with pytest.raises(RuntimeError):
        with atomic_outputs(a, b) as (ta, tb):
            ta.write_text("x")
            raise RuntimeError("writer failed")
    assert not a.exists() and not b.exists() and list(tmp_path.iterdir()) == []
    with atomic_outputs(a, b, None) as (ta, tb, tn):
        assert tn is None and ta.suffix == ".txt" and tb.suffix == ".csv"
        ta.write_text("x")  # b is optional and not written
    assert a.read_text() == "x" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with pytest.raises(InputError, match="output folder does not exist"):
        with atomic_outputs(tmp_path / "nope" / "x.txt"):
            pass
