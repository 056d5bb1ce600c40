"""``BatchConfig``: the settings of ``mst batch`` on :mod:`mst.core.config`."""

from __future__ import annotations

from dataclasses import dataclass

from mst.core.config import Config, param


@dataclass
class BatchConfig(Config):
    """Settings of the batch runner (``mst batch``)."""

    workers: int = param(2, min=1, max=512, help="worker processes of the LocalCluster (ignored with scheduler)")
    threads_per_worker: int = param(1, min=1, max=64,
                                    help="tasks run at once per local worker (1: the stages' own threads do the rest)")
    scheduler: str | None = param(None, help="address of a running dask scheduler (tcp://host:8786); "
                                             "null: a LocalCluster on this machine")
    connect_timeout_s: float = param(10.0, min=0, min_open=True, max=3600,
                                     help="how long to wait for the scheduler before giving up, s")
    retry_failed: bool = param(False, help="run again a stage that failed with the same command line and inputs "
                                           "(default: report its recorded error without running it)")
