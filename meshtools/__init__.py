"""mst.meshtools: 3D model I/O (OBJ, PLY, VRML, ViSP .cao, CityJSON, ...), TIN to polygon
conversion, and generated test models.

May import mst.core (and mst.errors); never mst.pipeline, mst.eval or mst.cli.
"""
