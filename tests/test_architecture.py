"""The package structure keeps its promises (README "Architecture"): dependencies point one way,
every package says what it holds and may import, and no module grows past ~500 lines without a
reason in its docstring.

Read from the source with :mod:`ast` (no imports executed), so a violation names the file and line.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: layer of each top-level package; a module may import its own layer and lower ones only
#: (mst.errors and the mst top-level helpers are the base every layer may use)
LAYERS = {"core": 0, "meshtools": 1, "pipeline": 2, "eval": 3, "cli": 4}
#: the benchmarks sit on top of everything (they time whole commands); nothing imports them
BENCH = "eval.bench"

#: a long module must say why in its docstring with this phrase
LONG_REASON = "Longer than 500 lines"
MAX_LINES = 550


def _modules() -> list[Path]:
    out = []
    for pkg in LAYERS:
        out += sorted((ROOT / pkg).rglob("*.py"))
    return out


def _dotted(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, imported mst module without the ``mst.`` prefix) of every import in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = _dotted(path).split(".")
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name[4:]) for a in node.names if a.name.startswith("mst.")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = me if is_pkg else me[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
                names = [mod] if node.module else [f"{mod}.{a.name}" for a in node.names]
                out += [(node.lineno, n) for n in names]
            elif node.module and node.module.startswith("mst."):
                out.append((node.lineno, node.module[4:]))
    return out


def _layer(dotted: str) -> int | None:
    return LAYERS.get(dotted.split(".")[0])


def test_dependencies_point_one_way():
    bad = []
    for path in _modules():
        me = _dotted(path)
        mine = _layer(me)
        for line, mod in _imports(path):
            if mod.startswith(BENCH) and not me.startswith(BENCH):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports the benchmarks ({mod})")
                continue
            theirs = _layer(mod)
            if me.startswith(BENCH) or theirs is None or mine is None:
                continue
            if theirs > mine:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({me}) imports the higher layer {mod}")
    assert not bad, "\n".join(bad)


def test_every_package_docstring_says_what_it_holds_and_may_import():
    bad = []
    for init in sorted(p for pkg in LAYERS for p in (ROOT / pkg).rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        if not doc or "import" not in doc.lower():
            bad.append(str(init.relative_to(ROOT)))
    assert not bad, "package docstrings without what they hold / may import: " + ", ".join(bad)


def test_long_modules_state_their_reason():
    bad = []
    for path in _modules():
        n = len(path.read_text().splitlines())
        if n > MAX_LINES:
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            if LONG_REASON not in doc:
                bad.append(f"{path.relative_to(ROOT)} ({n} lines)")
    assert not bad, f"modules over {MAX_LINES} lines without '{LONG_REASON}: ...' in the docstring: " + ", ".join(bad)


@pytest.mark.parametrize("pkg", ["core"])
def test_the_foundation_imports_no_stage(pkg):
    """mst.core is the foundation: numpy/OpenCV/stdlib and mst.errors only (mst top-level helpers too)."""
    bad = []
    for path in sorted((ROOT / pkg).rglob("*.py")):
        for line, mod in _imports(path):
            if not (mod.startswith("core") or mod == "errors"):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports mst.{mod}")
    assert not bad, "\n".join(bad)
