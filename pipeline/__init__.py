"""mst.pipeline: the stage cores between a model and a video: rendering and visibility, moving
edges, pose optimisation, tracking, SLAM, depth fusion, synthetic sequences, navigation fusion.

May import mst.core and mst.meshtools; never mst.eval or mst.cli.
"""
