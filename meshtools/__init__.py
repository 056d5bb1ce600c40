"""mst.meshtools: polygon models (model.py), their file formats (formats/), polygon geometry
(polygons.py), TIN -> polygon conversion (convert.py) and procedural test meshes (generate.py).

May import numpy, numba (mst.meshtools.kernels), scipy, mapbox_earcut, trimesh (lazily), :mod:`mst` and :mod:`mst.core`; never
:mod:`mst.pipeline`, :mod:`mst.eval` or :mod:`mst.cli`.
"""
