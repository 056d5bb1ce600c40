"""Local dask workers for the tests: forked from a fork server that imported the stages' libraries once
(a clean single-threaded process), so a test pays for its tasks, not for fresh interpreters' imports."""

from __future__ import annotations

from contextlib import contextmanager

#: imported once by the fork server (missing modules are skipped by multiprocessing)
PRELOAD = ["distributed", "mst.cli.main", "mst.cli.batch", "mst.eval.batch.execute", "cv2", "numba", "scipy.spatial",
           "matplotlib.pyplot", "mst.pipeline.tracking.runner", "mst.pipeline.fusion", "mst.eval.c2m",
           "mst.eval.c2m.tiles", "mst.eval.traj", "mst.eval.plots", "mst.meshtools.convert", "mst.pipeline.init_pose",
           "mst.pipeline.slam", "laspy"]


@contextmanager
def fast_local_workers():
    """Inside: LocalCluster workers start from the preloaded fork server."""
    import dask
    from distributed.utils import get_mp_context

    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        get_mp_context().set_forkserver_preload(PRELOAD)
        yield
