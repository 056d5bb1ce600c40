"""One stage of a batch, as run inside a dask task: skip it when fresh, else run its ``mst`` command.

The command runs in-process through the click group (``standalone_mode=False``; the command layer
gives the function that does it), its ``--json
summary captured from stdout and kept in the stage's summary file (atomically). The result is a
plain dict (it travels back to the client): ``status`` (ok, skipped, failed, blocked), the one-line
``error``, ``elapsed_s`` and the new state ``entry`` that the client records. A worker never writes
the state file, and a stage whose predecessor failed is ``blocked`` without running.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from mst.eval.batch.plan import Stage
from mst.eval.batch.state import HashCache, is_fresh, output_hashes, stage_key

#: argv -> (exit code, stdout, one-line error or None)
CallMst = Callable[[tuple[str, ...]], tuple[int, str, "str | None"]]


def _result(stage: Stage, status: str, **kw: Any) -> dict[str, Any]:
    return {"id": stage.id, "unit": stage.unit, "stage": stage.name, "status": status, "error": None,
            "elapsed_s": 0.0, "entry": None, **kw}


def check_fresh(stage: Stage, entry: dict | None) -> tuple[bool, str, HashCache]:
    """(fresh, key, the hashes used) for ``stage`` against its recorded ``entry``."""
    cache: HashCache = dict((entry or {}).get("files") or {})
    used: HashCache = {}
    key = stage_key(stage.argv, stage.inputs, cache, used)
    return is_fresh(entry, key, cache, used), key, used


def known_outcome(stage: Stage, entry: dict | None, retry_failed: bool = False) -> dict[str, Any] | None:
    """The result of ``stage`` without running it, or None: ``skipped`` when fresh; ``failed`` (the
    recorded error, ``cached``) when it failed with the same command line and inputs (unless
    ``retry_failed``)."""
    fresh, key, _ = check_fresh(stage, entry)
    if fresh:
        return _result(stage, "skipped", entry=entry)
    if not retry_failed and entry and entry.get("status") == "failed" and entry.get("key") == key:
        return _result(stage, "failed", error=entry.get("error"), cached=True)
    return None


def run_stage(stage: Stage, entry: dict | None, retry_failed: bool, call: CallMst,
              *upstream: dict[str, Any]) -> dict[str, Any]:
    """The dask task of one stage (``upstream``: the results of the stages it needs). ``call(argv)``
    runs the ``mst`` command in-process: ``(exit code, stdout, the one-line error or None)``; it is
    the command layer's :func:`mst.cli.batch.call_mst` (this package does not import that layer)."""
    bad = [u for u in upstream if u["status"] in ("failed", "blocked")]
    if bad:
        return _result(stage, "blocked", error=bad[0]["error"], cause=bad[0]["id"])
    t0 = time.perf_counter()
    known = known_outcome(stage, entry, retry_failed)
    if known is not None:
        return known
    _, key, used = check_fresh(stage, entry)
    code, stdout, error = call(stage.argv)
    elapsed = time.perf_counter() - t0
    if code != 0:
        return _result(stage, "failed", error=error, elapsed_s=elapsed,
                       entry={"status": "failed", "key": key, "error": error, "files": used})
    if stage.summary is not None:
        from mst import atomic_output

        with atomic_output(stage.summary) as tmp:
            tmp.write_text(stdout)
    cache = dict(used)
    outs = output_hashes((*stage.outputs, *([stage.summary] if stage.summary else [])), cache, used)
    new = {"status": "ok", "key": key, "argv": list(stage.argv), "outputs": outs, "files": used,
           "elapsed_s": round(elapsed, 3), "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    return _result(stage, "ok", elapsed_s=elapsed, entry=new)
