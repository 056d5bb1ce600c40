"""mst.eval: how well cloud, model and trajectory agree (cloud-to-mesh, trajectory metrics,
navigation tables, plots, reports); the benchmarks live apart in :mod:`mst.eval.bench`.

May import mst.core, mst.meshtools and mst.pipeline; never mst.cli. Only the benchmarks import
the benchmarks.
"""
