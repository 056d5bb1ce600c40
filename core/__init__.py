"""mst.core: the foundation every stage shares: camera and projection, rigid poses, the KLT front
end, file formats (PLY, trajectories) and the configuration system.

May import numpy, OpenCV, the standard library and :mod:`mst.errors` only; never
:mod:`mst.pipeline`, :mod:`mst.meshtools`, :mod:`mst.eval` or :mod:`mst.cli` (they import it).
"""
