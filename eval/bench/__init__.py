"""mst.eval.bench: the speed and memory benchmarks of ``make bench`` (``python -m mst.eval.bench``).

Holds the harness (``harness``: timing children, the table, the JSON report) and one module per stage
(convert, c2m, synth, track, slam, fuse, nav, uav), each with ``run(workdir) -> list[dict]`` rows.
May import any public mst API (the product never imports this package) and the test helpers of tests/.
"""
