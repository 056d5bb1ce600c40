"""mst.eval: how well cloud, model and trajectory agree: ``c2m/`` (cloud-to-mesh), ``traj/`` (trajectory
metrics, the UAV table against nav logs), ``plots``, ``cloud_io``; the benchmarks live apart in :mod:`mst.eval.bench`.

May import mst.core, mst.meshtools and mst.pipeline; never mst.cli. Only the benchmarks import
the benchmarks.
"""
