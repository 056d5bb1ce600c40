"""The batch client: plan, skip what is fresh, run the rest as a dask.distributed graph, record, summarise.

:func:`run_batch` takes a checked :class:`~mst.eval.batch.manifest.Manifest` and returns a typed
:class:`BatchResult`. Stages whose inputs and outputs are unchanged since they last finished are
skipped here, without a cluster; the others go to a ``LocalCluster`` (``workers`` processes) or to
the scheduler at ``scheduler`` as one task each, depending on the futures of the stages they need.
The client writes each unit's state file as its stages finish, so an interrupted batch resumes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mst.errors import MstError
from mst.eval.batch.config import BatchConfig
from mst.eval.batch.execute import CallMst, _result, known_outcome, run_stage
from mst.eval.batch.manifest import STAGES, Manifest
from mst.eval.batch.plan import Stage, build_plan
from mst.eval.batch.state import load_state, save_state

log = logging.getLogger(__name__)


class SchedulerError(MstError):
    """The scheduler address cannot be reached."""


@dataclass
class SequenceResult:
    name: str
    folder: str
    status: str                         #: ok (every stage ok or skipped) or failed
    stages: dict[str, dict[str, Any]]   #: stage -> {status, elapsed_s, error}
    error: str | None = None            #: the first failing stage's one-line error

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "folder": self.folder, "status": self.status, "error": self.error,
                "stages": self.stages}


@dataclass
class BatchResult:
    manifest: str
    out: str
    sequences: list[SequenceResult]
    models: dict[str, dict[str, Any]]   #: model unit -> {status, elapsed_s, error}
    counts: dict[str, int]              #: stage runs by status: ok, skipped, failed, blocked
    elapsed_s: float
    config: BatchConfig = field(default_factory=BatchConfig)
    scheduler: str | None = None        #: the address used (null: no cluster was needed)

    @property
    def failed(self) -> list[SequenceResult]:
        return [s for s in self.sequences if s.status != "ok"]

    def to_json(self) -> dict[str, Any]:
        return {"manifest": self.manifest, "out": self.out, "sequences": [s.to_json() for s in self.sequences],
                "sequences_ok": len(self.sequences) - len(self.failed), "sequences_failed": len(self.failed),
                "models": self.models, "stage_counts": self.counts, "scheduler": self.scheduler,
                "elapsed_s": self.elapsed_s, "config": self.config.to_dict()}


def connect(cfg: BatchConfig):
    """A dask ``Client``: to ``cfg.scheduler``, or to a new ``LocalCluster`` of ``cfg.workers`` processes."""
    from dask.distributed import Client, LocalCluster

    if cfg.scheduler is not None:
        _probe(cfg.scheduler, cfg.connect_timeout_s)
        try:
            return Client(cfg.scheduler, timeout=cfg.connect_timeout_s)
        except (OSError, TimeoutError, ValueError) as e:
            why = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise SchedulerError(f"cannot reach the dask scheduler at {cfg.scheduler} "
                                 f"(within {cfg.connect_timeout_s:g} s): {why}") from None
    # numba's thread pool sized to the worker's threads before the worker imports numba (its default
    # is every core: N workers on N cores would each start N threads; set_num_threads in the task
    # cannot shrink a pool already launched). 100M-point c2m on 2 cores: 1.56x -> 1.76x for 2 workers
    cluster = LocalCluster(n_workers=cfg.workers, threads_per_worker=cfg.threads_per_worker, processes=True,
                           dashboard_address=None, silence_logs=logging.ERROR,
                           env={"NUMBA_NUM_THREADS": str(max(1, int(cfg.threads_per_worker)))})
    return Client(cluster)


def _probe(address: str, timeout_s: float) -> None:
    """A refused or unresolvable ``tcp://host:port`` fails at once (dask's own connect retries until its
    timeout); anything else (other protocols, a slow network) is left to dask."""
    import socket
    from urllib.parse import urlsplit

    try:
        u = urlsplit(address if "://" in address else f"tcp://{address}")
        host, port = u.hostname, u.port
    except ValueError:
        return
    if u.scheme != "tcp" or not host or port is None:
        return
    try:
        socket.create_connection((host, port), timeout=min(timeout_s, 5.0)).close()
    except (ConnectionRefusedError, socket.gaierror) as e:
        raise SchedulerError(f"cannot reach the dask scheduler at {address} (within {timeout_s:g} s): "
                             f"{e.strerror or e}") from None
    except OSError:
        return


def close_client(client) -> None:
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()


def _plan_pass(plan: list[Stage], states: dict[str, dict], retry_failed: bool) -> dict[str, dict[str, Any]]:
    """Results known without a task: stages fresh now (skipped) or failed before with the same inputs,
    whose predecessors are all fresh, and the stages these block."""
    done: dict[str, dict[str, Any]] = {}
    for st in plan:
        if not all(d in done for d in st.deps):
            continue
        bad = [done[d] for d in st.deps if done[d]["status"] in ("failed", "blocked")]
        if bad:
            done[st.id] = _result(st, "blocked", error=bad[0]["error"], cause=bad[0]["id"])
            continue
        known = known_outcome(st, states[st.folder]["stages"].get(st.name), retry_failed)
        if known is not None:
            done[st.id] = known
    return done


def _record(res: dict[str, Any], st: Stage, states: dict[str, dict]) -> None:
    if res["status"] in ("ok", "failed") and res.get("entry") is not None and not res.get("cached"):
        states[st.folder]["stages"][st.name] = res["entry"]
        save_state(Path(st.folder), states[st.folder])


def _submit(client, plan: list[Stage], done: dict, states: dict, retry_failed: bool, call) -> dict[str, Any]:
    futures: dict[str, Any] = {}
    for st in plan:
        if st.id in done:
            continue
        ups = [futures.get(d, done.get(d)) for d in st.deps]
        entry = states[st.folder]["stages"].get(st.name)
        futures[st.id] = client.submit(run_stage, st, entry, retry_failed, call, *ups, key=f"{st.name}:{st.unit}-{time.time_ns()}",
                                       pure=False, retries=0)
    return futures


def run_batch(manifest: Manifest, out: str | Path, call: CallMst, cfg: BatchConfig | None = None,
              on_result: Callable[[Stage, dict[str, Any]], None] | None = None,
              on_plan: Callable[[list[Stage], dict[str, dict[str, Any]]], None] | None = None) -> BatchResult:
    """Run (or resume) every sequence of ``manifest`` into ``out``; see the module docstring.

    ``call`` runs one ``mst`` command line in-process (:data:`~mst.eval.batch.execute.CallMst`; the CLI
    gives :func:`mst.cli.batch.call_mst`). ``on_plan(plan, skipped)`` is called once before any work, ``on_result(stage, result)`` as each
    stage ends (progress display). A failing stage blocks its sequence only.
    """
    cfg = cfg or BatchConfig()
    t0 = time.perf_counter()
    out = Path(out)
    plan = build_plan(manifest, out)
    by_id = {st.id: st for st in plan}
    client = connect(cfg) if cfg.scheduler is not None else None  # an unreachable address: before any write
    try:
        states = {st.folder: load_state(Path(st.folder)) for st in plan}
        done = _plan_pass(plan, states, cfg.retry_failed)
        if on_plan is not None:
            on_plan(plan, done)
        for rid, res in done.items():
            if on_result is not None:
                on_result(by_id[rid], res)
        used = cfg.scheduler
        if len(done) < len(plan):
            for folder in dict.fromkeys(st.folder for st in plan):
                Path(folder).mkdir(parents=True, exist_ok=True)
            if client is None:
                client = connect(cfg)
                used = "LocalCluster"
            from dask.distributed import as_completed

            futures = _submit(client, plan, done, states, cfg.retry_failed, call)
            id_of = {f.key: i for i, f in futures.items()}
            for fut in as_completed(list(futures.values())):
                st = by_id[id_of[fut.key]]
                try:
                    res = fut.result()
                except Exception as e:  # noqa: BLE001 - a task that could not run (e.g. a worker without mst)
                    res = _result(st, "failed", error=f"mst batch: error: {st.id}: the task failed on its "
                                                      f"worker: {type(e).__name__}: {e}".replace("\n", " "))
                _record(res, st, states)
                done[st.id] = res
                if on_result is not None:
                    on_result(st, res)
    finally:
        if client is not None:
            close_client(client)
    return _summarise(manifest, out, plan, done, cfg, used, time.perf_counter() - t0)


def _summarise(manifest: Manifest, out: Path, plan: list[Stage], done: dict[str, dict[str, Any]],
               cfg: BatchConfig, used: str | None, elapsed: float) -> BatchResult:
    counts = dict.fromkeys(("ok", "skipped", "failed", "blocked"), 0)
    for r in done.values():
        counts[r["status"]] += 1
    brief = lambda r: {"status": r["status"], "elapsed_s": round(r["elapsed_s"], 3), "error": r["error"]}  # noqa: E731
    models = {st.unit: brief(done[st.id]) for st in plan if st.name == "convert-model"}
    seqs = []
    for s in manifest.sequences:
        mine = [st for st in plan if st.unit == s.name]
        stages = {st.name: brief(done[st.id]) for st in sorted(mine, key=lambda x: STAGES.index(x.name))}
        model_dep = next((d for st in mine for d in st.deps if d.startswith("models/")), None)
        chain = ([done[model_dep]] if model_dep else []) + [done[st.id] for st in mine]
        err = next((r["error"] for r in chain if r["status"] in ("failed", "blocked")), None)
        seqs.append(SequenceResult(s.name, str((out / s.name).resolve()), "failed" if err else "ok", stages, err))
    return BatchResult(str(manifest.path), str(out.resolve()), seqs, models, counts, round(elapsed, 3), cfg, used)
