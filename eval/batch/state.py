"""Content hashes and the batch state file (what each finished stage read and wrote).

A stage is *fresh* (skipped) when the hash of its command line and of the contents of every file it
reads equals the one recorded when it last finished, and every output it wrote is still there with
the content recorded then. File hashes are SHA-256 of the bytes; a folder's hash covers the names
and hashes of all its files. The recorded ``(size, mtime_ns)`` of each file lets an unchanged file
skip re-hashing (a touched but unchanged file is hashed again and found equal).

One state file per folder (``OUT/<sequence>/batch-state.json``, ``OUT/models/<model>/...``), written
by the batch's client only (atomically), never by the workers.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

STATE_NAME = "batch-state.json"
STATE_VERSION = 1

#: path -> [size, mtime_ns, sha256]
HashCache = dict[str, list]


def _file_hash(path: str, cache: HashCache, used: HashCache) -> str:
    st = os.stat(path)
    hit = cache.get(path)
    if hit is not None and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
        digest = hit[2]
    else:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        digest = h.hexdigest()
    used[path] = [st.st_size, st.st_mtime_ns, digest]
    return digest


def _expand(path: str) -> list[str]:
    """The files a path stands for: itself, a folder's files (recursively), or a glob/printf pattern's."""
    if os.path.isfile(path):
        return [path]
    if os.path.isdir(path):
        return sorted(str(p) for p in Path(path).rglob("*") if p.is_file())
    if any(c in path for c in "*?[") or re.search(r"%0?\d*d", path):
        return sorted(p for p in glob.glob(re.sub(r"%0?\d*d", "*", path)) if os.path.isfile(p))
    return []


def content_hash(path: str, cache: HashCache, used: HashCache) -> str | None:
    """SHA-256 of a file, or of a folder's/pattern's (name, hash) list; None when nothing is there."""
    files = _expand(path)
    if not files:
        return None
    if files == [path]:
        return _file_hash(path, cache, used)
    h = hashlib.sha256()
    root = path if os.path.isdir(path) else ""
    for f in files:
        h.update(os.path.relpath(f, root).encode() if root else f.encode())
        h.update(b"\0")
        h.update(_file_hash(f, cache, used).encode())
    return h.hexdigest()


def stage_key(argv: Iterable[str], inputs: Iterable[str], cache: HashCache, used: HashCache) -> str:
    """The hash that decides a rerun: the command line and the content of every input."""
    from mst import __version__

    h = hashlib.sha256(json.dumps({"mst": __version__, "argv": list(argv)}).encode())
    for p in inputs:
        h.update(b"\0" + p.encode() + b"=" + str(content_hash(p, cache, used)).encode())
    return h.hexdigest()


def output_hashes(outputs: Iterable[str], cache: HashCache, used: HashCache) -> dict[str, str | None]:
    return {p: content_hash(p, cache, used) for p in outputs}


def is_fresh(entry: dict[str, Any] | None, key: str, cache: HashCache, used: HashCache) -> bool:
    """True when ``entry`` (the stage's recorded state) finished with ``key`` and its outputs are unchanged."""
    if not entry or entry.get("status") != "ok" or entry.get("key") != key:
        return False
    recorded = entry.get("outputs") or {}
    return all(h is None or content_hash(p, cache, used) == h for p, h in recorded.items())


def load_state(folder: Path) -> dict[str, Any]:
    """The state of a folder (``{"stages": {name: entry}}``); empty when absent or unreadable."""
    p = Path(folder) / STATE_NAME
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError):
        return {"version": STATE_VERSION, "stages": {}}
    if not isinstance(data, dict) or data.get("version") != STATE_VERSION or not isinstance(data.get("stages"), dict):
        return {"version": STATE_VERSION, "stages": {}}
    return data


def save_state(folder: Path, state: dict[str, Any]) -> None:
    from mst import atomic_output

    with atomic_output(Path(folder) / STATE_NAME) as tmp:
        tmp.write_text(json.dumps(state, indent=1, sort_keys=True) + "\n")
