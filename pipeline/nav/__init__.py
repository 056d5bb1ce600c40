"""mst.pipeline.nav: navigation logs (GPS/AHRS: read, write, simulate), their fusion with the vision
track (filter + smoother, time offset and lever arm estimation) and the ``mst nav`` runners.

May import mst.core and mst.pipeline's depth/frame helpers; never mst.eval or mst.cli.
"""
